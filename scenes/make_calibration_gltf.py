#!/usr/bin/env python3
"""Writes the three glTF scenes of the error-estimate calibration suite (issue 15;
crates/tessera-render/tests/calibration.rs) next to this script. The suite's other three
are `builtin:cornell-box`, `builtin:veach-mis` and `builtin:caustic`.

- glossy-highlight.gltf: a small bright light seen in a glossy reflection. A glossy dielectric
  floor (base colour 0.3, metallic 0, roughness 0.1: a diffuse base under glTF's 4%
  specular layer, like varnished wood; 6 m x 6 m at y = 0) and a diffuse
  back wall (0.6, at z = -1.5), lit only by a small emissive sphere (radius 0.04, 24 x 12
  segments, at (0, 0.5, -0.8), emissive strength 100). The camera at (0, 0.35, 2) looks at
  (0, 0.1, -0.6), yfov 40 degrees, aspect 1: the light's highlight on the floor is a few
  pixels wide, where light sampling and BSDF sampling trade places (Veach & Guibas 1995).
- indirect-room.gltf: a scene lit mostly indirectly. A closed room 4 m x 2.5 m x 4 m
  (walls and ceiling 0.75, floor 0.6, all rough dielectrics facing in) with a 0.6 m cube
  (0.7, 0.3, 0.2) on the floor; the only light is a one-sided 0.8 m x 0.8 m emissive
  quad at y = 2.2 facing up (strength 10), so everything the camera sees below the ceiling
  is lit by light that bounced at least once. Camera at (0, 1, 1.9) looking at
  (0, 0.7, -2), yfov 60 degrees, aspect 1.
- textured-room.gltf: the same room lit by the same quad facing down (strength 6), with
  an 8 x 8 sRGB checker texture (two colours, NEAREST, REPEAT, 4 repeats) on the floor and a
  64 px colour gradient texture (LINEAR) on the back wall.

Run: python3 scenes/make_calibration_gltf.py (standard library only).
"""

import math
import os
import sys

sys.dont_write_bytecode = True  # keep scenes/ free of __pycache__
from gltf_writer import Gltf, uv_sphere  # noqa: E402

NEAREST, LINEAR, LINEAR_MIPMAP_LINEAR, REPEAT = 9728, 9729, 9987, 10497
HERE = os.path.dirname(os.path.abspath(__file__))


def quad_mesh(g, name, material, a, b, c, d, uv_scale=None):
    """The quad a b c d (counter-clockwise seen from its front) as one mesh with flat
    normals, and texture coordinates (0,0) (s,0) (s,s) (0,s) when `uv_scale` = s."""
    e1 = [b[k] - a[k] for k in range(3)]
    e2 = [c[k] - a[k] for k in range(3)]
    n = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]]
    length = math.sqrt(sum(x * x for x in n))
    n = tuple(x / length for x in n)
    uvs = None
    if uv_scale is not None:
        s = uv_scale
        uvs = [(0.0, s), (s, s), (s, 0.0), (0.0, 0.0)]
    mesh = g.mesh(name, [a, b, c, d], [0, 1, 2, 0, 2, 3], material, normals=[n] * 4, uvs=uvs)
    return g.node({"name": name, "mesh": mesh})


