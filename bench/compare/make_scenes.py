#!/usr/bin/env python3
"""Writes the comparison scenes that are not in scenes/ into bench/compare/scenes/
(generated, not committed: the Veach scene's sphere meshes make a 2 MB file).

- veach-mis.gltf: Veach & Guibas 1995, section 4.1 (figure 5), as glTF 2.0: four glossy
  metallic plates (roughness 0.443, 0.285, 0.178, 0.107: the GGX equivalents of the
  builtin's Phong exponents 50, 300, 2000, 15000, alpha = sqrt(2 / (n + 2)) and
  roughness = sqrt(alpha)), a dark diffuse floor and back wall, and four emissive UV
  spheres (radii 0.9, 0.3, 0.1, 0.0333, radiance 1 / r^2, 96 x 48 each: 36,480 emissive
  triangles), the geometry of `builtin:veach-mis`.
- glass-area.gltf: a smooth glass ball (ior 1.5) on a diffuse floor under a small square
  area light (0.2 m, 1.5 m above the ball, radiance 250): a caustic seen through glass.

- large.glb: 2,000,000 triangles of displaced terrain under a square area light (item 6 of
  build time, memory and speed on a large mesh).
- cornell-box.gltf: scenes/cornell-box.gltf with Lambertian walls (see `cornell_lambert`).

Run: python3 bench/compare/make_scenes.py (standard library only).
"""

import json
import math
import os
import struct
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.dont_write_bytecode = True
sys.path.insert(0, os.path.join(HERE, "..", "..", "scenes"))
from gltf_writer import Gltf, look_at_rotation, uv_sphere  # noqa: E402


def diffuse(g, name, albedo):
    """A Lambertian material: a dielectric with KHR_materials_specular's factor 0 has no
    specular layer (every renderer here reads that as pure diffuse)."""
    g.uses("KHR_materials_specular")
    return g.material(
        {
            "name": name,
            "pbrMetallicRoughness": {
                "baseColorFactor": [albedo, albedo, albedo, 1.0],
                "metallicFactor": 0.0,
                "roughnessFactor": 1.0,
            },
            "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}},
        }
    )


def quad(g, name, material, a, b, c, d, normal):
    mesh = g.mesh(name, [a, b, c, d], [0, 1, 2, 0, 2, 3], material, normals=[normal] * 4)
    # Wind counter-clockwise about the normal.
    e1 = [b[i] - a[i] for i in range(3)]
    e2 = [c[i] - a[i] for i in range(3)]
    n = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]]
    if sum(n[i] * normal[i] for i in range(3)) < 0:
        g.doc["meshes"][mesh]["primitives"][0]["indices"] = g.index_accessor([0, 2, 1, 0, 3, 2])
    g.node({"name": name, "mesh": mesh})


def normalize(v):
    n = math.sqrt(sum(c * c for c in v))
    return [c / n for c in v]


def veach(path):
    g = Gltf("bench/compare/make_scenes.py")
    eye = [0.0, 2.0, 15.0]
    floor = diffuse(g, "floor", 0.1)
    for i, (r, x) in enumerate(zip([0.9, 0.3, 0.1, 0.0333], [-3.75, -1.25, 1.25, 3.75])):
        m = g.emissive("light%d" % i, 1.0 / (r * r))
        positions, normals, indices = uv_sphere(r, 96, 48)
        mesh = g.mesh("light%d" % i, positions, indices, m, normals=normals)
        g.node({"name": "light%d" % i, "mesh": mesh, "translation": [x, 0.0, 0.0]})
    centers = [[0.0, -1.10, 1.0], [0.0, -1.91, 2.2], [0.0, -2.57, 3.4], [0.0, -3.07, 4.6]]
    for k, (c, n) in enumerate(zip(centers, [50.0, 300.0, 2000.0, 15000.0])):
        roughness = math.sqrt(math.sqrt(2.0 / (n + 2.0)))
        m = g.material(
            {
                "name": "plate%d" % k,
                "pbrMetallicRoughness": {
                    "baseColorFactor": [0.75, 0.75, 0.75, 1.0],
                    "metallicFactor": 1.0,
                    "roughnessFactor": roughness,
                },
            }
        )
        to_eye = normalize([eye[i] - c[i] for i in range(3)])
        to_row = normalize([-c[i] for i in range(3)])
        normal = normalize([to_eye[i] + to_row[i] for i in range(3)])
        along = [1.0, 0.0, 0.0]
        across = normalize([normal[1] * along[2] - normal[2] * along[1],
                            normal[2] * along[0] - normal[0] * along[2],
                            normal[0] * along[1] - normal[1] * along[0]])
        across = [0.75 * a for a in across]
        pts = [[c[i] + sa * 4.0 * along[i] + sb * across[i] for i in range(3)]
               for sa, sb in [(-1, -1), (1, -1), (1, 1), (-1, 1)]]
        quad(g, "plate%d" % k, m, *pts, normal)
    quad(g, "floor", floor, [-10, -4, -4], [-10, -4, 12], [10, -4, 12], [10, -4, -4], [0, 1, 0])
    quad(g, "back", floor, [-10, -4, -4], [10, -4, -4], [10, 8, -4], [-10, 8, -4], [0, 0, 1])
    g.look_at_camera(eye, [0.0, -2.0, 2.5], 28.0, 1.5)
    g.write(path)


