#!/usr/bin/env python3
"""Writes mirror-caustic.gltf next to this script: a point light's caustic under a glass
ball, seen only in a mirror (`L S S D S E`, the issue's "caustic from a point light seen in
a mirror").

- Floor: 12 m x 12 m at y = 0, facing up; base colour 0.8, metallic 0, roughness 1.
- Glass ball: a UV sphere of radius 0.4 (48 segments x 24 rings, smooth normals) centred at
  (0, 1, 3.5), floating; KHR_materials_transmission 1, KHR_materials_ior 1.5. It focuses
  the light onto the floor below it.
- Point light (KHR_lights_punctual) at (0, 3, 3.5), 2 m above the ball's centre:
  intensity 6830 cd (= 10 W/sr at 683 lm/W).
- Mirror: a 6 m x 3 m quad in the plane z = -2 facing +z (y from 0 to 3), base colour 1,
  metallic 1, roughness 0 (a perfect mirror).
- Camera "main" at (0, 1, 2) looking at (0, 0.3, -2), yfov 35 degrees, aspect 4:3: it
  faces the mirror with the ball and its caustic behind it, so it sees the floor in front
  of it directly (lit by the point light: `L D E`) and the caustic only in the mirror.

Run: python3 scenes/make_mirror_caustic_gltf.py (standard library only).
"""

import os
import sys

sys.dont_write_bytecode = True  # keep scenes/ free of __pycache__
from gltf_writer import Gltf, uv_sphere  # noqa: E402


def main():
    g = Gltf("scenes/make_mirror_caustic_gltf.py")
    floor = g.material(
        {
            "name": "floor",
            "pbrMetallicRoughness": {
                "baseColorFactor": [0.8, 0.8, 0.8, 1.0],
                "metallicFactor": 0.0,
                "roughnessFactor": 1.0,
            },
        }
    )
    glass = g.smooth_glass("glass", 1.5)
    mirror = g.material(
        {
            "name": "mirror",
            "pbrMetallicRoughness": {
                "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                "metallicFactor": 1.0,
                "roughnessFactor": 0.0,
            },
        }
    )
    floor_mesh = g.mesh(
        "floor",
        [(-6.0, 0.0, -6.0), (-6.0, 0.0, 6.0), (6.0, 0.0, 6.0), (6.0, 0.0, -6.0)],
        [0, 1, 2, 0, 2, 3],
        floor,
        normals=[(0.0, 1.0, 0.0)] * 4,
    )
    g.node({"name": "floor", "mesh": floor_mesh})
    mirror_mesh = g.mesh(
        "mirror",
        [(-3.0, 0.0, -2.0), (3.0, 0.0, -2.0), (3.0, 3.0, -2.0), (-3.0, 3.0, -2.0)],
        [0, 1, 2, 0, 2, 3],
        mirror,
        normals=[(0.0, 0.0, 1.0)] * 4,
    )
    g.node({"name": "mirror", "mesh": mirror_mesh})
    positions, normals, indices = uv_sphere(0.4, 48, 24)
    ball = g.mesh("glass-ball", positions, indices, glass, normals=normals)
    g.node({"name": "glass-ball", "mesh": ball, "translation": [0.0, 1.0, 3.5]})
    light = g.light(
        {"name": "lamp", "type": "point", "color": [1.0, 1.0, 1.0], "intensity": 6830.0}
    )
    g.node(
        {
            "name": "lamp",
            "translation": [0.0, 3.0, 3.5],
            "extensions": {"KHR_lights_punctual": {"light": light}},
        }
    )
    g.look_at_camera([0.0, 1.0, 2.0], [0.0, 0.3, -2.0], 35.0, 4.0 / 3.0)
    g.write(os.path.join(os.path.dirname(os.path.abspath(__file__)), "mirror-caustic.gltf"))


if __name__ == "__main__":
    main()
