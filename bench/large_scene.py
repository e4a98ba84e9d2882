#!/usr/bin/env python3
"""Writes bench/compare's displaced terrain (`make_scenes.large`) at any size, for the
memory and scale figures in docs/benchmarks.md ("Memory and scale"): one mesh placed
once (not instanced), under a square area light, as a binary .glb.

    python3 bench/large_scene.py --triangles 10000000 -o /tmp/large10m.glb

The terrain is n x n quads with n = ceil(sqrt(triangles / 2)), so the mesh has at least
the triangles asked for (2,000,000 exactly for n = 1000, bench/compare's large.glb).
Needs numpy.
"""

import argparse
import math
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "compare"))
import make_scenes  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--triangles", type=int, default=2_000_000, help="at least this many terrain triangles")
    ap.add_argument("-o", "--output", required=True, help="the .glb to write")
    args = ap.parse_args()
    if args.triangles < 2:
        ap.error("--triangles must be at least 2")
    n = math.isqrt(args.triangles // 2)
    if 2 * n * n < args.triangles:
        n += 1
    make_scenes.large(args.output, n)
    print(f"wrote {args.output}: {2 * n * n + 2} triangles ({n} x {n} quads and the light)")


if __name__ == "__main__":
    main()
