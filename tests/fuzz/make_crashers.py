"""Writes the minimized crashers of the robustness issue into corpus/gltf/.

Each is a one-triangle .glb:
- crasher-scale-1e38.glb: nodes[0].scale = [1e38, 1e38, 1e38] (the BVH builder panicked)
- crasher-bomb-16384x16384.glb, crasher-bomb-32768x8192.glb: an embedded PNG whose header
  claims 256 Mi texels; only the header and the first rows of zeros are kept (the importer
  refuses it from the header, so the rest of the data is not needed to reproduce it).
Run from this directory: python3 make_crashers.py
"""
import json, struct, zlib


def png_header_only(w, h, rows=4):
    def chunk(t, d):
        return struct.pack('>I', len(d)) + t + d + struct.pack('>I', zlib.crc32(t + d) & 0xffffffff)
    ihdr = struct.pack('>IIBBBBB', w, h, 8, 0, 0, 0, 0)  # 8-bit greyscale
    co = zlib.compressobj(9)
    data = co.compress(b'\0' * (w + 1) * rows) + co.flush(zlib.Z_SYNC_FLUSH)
    return b'\x89PNG\r\n\x1a\n' + chunk(b'IHDR', ihdr) + chunk(b'IDAT', data) + chunk(b'IEND', b'')


def glb(path, image=None, scale=None):
    bin_ = struct.pack('<9f', 0, 0, 0, 1, 0, 0, 0, 1, 0) + struct.pack('<6f', 0, 0, 1, 0, 0, 1)
    node = {"mesh": 0}
    if scale:
        node["scale"] = scale
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [node],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "material": 0}]}],
           "materials": [{"pbrMetallicRoughness": {}}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                          "min": [0, 0, 0], "max": [1, 1, 0]},
                         {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC2"}],
           "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36},
                           {"buffer": 0, "byteOffset": 36, "byteLength": 24}]}
    if image:
        doc["bufferViews"].append({"buffer": 0, "byteOffset": len(bin_), "byteLength": len(image)})
        doc["images"] = [{"name": "bomb", "bufferView": 2, "mimeType": "image/png"}]
        doc["textures"] = [{"source": 0}]
        doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] = {"index": 0}
        bin_ += image
    while len(bin_) % 4:
        bin_ += b'\0'
    doc["buffers"] = [{"byteLength": len(bin_)}]
    j = json.dumps(doc, separators=(',', ':')).encode()
    while len(j) % 4:
        j += b' '
    total = 12 + 8 + len(j) + 8 + len(bin_)
    out = b'glTF' + struct.pack('<III', 2, total, len(j)) + b'JSON' + j
    out += struct.pack('<I', len(bin_)) + b'BIN\0' + bin_
    open(path, 'wb').write(out)


glb('corpus/gltf/crasher-scale-1e38.glb', scale=[1e38, 1e38, 1e38])
glb('corpus/gltf/crasher-bomb-16384x16384.glb', image=png_header_only(16384, 16384))
glb('corpus/gltf/crasher-bomb-32768x8192.glb', image=png_header_only(32768, 8192))
