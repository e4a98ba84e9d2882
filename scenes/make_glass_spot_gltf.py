#!/usr/bin/env python3
"""Writes glass-spot.gltf next to this script: a smooth glass ball lit by a spot light.

- Floor: 10 m x 10 m at y = 0, facing up; base colour 0.8, metallic 0, roughness 1.
- Glass ball: a UV sphere of radius 0.5 (48 segments x 24 rings, smooth normals) resting on
  the floor at the origin (node translation (0, 0.5, 0)); base colour 1, metallic 0,
  roughness 0, KHR_materials_transmission 1, KHR_materials_ior 1.5.
- Spot light (KHR_lights_punctual) 3 m above the ball pointing straight down (node rotated
  -90 degrees about X, since lights shine along their local -Z): intensity 6830 cd
  (= 10 W/sr at 683 lm/W), inner cone 0.25 rad, outer cone 0.4 rad.
- Camera "main" at (0, 1.6, 4) looking at (0, 0.4, 0), yfov 40 degrees, aspect 4:3.

Run: python3 scenes/make_glass_spot_gltf.py (standard library only).
"""

import math
import os
import sys

sys.dont_write_bytecode = True  # keep scenes/ free of __pycache__
from gltf_writer import Gltf, uv_sphere  # noqa: E402


def main():
    g = Gltf("scenes/make_glass_spot_gltf.py")
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
    glass = g.smooth_glass()
    floor_mesh = g.mesh(
        "floor",
        [(-5.0, 0.0, -5.0), (-5.0, 0.0, 5.0), (5.0, 0.0, 5.0), (5.0, 0.0, -5.0)],
        [0, 1, 2, 0, 2, 3],
        floor,
        normals=[(0.0, 1.0, 0.0)] * 4,
    )
    g.node({"name": "floor", "mesh": floor_mesh})
    positions, normals, indices = uv_sphere(0.5, 48, 24)
    ball = g.mesh("glass-ball", positions, indices, glass, normals=normals)
    g.node({"name": "glass-ball", "mesh": ball, "translation": [0.0, 0.5, 0.0]})

    spot = g.light(
        {
            "name": "spot",
            "type": "spot",
            "color": [1.0, 1.0, 1.0],
            "intensity": 6830.0,
            "spot": {"innerConeAngle": 0.25, "outerConeAngle": 0.4},
        }
    )
    s = math.sqrt(0.5)
    g.node(
        {
            "name": "spot",
            "translation": [0.0, 3.0, 0.0],
            "rotation": [-s, 0.0, 0.0, s],
            "extensions": {"KHR_lights_punctual": {"light": spot}},
        }
    )

    g.look_at_camera([0.0, 1.6, 4.0], [0.0, 0.4, 0.0], 40.0, 4.0 / 3.0)
    g.write(os.path.join(os.path.dirname(os.path.abspath(__file__)), "glass-spot.gltf"))


if __name__ == "__main__":
    main()