def glass_area(path):
    g = Gltf("bench/compare/make_scenes.py")
    floor = diffuse(g, "floor", 0.8)
    glass = g.smooth_glass()
    quad(g, "floor", floor, [-5, 0, -5], [-5, 0, 5], [5, 0, 5], [5, 0, -5], [0, 1, 0])
    positions, normals, indices = uv_sphere(0.5, 64, 32)
    ball = g.mesh("glass-ball", positions, indices, glass, normals=normals)
    g.node({"name": "glass-ball", "mesh": ball, "translation": [0.0, 0.5, 0.0]})
    light = g.emissive("light", 250.0)
    h, y = 0.1, 2.5
    quad(g, "light", light, [-h, y, -h], [h, y, -h], [h, y, h], [-h, y, h], [0, -1, 0])
    g.look_at_camera([0.0, 1.6, 4.0], [0.0, 0.4, 0.0], 40.0, 4.0 / 3.0)
    g.write(path)


def cornell_lambert(path):
    """scenes/cornell-box.gltf with Lambertian walls and blocks (the builtin's materials):
    KHR_materials_specular with factor 0 on every non-emissive material."""
    with open(os.path.join(HERE, "..", "..", "scenes", "cornell-box.gltf"), encoding="utf-8") as f:
        doc = json.load(f)
    doc.setdefault("extensionsUsed", []).append("KHR_materials_specular")
    for m in doc["materials"]:
        if not any(m.get("emissiveFactor", [0, 0, 0])):
            m.setdefault("extensions", {})["KHR_materials_specular"] = {"specularFactor": 0.0}
    with open(path, "w", encoding="utf-8") as f:
        json.dump(doc, f)


def large(path, n=1000):
    """A displaced terrain of n x n quads (2 n^2 triangles: 2,000,000 for n = 1000) under a
    square area light, as a binary .glb (numpy; 48 MB), Lambertian (specular factor 0)."""
    import numpy as np

    size = 10.0
    x, z = np.meshgrid(np.linspace(-size / 2, size / 2, n + 1), np.linspace(-size / 2, size / 2, n + 1))
    y = 0.3 * np.sin(3.1 * x) * np.cos(2.3 * z) + 0.1 * np.sin(17.0 * x + 5.0 * z)
    positions = np.stack([x, y, z], axis=-1).reshape(-1, 3).astype("<f4")
    i = np.arange(n)
    a = (i[:, None] * (n + 1) + i[None, :]).ravel()
    b, c, d = a + 1, a + n + 1, a + n + 2
    # Counter-clockwise seen from above (+y).
    indices = np.stack([a, c, b, b, c, d], axis=-1).reshape(-1).astype("<u4")
    light_p = np.array([[-0.5, 4.0, -0.5], [0.5, 4.0, -0.5], [0.5, 4.0, 0.5], [-0.5, 4.0, 0.5]], "<f4")
    light_i = np.array([0, 1, 2, 0, 2, 3], "<u4")
    blobs, views, accessors = [], [], []

    def view(data, target):
        offset = sum(len(x) for x in blobs)
        blobs.append(data.tobytes() + b"\0" * ((-len(data.tobytes())) % 4))
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": data.nbytes, "target": target})
        return len(views) - 1

    def acc(data, kind, component, target, bounds=False):
        a = {"bufferView": view(data, target), "componentType": component, "count": len(data), "type": kind}
        if bounds:
            a["min"] = data.min(axis=0).tolist()
            a["max"] = data.max(axis=0).tolist()
        accessors.append(a)
        return len(accessors) - 1

    terrain = {"attributes": {"POSITION": acc(positions, "VEC3", 5126, 34962, True)},
               "indices": acc(indices, "SCALAR", 5125, 34963), "material": 0}
    lamp = {"attributes": {"POSITION": acc(light_p, "VEC3", 5126, 34962, True)},
            "indices": acc(light_i, "SCALAR", 5125, 34963), "material": 1}
    eye, target = [0.0, 3.0, 6.0], [0.0, 0.0, 0.0]
    doc = {
        "asset": {"version": "2.0", "generator": "bench/compare/make_scenes.py"},
        "extensionsUsed": ["KHR_materials_specular", "KHR_materials_emissive_strength"],
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2]}],
        "nodes": [{"name": "terrain", "mesh": 0}, {"name": "light", "mesh": 1},
                  {"name": "main", "camera": 0, "translation": eye,
                   "rotation": look_at_rotation(eye, target, [0.0, 1.0, 0.0])}],
        "meshes": [{"name": "terrain", "primitives": [terrain]}, {"name": "light", "primitives": [lamp]}],
        "materials": [
            {"name": "ground", "pbrMetallicRoughness": {"baseColorFactor": [0.6, 0.6, 0.6, 1], "metallicFactor": 0.0, "roughnessFactor": 1.0},
             "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}},
            {"name": "light", "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0.0},
             "emissiveFactor": [1.0, 1.0, 1.0], "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 60.0}}},
        ],
        "cameras": [{"type": "perspective", "perspective": {"yfov": math.radians(45.0), "aspectRatio": 1.0, "znear": 0.01}}],
        "accessors": accessors,
        "bufferViews": views,
    }
    binary = b"".join(blobs)
    doc["buffers"] = [{"byteLength": len(binary)}]
    text = json.dumps(doc).encode("utf-8")
    text += b" " * ((-len(text)) % 4)
    with open(path, "wb") as f:
        f.write(b"glTF" + struct.pack("<II", 2, 12 + 8 + len(text) + 8 + len(binary)))
        f.write(struct.pack("<I", len(text)) + b"JSON" + text)
        f.write(struct.pack("<I", len(binary)) + b"BIN\0" + binary)


def main():
    out = os.path.join(HERE, "scenes")
    os.makedirs(out, exist_ok=True)
    cornell_lambert(os.path.join(out, "cornell-box.gltf"))
    veach(os.path.join(out, "veach-mis.gltf"))
    glass_area(os.path.join(out, "glass-area.gltf"))
    large(os.path.join(out, "large.glb"))
    print("wrote", out)


if __name__ == "__main__":
    main()
