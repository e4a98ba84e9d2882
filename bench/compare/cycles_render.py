#!/usr/bin/env python3
"""Renders a glTF scene with Cycles (Blender 5, `pip install bpy==5.0.1`) for bench/compare.

    python3 cycles_render.py SCENE.gltf --width W --height H --spp N --seed S --threads T
        --max-depth D --out OUT.exr

The file goes through Blender's own glTF importer (what a Blender user gets), the first
camera renders. Cycles on the CPU with its defaults for sampling and light selection (the
light tree is on), except what makes the comparison fair: no denoising, no adaptive
sampling, no clamping, no filter glossy, a box pixel filter of one pixel (Tessera's and
Mitsuba's), `max_bounces` = Tessera's max depth for every ray type, the Standard view
transform, a fixed seed, and one-sided emission (see `one_sided_emission`).

Prints one JSON line: {"renderer": "cycles", "seconds": the render call's seconds
(including Cycles' scene synchronisation and BVH build, which Blender does per render),
"paths": width*height*spp}.
"""

import argparse
import json
import time

import bpy


def one_sided_emission():
    """glTF emission (like Tessera's and Mitsuba's area lights) leaves the front face only;
    Cycles emits from both sides. For every emissive Principled BSDF the back face gets a
    diffuse BSDF of the same base colour instead (Geometry > Backfacing into a Mix
    Shader), and Cycles' light sampling is told the emission is front-facing only."""
    for m in bpy.data.materials:
        if not m.use_nodes:
            continue
        nodes, links = m.node_tree.nodes, m.node_tree.links
        for n in list(nodes):
            if n.type != "BSDF_PRINCIPLED" or n.inputs["Emission Strength"].default_value <= 0.0:
                continue
            out = next(l for l in n.outputs["BSDF"].links)
            target = out.to_socket
            links.remove(out)
            back = nodes.new("ShaderNodeBsdfDiffuse")
            back.inputs["Color"].default_value = n.inputs["Base Color"].default_value
            geometry = nodes.new("ShaderNodeNewGeometry")
            mix = nodes.new("ShaderNodeMixShader")
            links.new(geometry.outputs["Backfacing"], mix.inputs["Fac"])
            links.new(n.outputs["BSDF"], mix.inputs[1])
            links.new(back.outputs["BSDF"], mix.inputs[2])
            links.new(mix.outputs["Shader"], target)
            m.cycles.emission_sampling = "FRONT"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--max-depth", type=int, default=16)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.gltf(filepath=a.scene)
    one_sided_emission()
    s = bpy.context.scene
    cameras = [o for o in s.objects if o.type == "CAMERA"]
    if not cameras:
        raise SystemExit("the scene has no camera")
    s.camera = cameras[0]
    s.render.engine = "CYCLES"
    c = s.cycles
    c.device = "CPU"
    c.samples = a.spp
    c.seed = a.seed
    c.use_animated_seed = False
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.pixel_filter_type = "BOX"
    c.filter_width = 1.0
    for bounce in ("max_bounces", "diffuse_bounces", "glossy_bounces", "transmission_bounces", "transparent_max_bounces"):
        setattr(c, bounce, a.max_depth)
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.blur_glossy = 0.0
    c.caustics_reflective = True
    c.caustics_refractive = True
    s.render.film_transparent = False
    s.render.resolution_x, s.render.resolution_y, s.render.resolution_percentage = a.width, a.height, 100
    s.render.threads_mode = "FIXED"
    s.render.threads = a.threads
    s.view_settings.view_transform = "Standard"
    s.view_settings.look = "None"
    s.view_settings.exposure = 0.0
    s.view_settings.gamma = 1.0
    if s.world is None:
        s.world = bpy.data.worlds.new("black")
    s.world.use_nodes = True
    bg = s.world.node_tree.nodes.get("Background")
    if bg is not None:
        bg.inputs["Strength"].default_value = 0.0
    s.render.image_settings.file_format = "OPEN_EXR"
    s.render.image_settings.color_depth = "32"
    s.render.image_settings.color_mode = "RGB"
    s.render.filepath = a.out
    t0, c0 = time.perf_counter(), time.process_time()
    bpy.ops.render.render(write_still=True)
    cpu = time.process_time() - c0
    seconds = time.perf_counter() - t0
    print(json.dumps({"renderer": "cycles", "seconds": seconds, "cpu_seconds": cpu, "paths": a.width * a.height * a.spp}))


if __name__ == "__main__":
    main()
