"""``python -m tessera_client submit|status|fetch|quote|cancel``: the client from a shell.

The server, token and CA file are ``--server`` (``TESSERA_SERVER``), ``--token``
(``TESSERA_API_TOKEN``) and ``--tls-ca``, as with ``tessera submit``. Errors are one line
on standard error and exit status 1, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys

from .client import Client, TesseraError
from .models import ADAPTIVE_MODES, FrameRange, JobSettings


def _connection(p: argparse.ArgumentParser) -> None:
    p.add_argument("--server", help="the coordinator's URL (default: $TESSERA_SERVER or http://127.0.0.1:8080)")
    p.add_argument("--token", help="API bearer token (default: $TESSERA_API_TOKEN)")
    p.add_argument("--tls-ca", metavar="FILE", help="CA certificate(s) (PEM) an https:// server's certificate must be issued by")


def _job_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="a .glb/.gltf file (uploaded unless the coordinator has it) or builtin:NAME")
    p.add_argument("--spp", type=int, default=64)
    p.add_argument("--width", type=int)
    p.add_argument("--height", type=int)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--camera")
    p.add_argument("--frame-start", type=int, default=0)
    p.add_argument("--frame-end", type=int, help="last frame, inclusive (default: the first)")
    p.add_argument("--fps", type=float, default=24.0)
    p.add_argument("--target-error", type=float)
    p.add_argument("--adaptive", choices=ADAPTIVE_MODES, default="off")
    p.add_argument("--time-limit", type=float, help="seconds")
    p.add_argument("--priority", type=int, default=0)
    p.add_argument("--name")
    p.add_argument("--environment", metavar="FILE|R,G,B",
                   help="light the scene with an equirectangular .hdr/.exr image (uploaded) or a uniform colour")
    p.add_argument("--environment-strength", type=float, default=1.0)
    p.add_argument("--environment-rotation", type=float, default=0.0, help="degrees about the up axis")


def _settings(a) -> JobSettings:
    return JobSettings(
        scene=a.scene,
        spp=a.spp,
        width=a.width,
        height=a.height,
        seed=a.seed,
        camera=a.camera,
        frames=FrameRange(a.frame_start, a.frame_end if a.frame_end is not None else a.frame_start),
        fps=a.fps,
        target_error=a.target_error,
        adaptive=a.adaptive,
        time_limit_seconds=a.time_limit,
        priority=a.priority,
        name=a.name,
    )


def _scene_bytes(scene: str):
    if scene.startswith("builtin:"):
        return None
    try:
        with open(scene, "rb") as f:
            return f.read()
    except OSError as e:
        raise TesseraError(f"reading {scene}: {e.strerror or e}") from None


def _progress():
    """A progress callback printing each new status line to standard error."""
    last = [""]

    def show(st):
        line = st.progress_line()
        if line != last[0]:
            print(line, file=sys.stderr, flush=True)
            last[0] = line

    return show


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tessera_client", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)

    p = sub.add_parser("submit", help="submit a job (uploading its scene if needed)")
    _job_args(p)
    _connection(p)
    p.add_argument("--wait", action="store_true", help="follow the job to its end")
    p.add_argument("-o", "--output", help="with --wait: write the frames here (a run of # is the frame number)")

    p = sub.add_parser("quote", help="quote a job (a dry run: nothing is queued)")
    _job_args(p)
    _connection(p)
    p.add_argument("--workers", type=int, help="the workers the quote assumes")
    p.add_argument("--json", action="store_true", help="print the server's answer")

    p = sub.add_parser("status", help="list the jobs, or show one")
    p.add_argument("job", type=int, nargs="?")
    _connection(p)
    p.add_argument("--json", action="store_true")

    p = sub.add_parser("fetch", help="download a job's frames")
    p.add_argument("job", type=int)
    p.add_argument("-o", "--output", required=True, help="file, with a run of # for the frame number (out_####.exr)")
    p.add_argument("--wait", action="store_true", help="wait for the job to end first")
    _connection(p)

    p = sub.add_parser("cancel", help="cancel a job")
    p.add_argument("job", type=int)
    _connection(p)

    a = ap.parse_args(argv)
    try:
        return _run(a)
    except TesseraError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


def _run(a) -> int:
    c = Client(a.server, a.token, a.tls_ca)
    if a.cmd in ("submit", "quote"):
        s = _settings(a)
        data = _scene_bytes(a.scene)
        if a.environment is not None:
            s.environment = c.environment(a.environment, a.environment_strength, a.environment_rotation)
        if a.cmd == "quote":
            q = c.quote(s, a.workers) if data is None else c.quote_scene(data, s, a.workers)
            if a.json:
                print(json.dumps(q.raw, indent=2))
            else:
                print("\n".join(q.lines()))
            return 0
        if a.output and not a.wait:
            raise TesseraError("-o/--output needs --wait")
        if data is None:
            job = c.submit(s)
        else:
            job = c.submit_scene(
                data, s, on_upload=lambda up: print(f"uploaded {a.scene} ({up.bytes} bytes, {up.triangles} triangles): {up.hash}")
            )
        print(f"job {job.id} {job.state}")
        if not a.wait:
            return 0
        return _finish(c, job.id, a.output)
    if a.cmd == "status":
        if a.job is None:
            for j in c.jobs():
                print(j.progress_line())
            return 0
        st = c.job(a.job)
        if a.json:
            print(json.dumps(c._json("GET", f"/jobs/{a.job}"), indent=2))
        else:
            print(st.progress_line())
            if st.error:
                print(f"error: {st.error}")
        return 0
    if a.cmd == "fetch":
        if a.wait:
            return _finish(c, a.job, a.output)
        for path in c.download_frames(a.job, a.output):
            print(f"wrote {path}")
        return 0
    if a.cmd == "cancel":
        print(c.cancel(a.job).progress_line())
        return 0
    return 2


def _finish(c: Client, job_id: int, output) -> int:
    done = c.wait(job_id, on_progress=_progress())
    print(done.progress_line())
    if done.stop_reason:
        print(f"stopped: {done.stop_reason}")
    if done.state != "done":
        raise TesseraError(f"job {job_id} ended {done.state}" + (f": {done.error}" if done.error else ""))
    if output:
        for path in c.download_frames(job_id, output, done.settings.frames):
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
