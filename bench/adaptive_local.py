#!/usr/bin/env python3
"""Compares the unbiased adaptive mode of two builds, and uniform sampling, in one process
each (`tessera render`), on one scene at 64x64 (docs/benchmarks.md, "the optimal
(Neyman) allocation for the unbiased mode").

Usage: bench/adaptive_local.py SCENE OLD_BINARY NEW_BINARY
Environment: OUT (default /tmp/adaptive-local: reference and images), REF_SPP (65536),
SEED (7), UNIFORM (spp list, 512,1024,2048,4096), TARGETS (0.05,0.035,0.025,0.018).

Prints one line per render: the run, its spp or target, the child's CPU seconds, the
measured error against the reference (as bench/adaptive_farm.py defines it) and the
render's own estimate. The reference is rendered once with NEW_BINARY and kept in OUT.
Not a test: it measures the clock.
"""
import os
import resource
import subprocess
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from adaptive_farm import estimated_error, measured_error  # noqa: E402
from exr import read_exr  # noqa: E402


def child_cpu():
    u = resource.getrusage(resource.RUSAGE_CHILDREN)
    return u.ru_utime + u.ru_stime


def render(binary, scene, path, *flags):
    c0 = child_cpu()
    subprocess.run([binary, "render", scene, "--width", "64", "--height", "64", "--threads", "2",
                    "-o", path, *flags], capture_output=True, text=True, check=True)
    return round(child_cpu() - c0, 2)


def main():
    scene, old, new = sys.argv[1:4]
    out = os.environ.get("OUT", "/tmp/adaptive-local")
    os.makedirs(out, exist_ok=True)
    name = scene.replace("builtin:", "").replace("/", "_")
    ref_path = f"{out}/ref-{name}.exr"
    if not os.path.exists(ref_path):
        c = render(new, scene, ref_path, "--spp", os.environ.get("REF_SPP", "65536"),
                   "--seed", "1592590337")
        print("reference cpu", c, flush=True)
    ref = read_exr(ref_path)
    seed = os.environ.get("SEED", "7")
    for spp in os.environ.get("UNIFORM", "512,1024,2048,4096").split(","):
        p = f"{out}/{name}-uniform-{spp}-{seed}.exr"
        c = render(new, scene, p, "--spp", spp, "--seed", seed)
        print("uniform", spp, c, measured_error(p, ref), estimated_error(p), flush=True)
    for label, binary in (("old", old), ("new", new)):
        for t in os.environ.get("TARGETS", "0.05,0.035,0.025,0.018").split(","):
            p = f"{out}/{name}-{label}-{t}-{seed}.exr"
            c = render(binary, scene, p, "--spp", "16384", "--adaptive", "unbiased",
                       "--target-error", t, "--seed", seed)
            print(label, t, c, measured_error(p, ref), estimated_error(p), flush=True)


if __name__ == "__main__":
    main()
