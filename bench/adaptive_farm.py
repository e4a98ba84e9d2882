#!/usr/bin/env python3
"""Worker-seconds to a measured error on the farm: adaptive vs uniform.

For each scene, renders a converged reference once with `tessera render` (cached in
--cache, outside the repository), then starts `tessera serve --workers 2
--threads-per-worker 1 --spot-check-fraction 0` on free loopback ports and submits, one
at a time:

- uniform (`adaptive: off`) at a ladder of samples per pixel;
- `adaptive: unbiased` and `adaptive: sequential` at a ladder of target errors, with a
  large spp cap.

For every job it records the worker-seconds it cost, two ways:

- `cpu`: CPU seconds (user + system, /proc/PID/stat) of the two worker processes from
  submission to done: what the table uses, since it does not move with the machine's load;
- `render`: `tessera_worker_render_seconds_total` in /metrics over the job (the wall
  seconds the workers report for their units; inflated when the machine is loaded);

and the MEASURED relative RMS error of the job's EXR against the reference, defined as in
`tessera bench accuracy` (crates/tessera-cli/src/accuracy.rs): with `lum` the Rec. 709
luminance, `v_r` the reference's luminance variance of the mean and REL_EPS = 0.01,
`relMSE = max(0, mean over pixels of ((lum m - lum r)^2 - v_r) / (max(lum r, 0) + REL_EPS)^2)`
and the error is `sqrt(relMSE)`. Sequential stopping is biased (docs/ARCHITECTURE.md §3,
"Adaptive stopping"): its measured error includes the bias, which is the fair comparison.

Per scene and mode, the worker-seconds to reach the goal error (default 2%) are
interpolated on log-log axes between the runs that bracket it (as `time_to_reach` in
accuracy.rs); where a mode never reaches it, the table says so and a second table compares
the modes at the smallest error all of them reach.

Every run is appended to --cache/runs-<size>.jsonl and reused by later invocations with the
same binary (keyed by scene, size, mode, ladder value and the binary's SHA-256), so an
interrupted benchmark resumes where it stopped.

Usage: bench/adaptive_farm.py [--bin target/release/tessera] [--cache /work/bench-cache]
       [--size 64] [--scenes builtin:veach-mis,builtin:caustic] [--goal 0.02]
Not a test: it measures CPU time; its figures go to docs/benchmarks.md.
"""
import argparse, json, math, os, socket, subprocess, sys, tempfile, time, urllib.request

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from exr import read_exr  # noqa: E402

LUM = (0.2126, 0.7152, 0.0722)
REL_EPS = 0.01
REF_SEED = 0x5EED0001  # distinct from every run's seed (1, 2, ...)
TICK = os.sysconf("SC_CLK_TCK")


def parse_args():
    target = os.environ.get("CARGO_TARGET_DIR", "target")
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--bin", default=f"{target}/release/tessera", help="the tessera binary")
    p.add_argument("--cache", default="/work/bench-cache", help="references and runs (outside the repository)")
    p.add_argument("--size", type=int, default=64, help="width and height")
    p.add_argument("--scenes", default="builtin:veach-mis,builtin:caustic", help="comma-separated")
    p.add_argument("--modes", default="off,unbiased,sequential",
                   help="off, unbiased, sequential; an adaptive mode with -pN sets min_passes N")
    p.add_argument("--reference-spp", type=int, default=65536, help="samples per pixel of the references")
    p.add_argument("--uniform-spp", default="16,32,64,128,256,512,1024,2048,4096,8192", help="ladder of the uniform jobs")
    p.add_argument("--targets", default="0.2,0.1,0.05,0.035,0.025,0.018,0.0125,0.009", help="ladder of the adaptive jobs")
    p.add_argument("--adaptive-cap", type=int, default=16384, help="spp cap of adaptive jobs")
    p.add_argument("--goal", type=float, default=0.02, help="the measured error to reach")
    p.add_argument("--replicate", type=int, default=0,
                   help="another ladder with other seeds (seed + 1000 x N), kept beside the others")
    p.add_argument("--report-only", action="store_true", help="print the tables from the cache")
    return p.parse_args()


# ---- measurement -------------------------------------------------------------------------

def lum_of(ch, i, prefix=""):
    return sum(w * ch[prefix + c][i] for w, c in zip(LUM, "RGB"))