def rough(g, name, rgb, texture=None):
    pbr = {"baseColorFactor": list(rgb) + [1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0}
    if texture is not None:
        pbr["baseColorTexture"] = {"index": texture}
    return g.material({"name": name, "pbrMetallicRoughness": pbr})


def glossy_highlight():
    g = Gltf("scenes/make_calibration_gltf.py")
    glossy = g.material(
        {
            "name": "glossy-floor",
            "pbrMetallicRoughness": {
                "baseColorFactor": [0.3, 0.3, 0.3, 1.0],
                "metallicFactor": 0.0,
                "roughnessFactor": 0.1,
            },
        }
    )
    wall = rough(g, "wall", (0.6, 0.6, 0.6))
    quad_mesh(g, "floor", glossy, (-3.0, 0.0, 3.0), (3.0, 0.0, 3.0), (3.0, 0.0, -3.0), (-3.0, 0.0, -3.0))
    quad_mesh(g, "wall", wall, (-3.0, 0.0, -1.5), (3.0, 0.0, -1.5), (3.0, 3.0, -1.5), (-3.0, 3.0, -1.5))
    positions, normals, indices = uv_sphere(0.04, 24, 12)
    light = g.mesh("light", positions, indices, g.emissive("light", 100.0), normals=normals)
    g.node({"name": "light", "mesh": light, "translation": [0.0, 0.5, -0.8]})
    g.look_at_camera([0.0, 0.35, 2.0], [0.0, 0.1, -0.6], 40.0, 1.0)
    g.write(os.path.join(HERE, "glossy-highlight.gltf"))


def room(name, light_up, textured):
    g = Gltf("scenes/make_calibration_gltf.py")
    floor_tex = wall_tex = None
    if textured:
        cells = [(200, 180, 140), (40, 60, 110)]
        checker = [cells[((x // 8) + (y // 8)) % 2] for y in range(64) for x in range(64)]
        floor_tex = g.png_texture(
            "checker", 64, 64, checker,
            {"magFilter": NEAREST, "minFilter": NEAREST, "wrapS": REPEAT, "wrapT": REPEAT},
        )
        gradient = [(4 * x, 255 - 4 * y, 128) for y in range(64) for x in range(64)]
        wall_tex = g.png_texture(
            "gradient", 64, 64, gradient,
            {"magFilter": LINEAR, "minFilter": LINEAR_MIPMAP_LINEAR, "wrapS": REPEAT, "wrapT": REPEAT},
        )
    white = rough(g, "white", (0.75, 0.75, 0.75))
    back = rough(g, "back", (0.75, 0.75, 0.75), wall_tex)
    floor = rough(g, "floor", (0.6, 0.6, 0.6) if floor_tex is None else (1.0, 1.0, 1.0), floor_tex)
    box = rough(g, "box", (0.7, 0.3, 0.2))
    x0, x1, y0, y1, z0, z1 = -2.0, 2.0, 0.0, 2.5, -2.0, 2.0
    # Every face wound counter-clockwise seen from inside the room.
    quad_mesh(g, "floor", floor, (x0, y0, z1), (x1, y0, z1), (x1, y0, z0), (x0, y0, z0),
              uv_scale=4.0 if textured else None)
    quad_mesh(g, "ceiling", white, (x0, y1, z0), (x1, y1, z0), (x1, y1, z1), (x0, y1, z1))
    quad_mesh(g, "back", back, (x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0),
              uv_scale=1.0 if textured else None)
    quad_mesh(g, "front", white, (x1, y0, z1), (x0, y0, z1), (x0, y1, z1), (x1, y1, z1))
    quad_mesh(g, "left", white, (x0, y0, z1), (x0, y0, z0), (x0, y1, z0), (x0, y1, z1))
    quad_mesh(g, "right", white, (x1, y0, z0), (x1, y0, z1), (x1, y1, z1), (x1, y1, z0))
    # The cube, centred at (0.5, 0.3, -0.6), faces wound counter-clockwise from outside.
    cx, cz, h = 0.5, -0.6, 0.3
    a0, a1, b0, b1 = cx - h, cx + h, cz - h, cz + h
    quad_mesh(g, "box-top", box, (a0, 2 * h, b1), (a1, 2 * h, b1), (a1, 2 * h, b0), (a0, 2 * h, b0))
    quad_mesh(g, "box-front", box, (a0, 0.0, b1), (a1, 0.0, b1), (a1, 2 * h, b1), (a0, 2 * h, b1))
    quad_mesh(g, "box-back", box, (a1, 0.0, b0), (a0, 0.0, b0), (a0, 2 * h, b0), (a1, 2 * h, b0))
    quad_mesh(g, "box-left", box, (a0, 0.0, b0), (a0, 0.0, b1), (a0, 2 * h, b1), (a0, 2 * h, b0))
    quad_mesh(g, "box-right", box, (a1, 0.0, b1), (a1, 0.0, b0), (a1, 2 * h, b0), (a1, 2 * h, b1))
    l = 0.4
    if light_up:
        quad_mesh(g, "light", g.emissive("light", 10.0), (-l, 2.2, l), (l, 2.2, l), (l, 2.2, -l), (-l, 2.2, -l))
    else:
        quad_mesh(g, "light", g.emissive("light", 6.0), (-l, 2.45, -l), (l, 2.45, -l), (l, 2.45, l), (-l, 2.45, l))
    g.look_at_camera([0.0, 1.0, 1.9], [0.0, 0.7, -2.0], 60.0, 1.0)
    g.write(os.path.join(HERE, name))


def main():
    glossy_highlight()
    room("indirect-room.gltf", light_up=True, textured=False)
    room("textured-room.gltf", light_up=False, textured=True)


if __name__ == "__main__":
    main()
