#!/usr/bin/env python3
"""Time to a given error, side by side: Tessera, Mitsuba 3 and Cycles on the same glTF files.

    python3 bench/compare/compare.py [--tessera BIN] [--scenes a.gltf,b.gltf] [--width 256]
        [--height 256] [--spp 64] [--threads 2] [--seeds 1,2] [--renderers ...] [--out DIR]

For every scene and seed the renderers run one after another (interleaved, so a change in
the machine's load hits all of them alike), each with 2 threads, writing an EXR. Then, per
renderer and scene:

- noise: the per-pixel variance of one render, estimated from the difference of two
  seeds' images, `mean_p mean_c (a - b)^2 / 2`, so that bias does not enter; pixels that
  see an emitter directly (any of 4x4 camera rays per pixel, cast by Mitsuba) are left out.
  With more than two seeds (`--seeds 1,2,3,4,...`) the seeds are taken in disjoint pairs
  (1 and 2, 3 and 4, ...): the noise is the mean of the pairs' estimates, and their spread
  gives its standard error (printed as `± SE`; the efficiency ratios' relative error
  combines the two renderers' relative errors). Heavy-tailed scenes (fireflies) need
  several pairs before two renderers can be ranked.
  Each renderer's images are first scaled so that their mean over the kept pixels equals
  Tessera's (the anchors' unit conventions differ by a few percent; the scale is printed),
  so the noise is compared at equal brightness.
- efficiency = 1 / (noise x CPU seconds), Veach's definition (Veach 1997, section 2.4: the
  inverse of variance times time), with the CPU seconds of the render threads (mean of
  the two seeds; scene loading excluded, as each renderer reports it). CPU time rather
  than wall time so that other load on the machine does not enter; with 2 threads on 2
  idle cores the two agree up to the factor 2 (wall seconds are printed as well);
- region means: the mean of each of 4x4 image regions against Mitsuba's (ratio), to check
  that the images agree.

Prints a Markdown table per scene. Needs `pip install mitsuba==3.9.1 bpy==5.0.1` and a
release build of Tessera (`cargo build --release -p tessera-cli`). Not run by CI.
"""

import argparse
import datetime
import json
import os
import platform
import re
import resource
import subprocess
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.abspath(os.path.join(HERE, "..", ".."))
DEFAULT_SCENES = ["cornell-box.gltf", "veach-mis.gltf", "glass-area.gltf"]


def read_exr(path):
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    return np.array(mi.Bitmap(path), dtype=np.float64)[:, :, :3]


def run_json(cmd):
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def tessera(a, binary, scene, seed, out, extra):
    cmd = [binary, "render", scene, "--width", str(a.width), "--height", str(a.height),
           "--spp", str(a.spp), "--threads", str(a.threads), "--seed", str(seed), "-o", out] + extra
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    text = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    seconds = float(re.search(r"^seconds: ([0-9.]+)", text, re.M).group(1))
    line = re.search(r"^cpu seconds: ([0-9.]+)", text, re.M)
    # Builds before the "cpu seconds" line: the whole process's CPU time (loading included).
    cpu = float(line.group(1)) if line else (after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime)
    scene_line = re.search(r"^scene: (.*)$", text, re.M)
    return {"seconds": seconds, "cpu_seconds": cpu, "plan": re.search(r"^rendered .*\((.*)\)", text, re.M).group(1),
            "scene": scene_line.group(1) if scene_line else ""}


def mitsuba(a, scene, seed, out, sampler, mask=None):
    cmd = [sys.executable, os.path.join(HERE, "mitsuba_render.py"), scene, "--width", str(a.width),
           "--height", str(a.height), "--spp", str(a.spp), "--seed", str(seed), "--threads", str(a.threads),
           "--sampler", sampler, "--max-depth", str(a.max_depth + 1), "--out", out]
    if mask:
        cmd += ["--mask", mask]
    return run_json(cmd)


def cycles(a, scene, seed, out):
    cmd = [sys.executable, os.path.join(HERE, "cycles_render.py"), scene, "--width", str(a.width),
           "--height", str(a.height), "--spp", str(a.spp), "--seed", str(seed), "--threads", str(a.threads),
           "--max-depth", str(a.max_depth), "--out", out]
    return run_json(cmd)