def measured_error(path, ref):
    img = read_exr(path)["channels"]
    r = ref["channels"]
    n = len(img["R"])
    if n != len(r["R"]):
        raise SystemExit(f"{path}: size differs from the reference")
    total = 0.0
    for i in range(n):
        lr = lum_of(r, i)
        d = lum_of(img, i) - lr
        vr = sum(w * w * r["variance." + c][i] for w, c in zip(LUM, "RGB"))
        total += (d * d - vr) / (max(lr, 0.0) + REL_EPS) ** 2
    return math.sqrt(max(0.0, total / n))


def estimated_error(path):
    rel = read_exr(path)["channels"]["relerr.Y"]
    return math.sqrt(sum(x * x for x in rel) / len(rel))


def reference(a, scene):
    name = scene.replace("builtin:", "").replace("/", "_")
    path = os.path.join(a.cache, f"ref-{name}-{a.size}x{a.size}-{a.reference_spp}spp.exr")
    if not os.path.exists(path):
        print(f"rendering the reference {path} ...", file=sys.stderr, flush=True)
        tmp = path + ".tmp.exr"
        out = subprocess.run(
            [a.bin, "render", scene, "--width", str(a.size), "--height", str(a.size),
             "--spp", str(a.reference_spp), "--seed", str(REF_SEED), "-o", tmp],
            check=True, capture_output=True, text=True).stdout
        with open(path + ".txt", "w") as f:
            f.write(out)
        os.rename(tmp, path)
    return path


# ---- the farm ----------------------------------------------------------------------------

def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def get(url, raw=False):
    with urllib.request.urlopen(url, timeout=30) as r:
        return r.read() if raw else json.load(r)


def post(url, body):
    req = urllib.request.Request(url, data=body, headers={"content-type": "application/json"})
    with urllib.request.urlopen(req, timeout=60) as r:
        return json.load(r)


def metric(base, name):
    text = get(base.replace("/api/v1", "/metrics"), raw=True).decode()
    for line in text.splitlines():
        if line.startswith(name + " ") or line.startswith(name + "{"):
            return float(line.rsplit(" ", 1)[1])
    return 0.0


def children(pid):
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    st = f.read()
            except OSError:
                continue
            fields = st[st.rindex(")") + 2:].split()
            if int(fields[1]) == pid:
                out.append(int(d))
    return out


def cpu_seconds(pids):
    total = 0
    for pid in pids:
        with open(f"/proc/{pid}/stat") as f:
            st = f.read()
        fields = st[st.rindex(")") + 2:].split()
        total += int(fields[11]) + int(fields[12])  # utime, stime (fields 14, 15)
    return total / TICK


class Farm:
    def __init__(self, a):
        self.http, self.grpc = free_port(), free_port()
        self.data = tempfile.mkdtemp(prefix="tessera-adaptive-bench-")
        self.proc = subprocess.Popen(
            [a.bin, "serve", "--workers", "2", "--threads-per-worker", "1",
             "--spot-check-fraction", "0", "--http", f"127.0.0.1:{self.http}",
             "--grpc", f"127.0.0.1:{self.grpc}", "--data", self.data, "--demo", "none"],
            stdout=subprocess.DEVNULL, stderr=open(os.path.join(self.data, "serve.log"), "w"))
        self.base = f"http://127.0.0.1:{self.http}/api/v1"
        for _ in range(600):
            try:
                if len(get(f"{self.base}/workers")["workers"]) >= 2:
                    break
            except Exception:
                pass
            time.sleep(0.1)
        else:
            raise SystemExit("the farm did not come up")
        self.workers = [p for p in children(self.proc.pid) if b"worker" in open(f"/proc/{p}/cmdline", "rb").read()]
        if len(self.workers) != 2:
            raise SystemExit(f"expected 2 worker processes, found {self.workers}")

    def run(self, settings, out_path):
        cpu0 = cpu_seconds(self.workers)
        rs0 = metric(self.base, "tessera_worker_render_seconds_total")
        pp0 = metric(self.base, "tessera_worker_pixel_passes_total")
        job = post(f"{self.base}/jobs", json.dumps(settings).encode())
        while True:
            st = get(f"{self.base}/jobs/{job['id']}")
            if st["state"] in ("done", "failed", "canceled"):
                break
            time.sleep(0.05)
        cpu1 = cpu_seconds(self.workers)
        rs1 = metric(self.base, "tessera_worker_render_seconds_total")
        pp1 = metric(self.base, "tessera_worker_pixel_passes_total")
        if st["state"] != "done":
            raise SystemExit(f"job {job['id']} {st['state']}: {st.get('error')}")
        with open(out_path, "wb") as f:
            f.write(get(f"{self.base}/jobs/{job['id']}/image?format=exr", raw=True))
        return {"cpu": cpu1 - cpu0, "render": rs1 - rs0, "pixel_passes": pp1 - pp0,
                "wall": st["elapsed_seconds"], "spp": st["spp_so_far"],
                "status_error": st["error_estimate"], "target_reached": st["target_reached"],
                "stop_reason": st["stop_reason"]}

    def close(self):
        self.proc.terminate()
        try:
            self.proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.proc.kill()


