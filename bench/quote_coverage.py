#!/usr/bin/env python3
"""Does a quote's 95% interval cover what the render it predicts takes?

For each scene and target error: `tessera estimate SCENE FLAGS --target-error T --threads 1
--json` (the pilot is deterministic: one quote per scene and target), then `tessera render`
with the same flags and `--seed 1..N`, each timed by `/usr/bin/time` (user + system CPU
seconds: the machine is shared, so wall time means little). A render is covered when its
CPU seconds lie in the quote's interval of whole-process seconds (`cost.seconds`: the
scene's set-up plus the worker-seconds, one worker of one thread), and its samples per
pixel in the quote's spp interval. A quote classed "unpredictable" claims only a lower
bound: it is held to the render taking at least its estimate.

Each scene x target runs under one acquisition of the shared heavy lock (`--lock`, flock),
so other timed work waits at most one batch. Results append to a JSON-lines file (one
line per render, one per quote) so a batch can be rerun alone; `--table` prints the
markdown table for docs/benchmarks.md from that file.

Usage:
  bench/quote_coverage.py BINARY [--only NAME[,NAME]] [--targets 0.05,0.02] [--seeds 10]
      [--out FILE] [--lock FILE]
  bench/quote_coverage.py --table [--out FILE]
  bench/quote_coverage.py --requote BINARY [--out FILE]   (a changed quote, the same renders)

Python 3 standard library only. Not a test: it measures the clock; its figures go to
docs/benchmarks.md ("Quotes and ETA").
"""
import argparse
import fcntl
import json
import os
import re
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

# (name, scene, flags, wall time limit of a render in seconds or None). The calibration
# suite's six scenes (crates/tessera-render/tests/it/calibration.rs) and bench/compare's
# glass ball (`python3 bench/compare/make_scenes.py` writes it), at 64x64 or what keeps a
# render near a minute of CPU: the indirect room needs 516 passes of 64 samples at 2%, so
# it runs at 24x24 in 8-pixel tiles (9 tiles, all of them in the pilot). The rare-path
# scenes get a time limit in wall seconds, above every lower bound quoted for them (20 s;
# 45 s for the glossy highlight, quoted 20 s at 2%; 90 s at 32x32, where its quote is a
# prediction and the render must finish): a render cut there took at least that long.
SCENES = [
    ("cornell-box", "builtin:cornell-box", ["--width", "64", "--height", "64"], None),
    ("veach-mis", "builtin:veach-mis", ["--width", "64", "--height", "64"], None),
    ("textured-room", "scenes/textured-room.gltf", ["--width", "64", "--height", "64"], None),
    ("indirect-room", "scenes/indirect-room.gltf",
     ["--width", "24", "--height", "24", "--tile-size", "8"], None),
    ("caustic", "builtin:caustic", ["--width", "64", "--height", "64"], 20),
    ("glossy-highlight", "scenes/glossy-highlight.gltf", ["--width", "64", "--height", "64"], 45),
    ("glass-area", "bench/compare/scenes/glass-area.gltf", ["--width", "64", "--height", "64"], 20),
    # The rare-path scenes at the suite's own 32x32: a pixel then averages four times the
    # area, its pass values are less heavy-tailed, and the pilot classes them otherwise.
    ("caustic-32", "builtin:caustic", ["--width", "32", "--height", "32"], 20),
    ("glossy-highlight-32", "scenes/glossy-highlight.gltf", ["--width", "32", "--height", "32"],
     90),
    ("glass-area-32", "bench/compare/scenes/glass-area.gltf", ["--width", "32", "--height", "32"],
     20),
]
# A sample budget no target here reaches: the render stops at its target.
COMMON = ["--spp", "1048576", "--threads", "1"]


def locked(path):
    f = open(path, "a")
    fcntl.flock(f, fcntl.LOCK_EX)
    return f


def timed(cmd):
    """Runs cmd under /usr/bin/time; (stdout, cpu seconds, wall seconds)."""
    with tempfile.NamedTemporaryFile("r", suffix=".time") as t:
        p = subprocess.run(["/usr/bin/time", "-f", "%U %S %e", "-o", t.name, *cmd],
                           capture_output=True, text=True)
        if p.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)} failed:\n{p.stderr}")
        u, s, e = map(float, t.read().split()[-3:])
    return p.stdout, u + s, e