def region_means(img, keep, n=4):
    h, w = keep.shape
    out = []
    for j in range(n):
        for i in range(n):
            sl = (slice(j * h // n, (j + 1) * h // n), slice(i * w // n, (i + 1) * w // n))
            k = keep[sl]
            out.append(img[sl][k].mean() if k.any() else np.nan)
    return np.array(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tessera", default=os.path.join(ROOT, "target", "release", "tessera"))
    ap.add_argument("--scenes", default=",".join(os.path.join(HERE, "scenes", s) for s in DEFAULT_SCENES))
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--max-depth", type=int, default=16,
                    help="bounces for every renderer (Tessera --max-depth; Mitsuba max_depth + 1)")
    ap.add_argument("--seeds", default="1,2")
    ap.add_argument("--renderers", default="tessera,mitsuba-multijitter,mitsuba-independent,cycles")
    ap.add_argument("--tessera-old", help="a second Tessera binary, renderer name tessera-old")
    ap.add_argument("--tessera-args", default="", help="extra arguments for tessera render")
    ap.add_argument("--out", default="/tmp/tessera-compare")
    a = ap.parse_args()
    if not os.path.exists(os.path.join(HERE, "scenes", "veach-mis.gltf")):
        subprocess.run([sys.executable, os.path.join(HERE, "make_scenes.py")], check=True)
    os.makedirs(a.out, exist_ok=True)
    seeds = [int(s) for s in a.seeds.split(",")]
    renderers = a.renderers.split(",")
    extra = ["--max-depth", str(a.max_depth)] + a.tessera_args.split()
    print("# bench/compare, %s, %s, %d cores; %dx%d, %d spp, %d threads, max depth %d, seeds %s\n"
          % (datetime.date.today(), platform.node(), os.cpu_count(), a.width, a.height, a.spp,
             a.threads, a.max_depth, a.seeds))
    for scene in a.scenes.split(","):
        name = os.path.splitext(os.path.basename(scene))[0]
        mask_file = os.path.join(a.out, name + ".mask.npy")
        times = {r: [] for r in renderers}
        cpu = {r: [] for r in renderers}
        plan = ""
        for seed in seeds:
            for r in renderers:
                out = os.path.join(a.out, "%s.%s.%d.exr" % (name, r, seed))
                if r == "tessera":
                    res = tessera(a, a.tessera, scene, seed, out, extra)
                    plan = res["plan"] + ("; scene: " + res["scene"] if res["scene"] else "")
                elif r == "tessera-old":
                    res = tessera(a, a.tessera_old, scene, seed, out, extra)
                elif r.startswith("mitsuba-"):
                    res = mitsuba(a, scene, seed, out, r.split("-", 1)[1],
                                  mask_file if not os.path.exists(mask_file) else None)
                elif r == "cycles":
                    res = cycles(a, scene, seed, out)
                else:
                    raise SystemExit("unknown renderer " + r)
                times[r].append(res["seconds"])
                cpu[r].append(res["cpu_seconds"])
        if not os.path.exists(mask_file):
            mitsuba(a, scene, seeds[0], os.path.join(a.out, "mask.exr"), "independent", mask_file)
        keep = ~np.load(mask_file)
        pairs = len(seeds) // 2
        imgs = {r: [read_exr(os.path.join(a.out, "%s.%s.%d.exr" % (name, r, s))) for s in seeds[:2 * pairs]]
                for r in renderers}
        base = renderers[0]
        base_mean = np.mean([im[keep].mean() for im in imgs[base]])
        rows = {}
        for r in renderers:
            scale = base_mean / np.mean([im[keep].mean() for im in imgs[r]])
            scaled = [im * scale for im in imgs[r]]
            # One independent estimate of the per-pixel variance per disjoint pair of seeds.
            per_pair = np.array([(((scaled[2 * i] - scaled[2 * i + 1]) ** 2) / 2.0)[keep].mean()
                                 for i in range(pairs)])
            noise = float(per_pair.mean())
            rel_se = float(per_pair.std(ddof=1) / np.sqrt(pairs) / noise) if pairs > 1 else float("nan")
            seconds = float(np.mean(times[r]))
            cpu_seconds = float(np.mean(cpu[r]))
            rows[r] = {"scale": scale, "noise": noise, "rel_se": rel_se, "seconds": seconds,
                       "cpu": cpu_seconds, "eff": 1.0 / (noise * cpu_seconds),
                       "mean": sum(scaled) / len(scaled) / scale}
        ref = next((r for r in renderers if r.startswith("mitsuba")), base)
        ref_regions = region_means(rows[ref]["mean"], keep)
        cyc_row = rows.get("cycles", rows[base])
        cyc = cyc_row["eff"]
        best_row = max((rows[r] for r in renderers if not r.startswith("tessera")),
                       key=lambda q: q["eff"], default=rows[base])
        best_anchor = best_row["eff"]

        def vs(q, other):
            text = "%.2fx" % (q["eff"] / other["eff"])
            if pairs > 1 and q is not other:
                text += " ± %.0f%%" % (100 * np.hypot(q["rel_se"], other["rel_se"]))
            return text
        paths = a.width * a.height * a.spp
        print("## %s (Tessera plan: %s)\n" % (name, plan))
        print("| renderer | seconds | CPU seconds | M paths per CPU-s | noise variance | efficiency vs Cycles | vs best anchor | brightness scale | region means / %s (min..max) |" % ref)
        print("|---|---|---|---|---|---|---|---|---|")
        for r in renderers:
            q = rows[r]
            ratio = region_means(q["mean"], keep) / ref_regions
            noise = "%.4g" % q["noise"]
            if pairs > 1:
                noise += " ± %.0f%%" % (100 * q["rel_se"])
            print("| %s | %.2f | %.2f | %.3f | %s | %s | %s | %.4f | %.3f..%.3f |" % (
                r, q["seconds"], q["cpu"], paths / q["cpu"] / 1e6, noise, vs(q, cyc_row),
                vs(q, best_row), q["scale"], np.nanmin(ratio), np.nanmax(ratio)))
        print()
        sys.stdout.flush()


if __name__ == "__main__":
    main()
