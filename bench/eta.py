#!/usr/bin/env python3
"""Measures the job status ETA against the actual finishing time.

Starts `tessera serve` (a coordinator and local workers) on free loopback ports, submits
one job per scene, polls its status every 0.1 s, and records the ETA the status reports
when 10%, 25% and 50% of the planned passes are merged. The predicted finishing time at
each point is `elapsed + eta_seconds`; the table compares it with the actual one, and a
`tessera estimate` quote of the same job, made before, alongside.

Usage: bench/eta.py [TESSERA_BINARY] (default target/release/tessera, else target/debug).
Not a test: it measures the clock, and its figures go to docs/benchmarks.md.
"""
import json, os, socket, subprocess, sys, tempfile, time, urllib.request

BIN = sys.argv[1] if len(sys.argv) > 1 else None
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
        s[f.lstrip("-").replace("-", "_")] = int(v)
    return s


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
