#!/usr/bin/env python3
"""Measures the job status ETA against the actual finishing time.

Starts `tessera serve` (a coordinator and local workers) on free loopback ports, submits
one job per scene, polls its status every 0.1 s, and records the ETA the status reports
when 10%, 25% and 50% of the planned passes are merged. The predicted finishing time at
each point is `elapsed + eta_seconds`; the table compares it with the actual one, and a
`tessera estimate` quote of the same job, made before, alongside.

With `--target`, jobs that stop at a target error (adaptive, with `target_error`)
instead: every poll is kept, and at the first poll past 10%, 25% and 50% of the actual
finishing time the table gives the predicted finish `elapsed + eta_seconds` (or "not
predictable"), the 95% interval `elapsed + [eta_low_seconds, eta_high_seconds]`, the
tail class, and whether the interval covers the actual finish.

Usage: bench/eta.py [--target] [TESSERA_BINARY] (default target/release/tessera, else
target/debug). Not a test: it measures the clock, and its figures go to docs/benchmarks.md.
"""
import json, os, socket, subprocess, sys, tempfile, time, urllib.request

ARGS = [a for a in sys.argv[1:] if a != "--target"]
TARGET = "--target" in sys.argv[1:]
BIN = ARGS[0] if ARGS else None
if BIN is None:
    target = os.environ.get("CARGO_TARGET_DIR", "target")
    for kind in ("release", "debug"):
        if os.path.exists(f"{target}/{kind}/tessera"):
            BIN = f"{target}/{kind}/tessera"
            break

# (scene, job flags): three kinds of scene, each about a minute on two workers.
JOBS = [
    ("builtin:cornell-box", ["--width", "256", "--height", "256", "--spp", "256"]),
    ("builtin:veach-mis", ["--width", "256", "--height", "192", "--spp", "256"]),
    ("scenes/glass-spot.gltf", ["--width", "192", "--height", "192", "--spp", "128"]),
]
# Jobs that stop at a target error (sequential adaptive stopping), small enough for the
# shared machine: the Cornell box (light tails), veach-mis (glossy highlights of small
# lights: heavy) and glass-spot (a bdpt caustic).
TARGET_JOBS = [
    ("builtin:cornell-box", ["--width", "64", "--height", "64", "--spp", "4096",
                             "--adaptive", "sequential", "--target-error", "0.03"]),
    ("builtin:veach-mis", ["--width", "64", "--height", "48", "--spp", "4096",
                           "--adaptive", "sequential", "--target-error", "0.05"]),
    ("scenes/glass-spot.gltf", ["--width", "48", "--height", "48", "--spp", "4096",
                                "--adaptive", "sequential", "--target-error", "0.08"]),
    # Unbiased: the pilot plans every pixel's passes, so the work left is known after it.
    ("builtin:veach-mis", ["--width", "64", "--height", "48", "--spp", "4096",
                           "--adaptive", "unbiased", "--target-error", "0.05"]),
    # Uniform with a target: on the farm it runs its planned passes (the target only
    # feeds the verdict), so its ETA is the passes left.
    ("builtin:cornell-box", ["--width", "64", "--height", "64", "--spp", "256",
                             "--target-error", "0.03"]),
]
# ETA_ONLY=0,2 runs those of TARGET_JOBS alone (to keep each locked run short).
if os.environ.get("ETA_ONLY"):
    TARGET_JOBS = [TARGET_JOBS[int(i)] for i in os.environ["ETA_ONLY"].split(",")]
WORKERS = int(os.environ.get("ETA_WORKERS", "2"))


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def get(url):
    with urllib.request.urlopen(url, timeout=10) as r:
        return json.load(r)


def post(url, body, content_type="application/json"):
    req = urllib.request.Request(url, data=body, headers={"content-type": content_type})
    with urllib.request.urlopen(req, timeout=60) as r:
        return json.load(r)


def settings(scene_ref, flags):
    s = {"scene": scene_ref}
    it = iter(flags)
    for f, v in zip(it, it):
        for kind in (int, float, str):
            try:
                s[f.lstrip("-").replace("-", "_")] = kind(v)
                break
            except ValueError:
                pass
    return s


def follow_target(base, scene, flags):
    """Runs one target job, keeping every poll; returns (polls, final status)."""
    ref = scene
    if not scene.startswith("builtin:"):
        with open(scene, "rb") as f:
            ref = post(f"{base}/scenes", f.read(), "model/gltf+json")["hash"]
    job = post(f"{base}/jobs", json.dumps(settings(ref, flags)).encode())
    polls = []
    while True:
        st = get(f"{base}/jobs/{job['id']}")
        if st["state"] in ("done", "failed", "canceled"):
            return polls, st
        if st["state"] == "running":
            polls.append(st)
        time.sleep(0.1)


def mark_note(st):
    """The status's reason at a mark, to the first colon (e.g. "not predictable yet")."""
    note = st.get("eta_note")
    return f" ({note.split(':')[0]})" if note else ""