# ---- interpolation and tables ------------------------------------------------------------

def cost_to_reach(points, target):
    """As `time_to_reach` in accuracy.rs: the first crossing, log-log interpolated."""
    pts = sorted(p for p in points if p[0] > 0 and p[1] > 0)
    if not pts:
        return None
    if pts[0][1] <= target:
        return pts[0][0]
    for (t0, e0), (t1, e1) in zip(pts, pts[1:]):
        if e0 > target >= e1:
            f = (math.log(target) - math.log(e0)) / (math.log(e1) - math.log(e0))
            return math.exp(math.log(t0) + f * (math.log(t1) - math.log(t0)))
    return None


def label(mode):
    """`off`, `unbiased`, `sequential`, or either adaptive mode with `-pN`: --min-passes N."""
    name, _, pilot = mode.partition("-p")
    text = {"off": "uniform", "unbiased": "adaptive unbiased", "sequential": "adaptive sequential"}[name]
    return f"{text} (min passes {pilot})" if pilot else text


def job_settings(scene, size, seed, mode, param, cap):
    name, _, pilot = mode.partition("-p")
    s = {"scene": scene, "width": size, "height": size, "seed": seed, "adaptive": name}
    if name == "off":
        s["spp"] = int(param)
    else:
        s["spp"] = cap
        s["target_error"] = float(param)
    if pilot:
        s["min_passes"] = int(pilot)
    return s


def reach(rs, key, target):
    """Per replicate (a ladder run with its own seeds), the cost to reach `target`; the
    geometric mean over the replicates if every one reached it, else None."""
    per = [cost_to_reach([(r[key], r["measured"]) for r in rs if r.get("replicate", 0) == k], target)
           for k in sorted({r.get("replicate", 0) for r in rs})]
    if per and all(per):
        return math.exp(sum(math.log(c) for c in per) / len(per)), per
    return None, per


def fmt_reach(c, per):
    if c is None:
        return "not reached" if not any(per) else "not reached by every replicate (%s)" % ", ".join(
            "-" if p is None else "%.1f" % p for p in per)
    return "%.1f" % c + (" (%s)" % ", ".join("%.1f" % p for p in per) if len(per) > 1 else "")


def tables(a, runs):
    goal = a.goal
    modes = a.modes.split(",")
    lines = [f"Worker-seconds (CPU seconds of the 2 worker processes) to a measured {goal:.0%}, "
             f"{a.size}x{a.size}; beside them, the render seconds the workers reported (wall time of their units, "
             "inflated by load). With several replicates (ladders with other seeds): the geometric mean, "
             "each replicate in brackets.", "",
             "| scene | mode | worker CPU-s to %g%% | render s to %g%% | uniform / mode (CPU-s) | lowest measured error (at CPU-s) |" % (goal * 100, goal * 100),
             "|---|---|---|---|---|---|"]
    common_lines = []
    for scene in a.scenes.split(","):
        per = {m: [r for r in runs if r["scene"] == scene and r["mode"] == m] for m in modes}
        base = reach(per["off"], "cpu", goal)[0] if "off" in per else None
        for m in modes:
            if not per[m]:
                continue
            c, reps = reach(per[m], "cpu", goal)
            rs = reach(per[m], "render", goal)[0]
            low = min(per[m], key=lambda r: r["measured"])
            ratio = f"{base / c:.2f}" if (c and base) else "-"
            lines.append(f"| {scene} | {label(m)} | {fmt_reach(c, reps)} | "
                         f"{'%.1f' % rs if rs else '-'} | {ratio} | "
                         f"{'%.4f (%.1f)' % (low['measured'], low['cpu']) if low else '-'} |")
        # The smallest error every mode (that ran on this scene) reaches: the largest of the
        # modes' lowest errors.
        ran = [m for m in modes if per[m]]
        if "off" in ran and len(ran) > 1:
            common = max(min(r["measured"] for r in per[m] if r.get("replicate", 0) == k)
                         for m in ran for k in {r.get("replicate", 0) for r in per[m]}) * 1.0001
            cells = []
            cb = reach(per["off"], "cpu", common)[0]
            for m in modes:
                c = reach(per[m], "cpu", common)[0]
                cells.append(f"{c:.1f} ({cb / c:.2f})" if c and cb else "-")
            common_lines.append(f"| {scene} | {common:.4f} | " + " | ".join(cells) + " |")
    out = "\n".join(lines)
    if common_lines:
        out += ("\n\nAt the smallest measured error every mode reaches: worker CPU-s (uniform / mode):\n\n"
                "| scene | error | " + " | ".join(label(m) for m in modes) + " |\n|---|---|"
                + "---|" * len(modes) + "\n" + "\n".join(common_lines))
    return out


