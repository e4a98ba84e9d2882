#!/usr/bin/env python3
"""Two builds' efficiency on one unbiased job, from renders under many seeds.

    python3 bench/seed_mse.py DIR/a DIR/b     # reads DIR/a-<seed>.exr and DIR/b-<seed>.exr

Both builds render the same job (same flags) under seeds 1..N. Both estimators are
unbiased, so the mean of all their renders is the reference; each render's mean squared
error (of the RGB mean, over the pixels) against it is one sample of its estimator's
variance. Prints each build's mean MSE with its standard error and the ratio b/a with its
propagated standard error; divide by the CPU ratio for the efficiency (1 / (MSE x s)).
Standard library only (bench/exr.py reads the files).
"""
import glob
import math
import sys

from exr import read_exr


def luminance_rgb_mean(path):
    ch = read_exr(path)["channels"]
    return [(r + g + b) / 3 for r, g, b in zip(ch["R"], ch["G"], ch["B"])]


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    sets = []
    for prefix in sys.argv[1:3]:
        files = sorted(glob.glob(prefix + "-*.exr"))
        if len(files) < 2:
            sys.exit(f"{prefix}: need at least two renders {prefix}-<seed>.exr")
        sets.append([luminance_rgb_mean(f) for f in files])
    every = sets[0] + sets[1]
    n = len(every[0])
    if any(len(img) != n for img in every):
        sys.exit("the renders differ in size")
    ref = [sum(img[i] for img in every) / len(every) for i in range(n)]
    stats = []
    for prefix, imgs in zip(sys.argv[1:3], sets):
        mses = [sum((img[i] - ref[i]) ** 2 for i in range(n)) / n for img in imgs]
        m = sum(mses) / len(mses)
        se = math.sqrt(sum((x - m) ** 2 for x in mses) / (len(mses) - 1) / len(mses))
        stats.append((m, se))
        print(f"{prefix}: {len(imgs)} seeds, MSE {m:.5g} +- {se:.2g}")
    (ma, sa), (mb, sb) = stats
    r = mb / ma
    print(f"ratio b/a {r:.3f} +- {r * math.sqrt((sa / ma) ** 2 + (sb / mb) ** 2):.3f}")


if __name__ == "__main__":
    main()