def target_table(rows):
    """Marks at the first poll past 10%, 25% and 50% of the actual finishing time with an
    ETA; a build without the interval fields (before them) gives the point alone."""
    print("| scene | job | at | predicted finish (s) | 95% interval (s) | class | covered | actual (s), spp |")
    print("|---|---|---|---|---|---|---|---|")
    covered_n, marks_n, within20 = 0, 0, 0
    for scene, flags, polls, final in rows:
        actual = final["elapsed_seconds"]
        for m in (0.10, 0.25, 0.50):
            st = next((p for p in polls if p["elapsed_seconds"] >= m * actual
                       and (p.get("eta_low_seconds") is not None
                            or p.get("eta_seconds") is not None)), None)
            if st is None:
                print(f"| {scene} | {' '.join(flags)} | {m:.0%} | - | - | - | - | {actual:.1f} |")
                continue
            marks_n += 1
            el = st["elapsed_seconds"]
            if st["eta_seconds"] is None:
                pred = "not predictable"
            else:
                p = el + st["eta_seconds"]
                within20 += abs(p - actual) <= 0.2 * actual
                pred = f"{p:.1f} ({(p - actual) / actual * 100:+.0f}%)"
            if st.get("eta_low_seconds") is None:
                interval, covered = "-", "no interval"
            else:
                # A missing high end (an older build's unbounded interval) is infinity.
                high = st.get("eta_high_seconds")
                lo, hi = el + st["eta_low_seconds"], el + (float("inf") if high is None else high)
                interval = f"[{lo:.1f}, {hi:.1f}]"
                ok = lo <= actual <= hi
                covered_n += ok
                covered = "yes" if ok else ("no, above" if actual > hi else "no, below")
            print(f"| {scene} | {' '.join(flags)} | {m:.0%} ({el:.1f} s) | {pred} | {interval} "
                  f"| {st.get('eta_tail_class', '-')}{mark_note(st)} | {covered} | {actual:.1f}, {final['spp_so_far']:.0f} "
                  f"{'' if final['state'] == 'done' else final['state']} |")
        notes = {p.get("eta_note") for p in polls if p.get("eta_note")}
        for n in sorted(notes)[:1]:
            print(f"<!-- {scene}: {n} -->")
    print(f"\nmarks {marks_n}, intervals covering the finish {covered_n}, "
          f"point within 20% {within20}")


def main():
    http, grpc = free_port(), free_port()
    data = tempfile.mkdtemp(prefix="tessera-eta-")
    serve = subprocess.Popen(
        [BIN, "serve", "--workers", str(WORKERS), "--http", f"127.0.0.1:{http}",
         "--grpc", f"127.0.0.1:{grpc}", "--data", data, "--demo", "none"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    base = f"http://127.0.0.1:{http}/api/v1"
    rows = []
    try:
        for _ in range(300):
            try:
                if len(get(f"{base}/workers")["workers"]) >= WORKERS:
                    break
            except Exception:
                pass
            time.sleep(0.1)
        if TARGET:
            for scene, flags in TARGET_JOBS:
                polls, final = follow_target(base, scene, flags)
                rows.append((scene, flags, polls, final))
            return target_table(rows)
        for scene, flags in JOBS:
            quoted = json.loads(subprocess.run(
                [BIN, "estimate", scene, *flags, "--workers", str(WORKERS), "--threads", "1", "--json"],
                check=True, capture_output=True, text=True).stdout)["quote"]
            quote = dict(quoted["planned"]["seconds"], tail_class=quoted.get("tail_class", "light"))
            ref = scene
            if not scene.startswith("builtin:"):
                with open(scene, "rb") as f:
                    ref = post(f"{base}/scenes", f.read(), "model/gltf+json")["hash"]
            job = post(f"{base}/jobs", json.dumps(settings(ref, flags)).encode())
            marks, seen = {}, None
            while True:
                st = get(f"{base}/jobs/{job['id']}")
                frac = st["passes_done"] / max(1, st["passes_planned"])
                # A mark first seen once the job is done says nothing (the ETA is 0 then):
                # it is left out ("-").
                done = st["state"] in ("done", "failed", "canceled")
                for m in (0.10, 0.25, 0.50):
                    if m not in marks and frac >= m and st["eta_seconds"] is not None and not done:
                        marks[m] = (frac, st["elapsed_seconds"], st["eta_seconds"])
                if st["state"] in ("done", "failed", "canceled"):
                    seen = st
                    break
                time.sleep(0.1)
            actual = seen["elapsed_seconds"]
            rows.append((scene, flags, quote, marks, actual, seen["state"]))
    finally:
        serve.terminate()
        serve.wait(timeout=30)
    print(f"| scene | job | quote before (s) | at 10%: predicted finish (s) | at 25% | at 50% | actual (s) |")
    print("|---|---|---|---|---|---|---|")
    for scene, flags, quote, marks, actual, state in rows:
        cells = []
        for m in (0.10, 0.25, 0.50):
            if m in marks:
                frac, el, eta = marks[m]
                pred = el + eta
                cells.append(f"{pred:.1f} ({(pred - actual) / actual * 100:+.0f}%)")
            else:
                cells.append("-")
        q = f"{quote['estimate']:.1f} [{quote['low']:.1f}, {quote['high']:.1f}] ({(quote['estimate'] - actual) / actual * 100:+.0f}%)"
        # A heavy-tailed pilot widens the interval; an unpredictable one is a lower bound.
        if quote["tail_class"] != "light":
            q += f" {quote['tail_class']}"
        print(f"| {scene} | {' '.join(flags)} | {q} | {' | '.join(cells)} | {actual:.1f} {'' if state == 'done' else state} |")


if __name__ == "__main__":
    main()
