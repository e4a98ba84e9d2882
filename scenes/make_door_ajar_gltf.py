#!/usr/bin/env python3
"""Writes door-ajar.gltf next to this script: Veach's "door ajar" (Veach 1997, section
11.5, figure 11.4): a room lit only through a door left slightly open, by a lamp in the
next room. The scene of docs/rendering.md ("mlt").

- Two rooms in one box x in [-4, 4], y in [0, 2.5], z in [0, 3] (walls, floor and ceiling
  diffuse, base colour 0.7), split at x = 0 by a partition wall (diffuse 0.7) with a door
  opening z in [1.0, 1.9], y in [0, 2.0].
- The door (diffuse 0.6), 0.9 m wide and 2 m high, hinged at z = 1.0 and opened 4 degrees
  into the far room (x < 0): its free edge stands 6 cm from the frame, the only way light
  gets into the near room.
- Point light (KHR_lights_punctual) in the far room at (-3.0, 1.6, 2.0), behind the
  partition as seen from the gap: intensity 683 cd (= 1 W/sr at 683 lm/W).
- Camera "main" in the near room at (3.8, 1.3, 0.6) looking at (0, 0.8, 1.6), yfov 55
  degrees, aspect 1: it sees the partition, the door and the floor; everything it sees is
  lit by light that came through the gap, mostly after bouncing in the far room.

Path tracing finds that light only when a path bounces through the gap and then sees
the lamp; Metropolis light transport, once a chain has found such a path, explores its
neighbours (crates/tessera-render/tests/it/mlt.rs renders it; docs/benchmarks.md has the
efficiencies).

Run: python3 scenes/make_door_ajar_gltf.py (standard library only).
"""

import math
import os
import sys

sys.dont_write_bytecode = True  # keep scenes/ free of __pycache__
from gltf_writer import Gltf  # noqa: E402


def quad(g, name, corners, material):
    """One two-triangle quad with its geometric normal (corners counter-clockwise seen
    from the side the normal points to)."""
    a, b, c = corners[0], corners[1], corners[2]
    u = [b[i] - a[i] for i in range(3)]
    v = [c[i] - a[i] for i in range(3)]
    n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]
    length = math.sqrt(sum(x * x for x in n))
    n = [x / length for x in n]
    mesh = g.mesh(name, corners, [0, 1, 2, 0, 2, 3], material, normals=[n] * 4)
    g.node({"name": name, "mesh": mesh})


def diffuse(g, name, albedo):
    return g.material(
        {
            "name": name,
            "pbrMetallicRoughness": {
                "baseColorFactor": [albedo, albedo, albedo, 1.0],
                "metallicFactor": 0.0,
                "roughnessFactor": 1.0,
            },
        }
    )


def main():
    g = Gltf("scenes/make_door_ajar_gltf.py")
    wall = diffuse(g, "wall", 0.7)
    door = diffuse(g, "door", 0.6)
    x0, x1, h, d = -4.0, 4.0, 2.5, 3.0
    # The box, normals inward.
    quad(g, "floor", [(x0, 0, 0), (x0, 0, d), (x1, 0, d), (x1, 0, 0)], wall)
    quad(g, "ceiling", [(x0, h, 0), (x1, h, 0), (x1, h, d), (x0, h, d)], wall)
    quad(g, "back", [(x0, 0, 0), (x1, 0, 0), (x1, h, 0), (x0, h, 0)], wall)
    quad(g, "front", [(x0, 0, d), (x0, h, d), (x1, h, d), (x1, 0, d)], wall)
    quad(g, "far-end", [(x0, 0, 0), (x0, h, 0), (x0, h, d), (x0, 0, d)], wall)
    quad(g, "near-end", [(x1, 0, 0), (x1, 0, d), (x1, h, d), (x1, h, 0)], wall)
    # The partition at x = 0 around the opening z in [z0, z1], y < yd; normals toward
    # the near room (surfaces scatter on both sides).
    z0, z1, yd = 1.0, 1.9, 2.0
    quad(g, "partition-left", [(0, 0, 0), (0, h, 0), (0, h, z0), (0, 0, z0)], wall)
    quad(g, "partition-right", [(0, 0, z1), (0, h, z1), (0, h, d), (0, 0, d)], wall)
    quad(g, "partition-top", [(0, yd, z0), (0, h, z0), (0, h, z1), (0, yd, z1)], wall)
    # The door: hinged at (0, z0), opened by `angle` into the far room.
    angle = math.radians(4.0)
    w = z1 - z0
    ex, ez = -w * math.sin(angle), z0 + w * math.cos(angle)
    quad(g, "door", [(0, 0, z0), (0, yd, z0), (ex, yd, ez), (ex, 0, ez)], door)
    light = g.light(
        {"name": "lamp", "type": "point", "color": [1.0, 1.0, 1.0], "intensity": 683.0}
    )
    g.node(
        {
            "name": "lamp",
            "translation": [-3.0, 1.6, 2.0],
            "extensions": {"KHR_lights_punctual": {"light": light}},
        }
    )
    g.look_at_camera([3.8, 1.3, 0.6], [0.0, 0.8, 1.6], 55.0, 1.0)
    g.write(os.path.join(os.path.dirname(os.path.abspath(__file__)), "door-ajar.gltf"))


if __name__ == "__main__":
    main()
