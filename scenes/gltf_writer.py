"""Tiny glTF 2.0 writer shared by the scene generators in this directory (standard library
only). It collects meshes, materials, nodes, cameras and lights, packs the binary data into
one buffer and writes a single human-readable .gltf with the buffer embedded as a base64
data: URI.
"""

import base64
import json
import math
import struct
import zlib

FLOAT = 5126
UNSIGNED_SHORT = 5123
UNSIGNED_INT = 5125
ARRAY_BUFFER = 34962
ELEMENT_ARRAY_BUFFER = 34963


def f32(x):
    """Rounds a Python float to the nearest IEEE single, as Rust's `f32` literals are."""
    return struct.unpack("<f", struct.pack("<f", x))[0]


class Gltf:
    def __init__(self, generator):
        self.doc = {
            "asset": {"version": "2.0", "generator": generator},
            "scene": 0,
            "scenes": [{"nodes": []}],
            "nodes": [],
            "meshes": [],
            "materials": [],
            "accessors": [],
            "bufferViews": [],
        }
        self.bin = bytearray()

    def _push(self, key, value):
        self.doc.setdefault(key, []).append(value)
        return len(self.doc[key]) - 1

    def uses(self, extension):
        used = self.doc.setdefault("extensionsUsed", [])
        if extension not in used:
            used.append(extension)

    def _view(self, data, target):
        while len(self.bin) % 4:
            self.bin.append(0)
        offset = len(self.bin)
        self.bin += data
        return self._push(
            "bufferViews",
            {"buffer": 0, "byteOffset": offset, "byteLength": len(data), "target": target},
        )

    def vec3_accessor(self, values, with_bounds):
        data = b"".join(struct.pack("<3f", *v) for v in values)
        acc = {
            "bufferView": self._view(data, ARRAY_BUFFER),
            "componentType": FLOAT,
            "count": len(values),
            "type": "VEC3",
        }
        if with_bounds:
            # The spec requires min/max on POSITION; use the stored (f32) values.
            acc["min"] = [min(f32(v[k]) for v in values) for k in range(3)]
            acc["max"] = [max(f32(v[k]) for v in values) for k in range(3)]
        return self._push("accessors", acc)

    def vec2_accessor(self, values):
        data = b"".join(struct.pack("<2f", *v) for v in values)
        acc = {
            "bufferView": self._view(data, ARRAY_BUFFER),
            "componentType": FLOAT,
            "count": len(values),
            "type": "VEC2",
        }
        return self._push("accessors", acc)

    def png_texture(self, name, width, height, rgb, sampler):
        """An embedded 8-bit sRGB PNG of `width` x `height` pixels (`rgb`: rows top to bottom
        of (r, g, b) bytes) as a texture with the given glTF sampler; returns its index."""
        raw = b"".join(
            b"\x00" + bytes(c for px in rgb[y * width : (y + 1) * width] for c in px)
            for y in range(height)
        )

        def chunk(kind, data):
            body = kind + data
            return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

        png = (
            b"\x89PNG\r\n\x1a\n"
            + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 9))
            + chunk(b"IEND", b"")
        )
        while len(self.bin) % 4:
            self.bin.append(0)
        offset = len(self.bin)
        self.bin += png
        view = self._push(
            "bufferViews", {"buffer": 0, "byteOffset": offset, "byteLength": len(png)}
        )
        image = self._push("images", {"name": name, "bufferView": view, "mimeType": "image/png"})
        s = self._push("samplers", sampler)
        return self._push("textures", {"name": name, "source": image, "sampler": s})

    def index_accessor(self, indices):
        big = max(indices) > 65535
        data = struct.pack("<%d%s" % (len(indices), "I" if big else "H"), *indices)
        return self._push(
            "accessors",
            {
                "bufferView": self._view(data, ELEMENT_ARRAY_BUFFER),
                "componentType": UNSIGNED_INT if big else UNSIGNED_SHORT,
                "count": len(indices),
                "type": "SCALAR",
            },
        )

    def material(self, material):
        return self._push("materials", material)

    def mesh(self, name, positions, indices, material, normals=None, uvs=None):
        attributes = {"POSITION": self.vec3_accessor(positions, True)}
        if normals is not None:
            attributes["NORMAL"] = self.vec3_accessor(normals, False)
        if uvs is not None:
            attributes["TEXCOORD_0"] = self.vec2_accessor(uvs)
        primitive = {
            "attributes": attributes,
            "indices": self.index_accessor(indices),
            "material": material,
        }
        return self._push("meshes", {"name": name, "primitives": [primitive]})

    def smooth_glass(self, name="glass", ior=1.5):
        """A smooth clear dielectric: white base colour, metallic 0, roughness 0,
        KHR_materials_transmission 1 and KHR_materials_ior `ior`."""
        self.uses("KHR_materials_transmission")
        self.uses("KHR_materials_ior")
        return self.material(
            {
                "name": name,
                "pbrMetallicRoughness": {
                    "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                    "metallicFactor": 0.0,
                    "roughnessFactor": 0.0,
                },
                "extensions": {
                    "KHR_materials_transmission": {"transmissionFactor": 1.0},
                    "KHR_materials_ior": {"ior": ior},
                },
            }
        )

    def camera(self, camera):
        return self._push("cameras", camera)

    def look_at_camera(self, eye, target, yfov_degrees, aspect):
        """A perspective camera "main" at `eye` looking at `target` (+Y up), as a camera and
        the node that places it."""
        cam = self.camera(
            {
                "name": "main",
                "type": "perspective",
                "perspective": {
                    "yfov": math.radians(yfov_degrees),
                    "aspectRatio": aspect,
                    "znear": 0.01,
                },
            }
        )
        return self.node(
            {
                "name": "main",
                "camera": cam,
                "translation": eye,
                "rotation": look_at_rotation(eye, target, [0.0, 1.0, 0.0]),
            }
        )

    def emissive(self, name, strength):
        """A black, one-sided emitter of radiance `strength` (emissiveFactor 1 times
        KHR_materials_emissive_strength)."""
        self.uses("KHR_materials_emissive_strength")
        return self.material(
            {
                "name": name,
                "pbrMetallicRoughness": {"baseColorFactor": [0.0, 0.0, 0.0, 1.0], "metallicFactor": 0.0},
                "emissiveFactor": [1.0, 1.0, 1.0],
                "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": strength}},
            }
        )

    def light(self, light):
        self.uses("KHR_lights_punctual")
        lights = self.doc.setdefault("extensions", {}).setdefault(
            "KHR_lights_punctual", {"lights": []}
        )["lights"]
        lights.append(light)
        return len(lights) - 1

    def node(self, node):
        index = self._push("nodes", node)
        self.doc["scenes"][0]["nodes"].append(index)
        return index

    def write(self, path):
        doc = dict(self.doc)
        doc["buffers"] = [
            {
                "byteLength": len(self.bin),
                "uri": "data:application/octet-stream;base64,"
                + base64.b64encode(bytes(self.bin)).decode("ascii"),
            }
        ]
        with open(path, "w", encoding="utf-8") as f:
            f.write(dumps(doc))
            f.write("\n")


