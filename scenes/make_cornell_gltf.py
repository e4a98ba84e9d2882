#!/usr/bin/env python3
"""Writes cornell-box.gltf next to this script: the same scene as `builtin:cornell-box`
(crates/tessera-scene/src/builtin.rs, `cornell_box()`), as pure glTF 2.0.

- Geometry in metres, the same coordinates, triangles and winding as builtin.rs (one mesh
  per builtin mesh group; the two blocks are one primitive each).
- Albedos as baseColorFactor with metallicFactor 0 and roughnessFactor 1 (a rough
  dielectric; the builtin uses a Lambertian material instead).
- The light: emissiveFactor (1, 12/17, 4/17) x KHR_materials_emissive_strength 17 =
  radiance (17, 12, 4) W/(m^2 sr), one-sided, facing down.
- The camera: a node at (0.278, 0.273, -0.8) rotated 180 degrees about +Y (glTF cameras
  look down -Z, so it looks along +Z), yfov 39.3077 degrees, aspectRatio 1.

Run: python3 scenes/make_cornell_gltf.py (standard library only).
"""

import math
import os
import sys

sys.dont_write_bytecode = True  # keep scenes/ free of __pycache__
from gltf_writer import Gltf, f32  # noqa: E402

X1, Y1, Z1 = 0.5528, 0.5488, 0.5592


def quad(a, b, c, d):
    """A quad a b c d (counter-clockwise seen from the front) as two triangles."""
    return [a, b, c, d], [0, 1, 2, 0, 2, 3]


def block(top, height):
    """builtin.rs `block`: top face at `height` plus four sides down to y = 0."""

    def t(i):
        return (top[i][0], height, top[i][1])

    def b(i):
        return (top[i][0], 0.0, top[i][1])

    # Orient the top face upward: counter-clockwise seen from +y (same f32 test as Rust).
    e1 = [f32(f32(t(1)[k]) - f32(t(0)[k])) for k in range(3)]
    e2 = [f32(f32(t(2)[k]) - f32(t(0)[k])) for k in range(3)]
    ny = e1[2] * e2[0] - e1[0] * e2[2]
    order = [0, 1, 2, 3] if ny > 0 else [3, 2, 1, 0]
    quads = [quad(t(order[0]), t(order[1]), t(order[2]), t(order[3]))]
    for k in range(4):
        i, j = order[k], order[(k + 1) % 4]
        quads.append(quad(b(i), b(j), t(j), t(i)))
    return quads


def merge(quads):
    positions, indices = [], []
    for p, idx in quads:
        base = len(positions)
        positions += p
        indices += [base + i for i in idx]
    return positions, indices


def main():
    g = Gltf("scenes/make_cornell_gltf.py")
    g.uses("KHR_materials_emissive_strength")

    def rough(name, rgb):
        return g.material(
            {
                "name": name,
                "pbrMetallicRoughness": {
                    "baseColorFactor": list(rgb) + [1.0],
                    "metallicFactor": 0.0,
                    "roughnessFactor": 1.0,
                },
            }
        )

    white = rough("white", (0.725, 0.71, 0.68))
    red = rough("red", (0.63, 0.065, 0.05))
    green = rough("green", (0.14, 0.45, 0.091))
    light = g.material(
        {
            "name": "light",
            "pbrMetallicRoughness": {
                "baseColorFactor": [0.78, 0.78, 0.78, 1.0],
                "metallicFactor": 0.0,
                "roughnessFactor": 1.0,
            },
            "emissiveFactor": [1.0, 12.0 / 17.0, 4.0 / 17.0],
            "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 17.0}},
        }
    )

    x1, y1, z1 = X1, Y1, Z1
    # builtin.rs computes y1 - 0.001 in f32.
    yl = f32(f32(y1) - f32(0.001))
    objects = [
        ("floor", white, [quad((0, 0, 0), (0, 0, z1), (x1, 0, z1), (x1, 0, 0))]),
        ("ceiling", white, [quad((0, y1, 0), (x1, y1, 0), (x1, y1, z1), (0, y1, z1))]),
        ("back", white, [quad((0, 0, z1), (0, y1, z1), (x1, y1, z1), (x1, 0, z1))]),
        ("red-wall", red, [quad((x1, 0, 0), (x1, 0, z1), (x1, y1, z1), (x1, y1, 0))]),
        ("green-wall", green, [quad((0, 0, 0), (0, y1, 0), (0, y1, z1), (0, 0, z1))]),
        (
            "light",
            light,
            [quad((0.343, yl, 0.227), (0.343, yl, 0.332), (0.213, yl, 0.332), (0.213, yl, 0.227))],
        ),
        (
            "short-block",
            white,
            block([[0.130, 0.065], [0.082, 0.225], [0.240, 0.272], [0.290, 0.114]], 0.165),
        ),
        (
            "tall-block",
            white,
            block([[0.423, 0.247], [0.265, 0.296], [0.314, 0.456], [0.472, 0.406]], 0.330),
        ),
    ]
    for name, material, quads in objects:
        positions, indices = merge(quads)
        mesh = g.mesh(name, positions, indices, material)
        g.node({"name": name, "mesh": mesh})

    camera = g.camera(
        {
            "name": "camera",
            "type": "perspective",
            "perspective": {
                "yfov": math.radians(39.3077),
                "aspectRatio": 1.0,
                "znear": 0.01,
            },
        }
    )
    g.node(
        {
            "name": "camera",
            "camera": camera,
            "translation": [0.278, 0.273, -0.8],
            "rotation": [0.0, 1.0, 0.0, 0.0],
        }
    )
    g.write(os.path.join(os.path.dirname(os.path.abspath(__file__)), "cornell-box.gltf"))


if __name__ == "__main__":
    main()
