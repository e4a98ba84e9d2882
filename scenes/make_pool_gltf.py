#!/usr/bin/env python3
"""Writes pool.gltf next to this script: a pool floor seen through flat water under a
point light, the `L S D S E` scene of docs/rendering.md ("vcm").

- Floor: 4 m x 4 m at y = 0, facing up; base colour 0.8, metallic 0, roughness 1.
- Water surface: 4 m x 4 m at y = 0.5, facing up; smooth, KHR_materials_transmission 1,
  KHR_materials_ior 1.33.
- Point light (KHR_lights_punctual) 1 m above the water and 1 m to the side, at
  (1, 1.5, 0): intensity 6830 cd (= 10 W/sr at 683 lm/W).
- Camera "main" 2 m above the water at (0, 2.5, 0.05) looking at the floor's centre,
  yfov 20 degrees, aspect 1: the floor is seen only through the water, and the light's
  mirror image in the water is outside the view.

Light reaches the camera only as light -> water -> floor -> water -> camera: path tracing
and bdpt render the floor black (crates/tessera-render/tests/it/vcm.rs has the same scene
with its closed form).

Run: python3 scenes/make_pool_gltf.py (standard library only).
"""

import os
import sys

sys.dont_write_bytecode = True  # keep scenes/ free of __pycache__
from gltf_writer import Gltf  # noqa: E402


def main():
    g = Gltf("scenes/make_pool_gltf.py")
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
    water = g.smooth_glass("water", 1.33)
    for name, y, material in [("floor", 0.0, floor), ("water", 0.5, water)]:
        mesh = g.mesh(
            name,
            [(-2.0, y, -2.0), (-2.0, y, 2.0), (2.0, y, 2.0), (2.0, y, -2.0)],
            [0, 1, 2, 0, 2, 3],
            material,
            normals=[(0.0, 1.0, 0.0)] * 4,
        )
        g.node({"name": name, "mesh": mesh})
    light = g.light(
        {"name": "lamp", "type": "point", "color": [1.0, 1.0, 1.0], "intensity": 6830.0}
    )
    g.node(
        {
            "name": "lamp",
            "translation": [1.0, 1.5, 0.0],
            "extensions": {"KHR_lights_punctual": {"light": light}},
        }
    )
    g.look_at_camera([0.0, 2.5, 0.05], [0.0, 0.0, 0.0], 20.0, 1.0)
    g.write(os.path.join(os.path.dirname(os.path.abspath(__file__)), "pool.gltf"))


if __name__ == "__main__":
    main()
