"""A small glTF 2.0 reader for the comparison scripts (numpy only): world-space triangle
meshes with their materials, the first camera, and nothing else (no animation, skins or
punctual lights; the comparison scenes do not use them).
"""

import base64
import json
import os
import struct

import numpy as np

COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def load(path):
    """(doc, buffers) of a .gltf (data URIs or files beside it) or .glb."""
    with open(path, "rb") as f:
        data = f.read()
    if data[:4] == b"glTF":
        length = struct.unpack_from("<I", data, 12)[0]
        doc = json.loads(data[20:20 + length])
        offset = 20 + length
        offset += (-offset) % 4
        chunk_length = struct.unpack_from("<I", data, offset)[0]
        bin_chunk = data[offset + 8:offset + 8 + chunk_length]
        buffers = [bin_chunk]
    else:
        doc = json.loads(data)
        buffers = []
        for b in doc.get("buffers", []):
            uri = b["uri"]
            if uri.startswith("data:"):
                buffers.append(base64.b64decode(uri.split(",", 1)[1]))
            else:
                with open(os.path.join(os.path.dirname(path), uri), "rb") as f:
                    buffers.append(f.read())
    return doc, buffers


def accessor(doc, buffers, index):
    """Accessor `index` as a numpy array of shape (count, width) (or (count,) for SCALAR)."""
    a = doc["accessors"][index]
    view = doc["bufferViews"][a["bufferView"]]
    dtype = np.dtype(COMPONENTS[a["componentType"]])
    n = WIDTH[a["type"]]
    buf = buffers[view["buffer"]]
    start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
    stride = view.get("byteStride", dtype.itemsize * n)
    if stride == dtype.itemsize * n:
        out = np.frombuffer(buf, dtype, a["count"] * n, start).reshape(a["count"], n)
    else:
        out = np.vstack([np.frombuffer(buf, dtype, n, start + i * stride) for i in range(a["count"])])
    return out if n > 1 else out.reshape(-1)


def quat_matrix(q):
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def local_matrix(node):
    if "matrix" in node:
        return np.array(node["matrix"], dtype=np.float64).reshape(4, 4).T
    m = np.eye(4)
    r = quat_matrix(node.get("rotation", [0, 0, 0, 1]))
    s = np.diag(node.get("scale", [1, 1, 1]))
    m[:3, :3] = r @ s
    m[:3, 3] = node.get("translation", [0, 0, 0])
    return m


def walk(doc):
    """(node index, world matrix) of every node of the default scene."""
    scene = doc["scenes"][doc.get("scene", 0)]
    stack = [(n, np.eye(4)) for n in scene["nodes"]]
    while stack:
        i, parent = stack.pop()
        world = parent @ local_matrix(doc["nodes"][i])
        yield i, world
        for c in doc["nodes"][i].get("children", []):
            stack.append((c, world))


def material(doc, index):
    """A flat description of material `index` (None: the glTF default material)."""
    m = doc["materials"][index] if index is not None else {}
    pbr = m.get("pbrMetallicRoughness", {})
    ext = m.get("extensions", {})
    strength = ext.get("KHR_materials_emissive_strength", {}).get("emissiveStrength", 1.0)
    return {
        "name": m.get("name", "default"),
        "base_color": pbr.get("baseColorFactor", [1, 1, 1, 1])[:3],
        "base_color_texture": pbr.get("baseColorTexture", {}).get("index"),
        "metallic": pbr.get("metallicFactor", 1.0),
        "roughness": pbr.get("roughnessFactor", 1.0),
        "emission": [c * strength for c in m.get("emissiveFactor", [0, 0, 0])],
        "transmission": ext.get("KHR_materials_transmission", {}).get("transmissionFactor", 0.0),
        "ior": ext.get("KHR_materials_ior", {}).get("ior", 1.5),
        "double_sided": m.get("doubleSided", False),
        "specular": ext.get("KHR_materials_specular", {}).get("specularFactor", 1.0),
    }


def image_bytes(doc, buffers, texture, base_dir):
    image = doc["images"][doc["textures"][texture]["source"]]
    if "bufferView" in image:
        v = doc["bufferViews"][image["bufferView"]]
        o = v.get("byteOffset", 0)
        return buffers[v["buffer"]][o:o + v["byteLength"]]
    uri = image["uri"]
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    with open(os.path.join(base_dir, uri), "rb") as f:
        return f.read()


def meshes(doc, buffers):
    """World-space triangle lists: dicts with positions (n, 3), normals (n, 3) or None,
    uvs (n, 2) or None, indices (m, 3) and the material index."""
    out = []
    for i, world in walk(doc):
        node = doc["nodes"][i]
        if "mesh" not in node:
            continue
        normal_matrix = np.linalg.inv(world[:3, :3]).T
        flip = np.linalg.det(world[:3, :3]) < 0
        for prim in doc["meshes"][node["mesh"]]["primitives"]:
            if prim.get("mode", 4) != 4:
                continue
            attr = prim["attributes"]
            p = accessor(doc, buffers, attr["POSITION"]).astype(np.float64)
            p = p @ world[:3, :3].T + world[:3, 3]
            n = None
            if "NORMAL" in attr:
                n = accessor(doc, buffers, attr["NORMAL"]).astype(np.float64) @ normal_matrix.T
                n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            uv = accessor(doc, buffers, attr["TEXCOORD_0"]).astype(np.float64) if "TEXCOORD_0" in attr else None
            if "indices" in prim:
                idx = accessor(doc, buffers, prim["indices"]).astype(np.uint32).reshape(-1, 3)
            else:
                idx = np.arange(len(p), dtype=np.uint32).reshape(-1, 3)
            if flip:
                idx = idx[:, [0, 2, 1]]
            out.append({"positions": p, "normals": n, "uvs": uv, "indices": idx,
                        "material": prim.get("material"), "name": doc["meshes"][node["mesh"]].get("name", "mesh")})
    return out


def camera(doc):
    """(world matrix, yfov radians) of the first camera node."""
    for i, world in walk(doc):
        node = doc["nodes"][i]
        if "camera" in node:
            cam = doc["cameras"][node["camera"]]
            return world, cam["perspective"]["yfov"]
    raise SystemExit("the scene has no camera")
