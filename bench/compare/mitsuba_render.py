#!/usr/bin/env python3
"""Renders a glTF scene with Mitsuba 3 (scalar_rgb, path tracer) for bench/compare.

    python3 mitsuba_render.py SCENE.gltf --width W --height H --spp N --seed S --threads T
        --sampler multijitter --max-depth D --rr-depth R --out OUT.exr [--mask MASK.npy]

glTF to Mitsuba: every primitive becomes a PLY mesh in world space (a temporary
directory); metallic-roughness materials become `principled` (base_color, metallic,
roughness, specular 0.5 = ior 1.5, as glTF's dielectric F0 of 0.04), transmissive ones
`dielectric` / `roughdielectric` (GGX, alpha = roughness^2), emissive ones get an `area`
emitter with radiance emissiveFactor x emissiveStrength (one-sided, like glTF's emission
seen from the front). The camera looks down -Z in glTF and +Z in Mitsuba (with +X to the
left), hence the 180 degree turn about Y. Pixel filter: box, as Tessera's. A dielectric
with KHR_materials_specular factor 0 is Lambertian (`diffuse`), as in Tessera.

Prints one JSON line: {"renderer": "mitsuba", "seconds": render seconds (scene loading
excluded), "paths": width*height*spp}. With --mask it also writes a boolean (H, W) array:
pixels where any of 4x4 camera rays per pixel hits an emitter directly.
"""

import argparse
import json
import os
import sys
import tempfile
import time

import numpy as np
import mitsuba as mi

sys.dont_write_bytecode = True
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import gltf_read  # noqa: E402


def write_ply(path, mesh):
    p = mesh["positions"].astype(np.float32)
    cols = [p]
    props = ["x", "y", "z"]
    if mesh["normals"] is not None:
        cols.append(mesh["normals"].astype(np.float32))
        props += ["nx", "ny", "nz"]
    if mesh["uvs"] is not None:
        cols.append(mesh["uvs"].astype(np.float32))
        props += ["u", "v"]
    vertices = np.hstack(cols).astype("<f4")
    faces = np.zeros(len(mesh["indices"]), dtype=[("n", "u1"), ("i", "<u4", (3,))])
    faces["n"] = 3
    faces["i"] = mesh["indices"]
    header = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % len(p)
    header += "".join("property float %s\n" % name for name in props)
    header += "element face %d\nproperty list uchar uint vertex_indices\nend_header\n" % len(faces)
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(vertices.tobytes())
        f.write(faces.tobytes())


def bsdf(m, texture_file, nearest=False):
    color = {"type": "rgb", "value": m["base_color"]}
    if texture_file is not None:
        # glTF's magFilter NEAREST (9728) is Mitsuba's "nearest"; otherwise bilinear, as
        # Tessera's (no mipmaps in either).
        color = {"type": "bitmap", "filename": texture_file,
                 "filter_type": "nearest" if nearest else "bilinear"}
    if m["transmission"] > 0.5:
        alpha = m["roughness"] ** 2
        if alpha < 1e-3:
            return {"type": "dielectric", "int_ior": m["ior"], "ext_ior": 1.0}
        return {"type": "roughdielectric", "distribution": "ggx", "alpha": alpha, "int_ior": m["ior"], "ext_ior": 1.0}
    if m["specular"] == 0.0 and m["metallic"] == 0.0:
        b = {"type": "diffuse", "reflectance": color}
        return {"type": "twosided", "material": b} if m["double_sided"] else b
    b = {"type": "principled", "base_color": color, "metallic": m["metallic"],
         "roughness": m["roughness"], "specular": 0.5}
    if m["double_sided"]:
        return {"type": "twosided", "material": b}
    return b


def scene_dict(path, width, height, spp, seed, sampler, max_depth, rr_depth, tmp):
    doc, buffers = gltf_read.load(path)
    d = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": max_depth, "rr_depth": rr_depth},
    }
    textures = {}
    for k, mesh in enumerate(gltf_read.meshes(doc, buffers)):
        ply = os.path.join(tmp, "mesh%d.ply" % k)
        write_ply(ply, mesh)
        m = gltf_read.material(doc, mesh["material"])
        tex = m["base_color_texture"]
        texture_file = None
        nearest = False
        if tex is not None and mesh["uvs"] is not None:
            tex_sampler = doc["textures"][tex].get("sampler")
            nearest = tex_sampler is not None and doc["samplers"][tex_sampler].get("magFilter") == 9728
            if tex not in textures:
                textures[tex] = os.path.join(tmp, "texture%d.png" % tex)
                with open(textures[tex], "wb") as f:
                    f.write(gltf_read.image_bytes(doc, buffers, tex, os.path.dirname(path)))
            texture_file = textures[tex]
        shape = {"type": "ply", "filename": ply, "face_normals": mesh["normals"] is None, "bsdf": bsdf(m, texture_file, nearest)}
        if max(m["emission"]) > 0:
            shape["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": m["emission"]}}
        d["mesh%d" % k] = shape
    world, yfov = gltf_read.camera(doc)
    to_world = world @ np.diag([-1.0, 1.0, -1.0, 1.0])
    d["sensor"] = {
        "type": "perspective",
        "fov": float(np.degrees(yfov)),
        "fov_axis": "y",
        "to_world": mi.ScalarTransform4f(to_world.tolist()),
        "sampler": {"type": sampler, "sample_count": spp, "seed": seed},
        "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
                 "pixel_format": "rgb"},
    }
    return d


def emitter_mask(scene, width, height, n=4):
    sensor = scene.sensors()[0]
    mask = np.zeros((height, width), dtype=bool)
    for y in range(height):
        for x in range(width):
            for j in range(n):
                for i in range(n):
                    pos = mi.ScalarPoint2f((x + (i + 0.5) / n) / width, (y + (j + 0.5) / n) / height)
                    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.ScalarPoint2f(0.5, 0.5))
                    si = scene.ray_intersect(ray)
                    if si.is_valid() and si.shape.is_emitter():
                        mask[y, x] = True
    return mask


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--sampler", default="multijitter")
    ap.add_argument("--max-depth", type=int, default=17)
    ap.add_argument("--rr-depth", type=int, default=5)
    ap.add_argument("--out", required=True)
    ap.add_argument("--mask")
    a = ap.parse_args()
    mi.set_variant("scalar_rgb")
    mi.set_log_level(mi.LogLevel.Warn)
    import drjit as dr
    dr.set_thread_count(a.threads)
    with tempfile.TemporaryDirectory(prefix="tessera-compare-") as tmp:
        scene = mi.load_dict(scene_dict(a.scene, a.width, a.height, a.spp, a.seed, a.sampler,
                                        a.max_depth, a.rr_depth, tmp))
        t0, c0 = time.perf_counter(), time.process_time()
        image = mi.render(scene, spp=a.spp, seed=a.seed)
        cpu = time.process_time() - c0
        seconds = time.perf_counter() - t0
        mi.Bitmap(image).write(a.out)
        if a.mask:
            np.save(a.mask, emitter_mask(scene, a.width, a.height))
    print(json.dumps({"renderer": "mitsuba-" + a.sampler, "seconds": seconds, "cpu_seconds": cpu, "paths": a.width * a.height * a.spp}))


if __name__ == "__main__":
    main()