def dumps(value, indent=0):
    """JSON with two-space indentation, keeping arrays of numbers on one line."""
    pad = "  " * indent
    inner = "  " * (indent + 1)
    if isinstance(value, dict):
        if not value:
            return "{}"
        items = [
            "%s%s: %s" % (inner, json.dumps(k), dumps(v, indent + 1)) for k, v in value.items()
        ]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(value, list):
        if all(isinstance(v, (int, float, str)) for v in value):
            return "[" + ", ".join(json.dumps(v) for v in value) + "]"
        items = [inner + dumps(v, indent + 1) for v in value]
        return "[\n" + ",\n".join(items) + "\n" + pad + "]"
    return json.dumps(value)


def look_at_rotation(eye, target, up):
    """Unit quaternion [x, y, z, w] turning a glTF camera (looking down -Z, +Y up) at `eye`
    toward `target`."""

    def sub(a, b):
        return [a[i] - b[i] for i in range(3)]

    def cross(a, b):
        return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]

    def normalize(a):
        n = math.sqrt(sum(c * c for c in a))
        return [c / n for c in a]

    forward = normalize(sub(target, eye))
    right = normalize(cross(forward, up))
    true_up = cross(right, forward)
    back = [-c for c in forward]
    # Columns of the rotation matrix: right, up, back.
    m = [[right[r], true_up[r], back[r]] for r in range(3)]
    trace = m[0][0] + m[1][1] + m[2][2]
    if trace > 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [(m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s, s / 4]
    elif m[0][0] > m[1][1] and m[0][0] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[0][0] - m[1][1] - m[2][2])
        q = [s / 4, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s, (m[2][1] - m[1][2]) / s]
    elif m[1][1] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[1][1] - m[0][0] - m[2][2])
        q = [(m[0][1] + m[1][0]) / s, s / 4, (m[1][2] + m[2][1]) / s, (m[0][2] - m[2][0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2][2] - m[0][0] - m[1][1])
        q = [(m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, s / 4, (m[1][0] - m[0][1]) / s]
    n = math.sqrt(sum(c * c for c in q))
    return [c / n for c in q]


def uv_sphere(radius, segments, rings):
    """A UV sphere about the origin: (positions, normals, indices), every triangle wound
    counter-clockwise seen from outside."""
    positions, normals, indices = [], [], []
    for i in range(rings + 1):
        theta = math.pi * i / rings
        for j in range(segments + 1):
            phi = 2.0 * math.pi * j / segments
            n = (math.sin(theta) * math.cos(phi), math.cos(theta), math.sin(theta) * math.sin(phi))
            normals.append(n)
            positions.append(tuple(radius * c for c in n))
    row = segments + 1
    for i in range(rings):
        for j in range(segments):
            a, b = i * row + j, i * row + j + 1
            c, d = (i + 1) * row + j, (i + 1) * row + j + 1
            if i != 0:
                indices.append((a, c, b))
            if i != rings - 1:
                indices.append((b, c, d))
    # Orient every triangle outward (counter-clockwise seen from outside).
    out = []
    for t in indices:
        p = [positions[k] for k in t]
        e1 = [p[1][k] - p[0][k] for k in range(3)]
        e2 = [p[2][k] - p[0][k] for k in range(3)]
        n = (
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            e1[0] * e2[1] - e1[1] * e2[0],
        )
        centroid = [sum(v[k] for v in p) for k in range(3)]
        if sum(n[k] * centroid[k] for k in range(3)) < 0:
            t = (t[0], t[2], t[1])
        out += list(t)
    return positions, normals, out