def batch(binary, name, scene, flags, limit, target, seeds, out):
    job = [scene, *flags, *COMMON, "--target-error", str(target)]
    est_out, est_cpu, _ = timed([binary, "estimate", *job, "--json"])
    est = json.loads(est_out)
    q = est["quote"]
    t = q["targets"][0]
    rec = {"kind": "quote", "name": name, "scene": scene, "flags": flags, "target": target,
           "integrator": est["integrator"], "samples_per_pass": est["samples_per_pass"],
           "setup_seconds": est["setup_seconds"], "pilot_cpu": est_cpu,
           "tail_class": q.get("tail_class", "light"), "tails": q.get("tails"),
           "tail_note": q.get("tail_note"), "spp": t["cost"]["spp"],
           "seconds": t["cost"]["seconds"], "worker_seconds": t["cost"]["worker_seconds"],
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "load": os.getloadavg()[0]}
    out.write(json.dumps(rec) + "\n")
    out.flush()
    print(f"{name} {target}: {rec['tail_class']} spp {fmt(rec['spp'], 0)} "
          f"s {fmt(rec['seconds'])}", flush=True)
    with tempfile.TemporaryDirectory() as d:
        for seed in seeds:
            cmd = [binary, "render", *job, "--seed", str(seed), "-o", f"{d}/x.exr"]
            if limit:
                cmd += ["--time-limit", str(limit)]
            text, cpu, wall = timed(cmd)
            spp = float(re.search(r"samples per pixel: mean ([0-9.]+)", text).group(1))
            stopped = re.search(r"stopped: (.*)", text).group(1).strip()
            err = re.search(r"estimated relative error: ([0-9.]+)", text)
            r = {"kind": "render", "name": name, "target": target, "seed": seed, "cpu": cpu,
                 "wall": wall, "spp": spp, "stopped": stopped,
                 "error": float(err.group(1)) if err else None, "load": os.getloadavg()[0]}
            out.write(json.dumps(r) + "\n")
            out.flush()
            print(f"  seed {seed}: {cpu:.2f} CPU s, {spp:g} spp, {stopped}", flush=True)


def fmt(i, digits=2):
    return f"{i['estimate']:.{digits}f} [{i['low']:.{digits}f}, {i['high']:.{digits}f}]"


def spp_counts(rs):
    """The renders' spp as `value xcount`, a render cut by its time limit marked `+`."""
    counts = {}
    for r in rs:
        key = f"{r['spp']:g}" + ("" if r["stopped"] == "target error reached" else "+")
        counts[key] = counts.get(key, 0) + 1
    return ", ".join(f"{k} x{n}" if n > 1 else k for k, n in
                     sorted(counts.items(), key=lambda kv: float(kv[0].rstrip("+"))))


def interval_verdict(rs, i, key):
    """Renders inside an interval of `key`: a cut render past its high end missed it, one
    cut inside it says nothing."""
    done = [r for r in rs if r["stopped"] == "target error reached"]
    ok = sum(i["low"] <= r[key] <= i["high"] for r in done)
    left = sum(r[key] <= i["high"] for r in rs if r not in done)
    return f"{ok}/{len(rs)}" + (f" ({left} cut inside it)" if left else "")


def bound_verdict(rs, above):
    """How renders bear on a lower bound: a render at or above it (finished or cut) agrees,
    a finished one below it contradicts it, a cut one below it says nothing."""
    done = [r["stopped"] == "target error reached" for r in rs]
    ok = sum(above(r) for r in rs)
    bad = sum(not above(r) and d for r, d in zip(rs, done))
    left = len(rs) - ok - bad
    return f"{ok}/{len(rs)} at or above the bound" + (f", {bad} below" if bad else "") + (
        f", {left} cut below it" if left else "")


def records(path):
    """The quotes and renders recorded in `path` (JSON lines), keyed by (scene name,
    target): `{key: quote}` and `{key: [render, ...]}`."""
    quotes, renders = {}, {}
    for line in open(path):
        r = json.loads(line)
        key = (r["name"], r["target"])
        if r["kind"] == "quote":
            quotes[key] = r
            renders[key] = []
        else:
            renders.setdefault(key, []).append(r)
    return quotes, renders