def runs_table(runs):
    out = ["| scene | mode | replicate | spp / target (cap) | spp in the image (mean) | worker CPU-s | render s | pixel-passes | measured error | estimated (status) | stop |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        cap = "" if r["mode"] == "off" else " (%d)" % r.get("cap", 16384)
        out.append(f"| {r['scene']} | {r['mode']} | {r.get('replicate', 0)} | {r['param']}{cap} | {r['spp']:.1f} | {r['cpu']:.2f} | "
                   f"{r['render']:.2f} | {int(r['pixel_passes'])} | {r['measured']:.4f} | "
                   f"{r['status_error'] if r['status_error'] is None else '%.4f' % r['status_error']} | "
                   f"{r['stop_reason'] or ''} |")
    return "\n".join(out)


def build_id(binary):
    """The binary's SHA-256 (12 hex digits): runs are reused only with the same binary."""
    import hashlib
    with open(binary, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()[:12]


def main():
    a = parse_args()
    os.makedirs(a.cache, exist_ok=True)
    version = build_id(a.bin)
    log = os.path.join(a.cache, f"runs-{a.size}.jsonl")
    runs = []
    if os.path.exists(log):
        with open(log) as f:
            runs = [json.loads(l) for l in f if l.strip()]
    # Adaptive runs are keyed by their spp cap too (records from before the field: 16384).
    cap_of = lambda r: 0 if r["mode"] == "off" else r.get("cap", 16384)
    done = {(r["scene"], r["mode"], r["param"], r["version"], cap_of(r), r.get("replicate", 0)) for r in runs}
    if not a.report_only:
        refs = {s: reference(a, s) for s in a.scenes.split(",")}
        farm = None
        try:
            for scene in a.scenes.split(","):
                ref = read_exr(refs[scene])
                print(f"reference {refs[scene]}: estimated error {estimated_error(refs[scene]):.5f}",
                      file=sys.stderr, flush=True)
                seed = 0
                for mode in a.modes.split(","):
                    ladder = a.uniform_spp if mode == "off" else a.targets
                    for param in ladder.split(","):
                        seed += 1
                        cap = 0 if mode == "off" else a.adaptive_cap
                        if (scene, mode, param, version, cap, a.replicate) in done:
                            continue
                        if farm is None:
                            farm = Farm(a)
                        s = job_settings(scene, a.size, seed + 1000 * a.replicate, mode, param, a.adaptive_cap)
                        out = os.path.join(farm.data, "out.exr")
                        r = farm.run(s, out)
                        r.update(scene=scene, mode=mode, param=param, version=version, seed=s["seed"], cap=cap, replicate=a.replicate,
                                 size=a.size, measured=measured_error(out, ref), uptime=os.getloadavg())
                        print(json.dumps(r), file=sys.stderr, flush=True)
                        with open(log, "a") as f:
                            f.write(json.dumps(r) + "\n")
                        runs.append(r)
        finally:
            if farm is not None:
                farm.close()
    runs = [r for r in runs if r["version"] == version and r["scene"] in a.scenes.split(",")]
    print(f"binary: {a.bin} (sha256 {version})\n")
    print(tables(a, runs))
    print("\nEvery run:\n")
    print(runs_table(runs))


if __name__ == "__main__":
    main()