def table(path):
    quotes, renders = records(path)
    print("| scene (technique, size) | target | alpha / share / g | class | quote: s [95%] "
          "(spp) | actual CPU s, fewest-most (spp x renders) | covered |")
    print("|---|---|---|---|---|---|---|")
    for key, q in quotes.items():
        rs = renders.get(key, [])
        tails = q["tails"] or {}
        a = tails.get("tail_index")
        g = tails.get("variance_growth")
        tl = (f"{a:.2f}" if a else "n/a") + f" / {tails.get('top_share', 0) * 100:.0f}% / " + \
            (f"{g:.2f}" if g else "n/a")
        s = q["seconds"]
        size = "x".join(q["flags"][i + 1] for i in (0, 2))
        cls = q["tail_class"]
        if cls == "unpredictable":
            covered = bound_verdict(rs, lambda r: r["cpu"] >= s["estimate"])
        else:
            covered = interval_verdict(rs, s, "cpu")
        cpus = sorted(r["cpu"] for r in rs)
        actual = (f"{cpus[0]:.2f}-{cpus[-1]:.2f} ({spp_counts(rs)})" if rs else "-")
        print(f"| {q['name']} ({q['integrator']}, {size}) | {q['target']:g} | {tl} | {cls} | "
              f"{fmt(s)} ({fmt(q['spp'], 0)}) | {actual} | {covered} |")


def requote(binary, path):
    """Quotes every scene and target of `path` again with `binary` (a build whose quote
    changed but whose renders did not: renders are bit-identical across builds) and judges
    the recorded renders against the new quote's spp interval. The pilot is deterministic,
    so a debug build gives the release build's class and spp; its seconds are a debug
    build's, so the seconds are derived: the recorded quote's seconds per spp at each end
    times the new spp."""
    quotes, renders = records(path)
    print("| scene (technique, size) | target | class | quote: spp [95%] | seconds (derived) "
          "| renders' spp | covered |")
    print("|---|---|---|---|---|---|---|")
    os.chdir(ROOT)
    for (name, target), old in quotes.items():
        job = [old["scene"], *old["flags"], *COMMON, "--target-error", str(target)]
        q = json.loads(subprocess.run([binary, "estimate", *job, "--json"], check=True,
                                      capture_output=True, text=True).stdout)["quote"]
        spp = q["targets"][0]["cost"]["spp"]
        rs = renders.get((name, target), [])
        # The old quote's seconds per spp at each end (its release build's cost per
        # pixel-pass) times the new spp: what the release build of the new quote says, up
        # to the spot checks' rounding.
        setup = old["setup_seconds"]
        secs = {k: setup + (old["seconds"][k] - setup) * spp[k] / old["spp"][k]
                for k in ("estimate", "low", "high")}
        if q["tail_class"] == "unpredictable":
            covered = bound_verdict(rs, lambda r: r["spp"] >= spp["estimate"])
        else:
            covered = (interval_verdict(rs, spp, "spp") + " by spp; "
                       + interval_verdict(rs, secs, "cpu") + " by CPU s (derived)")
        seen = spp_counts(rs)
        size = "x".join(old["flags"][i + 1] for i in (0, 2))
        cls = old["tail_class"] + (" -> " + q["tail_class"]
                                   if q["tail_class"] != old["tail_class"] else "")
        print(f"| {name} ({old['integrator']}, {size}) | {target:g} | {cls} | "
              f"{fmt(spp, 0)} (was {fmt(old['spp'], 0)}) | {fmt(secs)} | {seen} | {covered} |",
              flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("binary", nargs="?")
    ap.add_argument("--only", default="")
    ap.add_argument("--targets", default="0.05,0.02")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--out", default=os.path.join(ROOT, "out", "quote_coverage.jsonl"))
    ap.add_argument("--lock", default="/work/notes/heavy.lock")
    ap.add_argument("--table", action="store_true")
    ap.add_argument("--requote", metavar="BINARY")
    a = ap.parse_args()
    if a.table:
        return table(a.out)
    if a.requote:
        return requote(a.requote, a.out)
    if not a.binary:
        raise SystemExit("give the tessera binary")
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    only = set(filter(None, a.only.split(",")))
    seeds = range(a.first_seed, a.first_seed + a.seeds)
    os.chdir(ROOT)
    with open(a.out, "a") as out:
        for name, scene, flags, limit in SCENES:
            if only and name not in only:
                continue
            for target in map(float, a.targets.split(",")):
                with locked(a.lock):
                    batch(a.binary, name, scene, flags, limit, target, seeds, out)


if __name__ == "__main__":
    sys.exit(main())
