"""The client against a running coordinator with a worker.

Needs ``TESSERA_SERVER`` (the coordinator, started with ``--api-token`` set to
``TESSERA_API_TOKEN``), ``TESSERA_BIN`` (the ``tessera`` binary, for reference renders)
and ``TESSERA_TEST_DIR`` (a scratch directory); skipped without them. The end-to-end test
``tests/e2e/python_clients.rs`` starts the farm and runs this file.
"""

import hashlib
import json
import os
import subprocess
import struct
import sys
import uuid
import unittest

HERE = os.path.dirname(os.path.abspath(__file__))
PKG = os.path.dirname(HERE)
sys.path.insert(0, PKG)

from tessera_client import ApiError, Client, FrameRange, JobSettings, TesseraError, TransportError  # noqa: E402

REPO = os.path.abspath(os.path.join(HERE, "..", "..", ".."))
ANIMATED = os.path.join(REPO, "tests", "fixtures", "animation", "anim_cube.glb")
LIVE = all(os.environ.get(k) for k in ("TESSERA_SERVER", "TESSERA_API_TOKEN", "TESSERA_BIN", "TESSERA_TEST_DIR"))


def small_job(**kw) -> JobSettings:
    s = JobSettings(scene="", width=24, height=16, spp=16, seed=5, tile_size=8, fps=2.4)
    for k, v in kw.items():
        setattr(s, k, v)
    return s


def with_nonce(glb: bytes) -> bytes:
    """The same GLB with a random ``asset.extras.nonce``: the same scene under a hash no
    coordinator has seen, so that the first submission must upload it."""
    magic, version, _ = struct.unpack_from("<III", glb, 0)
    json_len, json_type = struct.unpack_from("<II", glb, 12)
    doc = json.loads(glb[20:20 + json_len])
    doc["asset"].setdefault("extras", {})["nonce"] = uuid.uuid4().hex
    j = json.dumps(doc, separators=(",", ":")).encode()
    j += b" " * (-len(j) % 4)
    rest = glb[20 + json_len:]
    head = struct.pack("<II", len(j), json_type) + j
    return struct.pack("<III", magic, version, 12 + len(head) + len(rest)) + head + rest


def render_local(scene: str, out: str, frame: int, extra=()):
    subprocess.run(
        [os.environ["TESSERA_BIN"], "render", scene, "--width", "24", "--height", "16",
         "--spp", "16", "--seed", "5", "--tile-size", "8", "--fps", "2.4",
         "--frame", str(frame), "-o", out, *extra],
        check=True, capture_output=True,
    )
    with open(out, "rb") as f:
        return f.read()


def radiance_hdr(width: int, height: int, texel) -> bytes:
    """A Radiance .hdr of flat RGBE scanlines, ``texel(x, y)`` the linear RGB of each."""
    import math

    out = bytearray(f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {height} +X {width}\n".encode())
    for y in range(height):
        for x in range(width):
            c = texel(x, y)
            m = max(c)
            mantissa, e = math.frexp(m)
            scale = mantissa * 256.0 / m
            out += bytes([min(255, int(v * scale)) for v in c] + [e + 128])
    return bytes(out)


@unittest.skipUnless(LIVE, "needs TESSERA_SERVER, TESSERA_API_TOKEN, TESSERA_BIN and TESSERA_TEST_DIR")
class AgainstARealFarm(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.c = Client()
        cls.dir = os.environ["TESSERA_TEST_DIR"]
        with open(ANIMATED, "rb") as f:
            cls.glb = f.read()

    def test_content_addressed_submit_wait_and_frames_equal_tessera_render(self):
        uploads = []
        glb = with_nonce(self.glb)
        scene = os.path.join(self.dir, "nonce.glb")
        with open(scene, "wb") as f:
            f.write(glb)
        job = self.c.submit_scene(
            glb, small_job(frames=FrameRange(0, 2), name="py-frames"), on_upload=uploads.append
        )
        self.assertEqual(job.scene, hashlib.sha256(glb).hexdigest())
        # A second job of the same bytes finds the scene on the coordinator: no upload.
        again = self.c.submit_scene(glb, small_job(frames=FrameRange(0, 0)), on_upload=uploads.append)
        self.assertEqual(len(uploads), 1, "the second submission uploaded the scene again")
        self.assertEqual(uploads[0].hash, job.scene)
        seen = []
        done = self.c.wait(job.id, on_progress=seen.append, every=0.1, timeout=240)
        self.assertEqual(done.state, "done", done.error)
        self.assertEqual(done.frames_done, 3)
        self.assertTrue(seen and seen[-1].state == "done")
        pattern = os.path.join(self.dir, "py", "frame_####.exr")
        paths = self.c.download_frames(job.id, pattern)
        self.assertEqual([os.path.basename(p) for p in paths],
                         ["frame_0000.exr", "frame_0001.exr", "frame_0002.exr"])
        for f, p in enumerate(paths):
            with open(p, "rb") as fh:
                farm = fh.read()
            local = render_local(scene, os.path.join(self.dir, f"local_{f}.exr"), f)
            self.assertEqual(hashlib.sha256(farm).hexdigest(), hashlib.sha256(local).hexdigest(),
                             f"frame {f}: the farm's EXR differs from tessera render's")
        self.assertEqual(self.c.wait(again.id, timeout=240).state, "done")

    def test_an_environment_image_lights_the_farm_job_as_tessera_render(self):
        sky = radiance_hdr(16, 8, lambda x, y: (0.5 + x / 4, 0.8, 1.0 if y < 4 else 0.3))
        path = os.path.join(self.dir, "sky.hdr")
        with open(path, "wb") as f:
            f.write(sky)
        with self.assertRaises(TesseraError):
            self.c.upload_environment(b"P6 not an HDR image")
        env = self.c.environment(path, strength=2.0, rotation_degrees=45.0)
        self.assertEqual(env["source"], hashlib.sha256(sky).hexdigest())
        s = small_job(name="py-environment", environment=env)
        job = self.c.submit_scene(self.glb, s)
        self.assertEqual(self.c.wait(job.id, timeout=240).state, "done")
        self.assertEqual(self.c.job(job.id).settings.environment["source"], env["source"])
        farm = self.c.image(job.id, "exr")
        local = render_local(
            ANIMATED, os.path.join(self.dir, "local_env.exr"), 0,
            ["--environment", path, "--environment-strength", "2", "--environment-rotation", "45"],
        )
        self.assertEqual(hashlib.sha256(farm).hexdigest(), hashlib.sha256(local).hexdigest(),
                         "the farm's EXR under the environment differs from tessera render's")

    def test_quote_names_targets_and_queues_nothing(self):
        before = [j.id for j in self.c.jobs(200)]
        q = self.c.quote_scene(self.glb, small_job(frames=FrameRange(0, 2), target_error=0.05))
        self.assertEqual(q.frames, 3)
        self.assertIn(0.05, [t.target for t in q.targets])
        self.assertTrue(all(t.seconds.low <= t.seconds.estimate <= t.seconds.high for t in q.targets))
        self.assertTrue(q.lines()[0].startswith("3 frame(s), 16 spp"))
        self.assertEqual(before, [j.id for j in self.c.jobs(200)])

    def test_api_errors_name_their_field(self):
        with self.assertRaises(ApiError) as e:
            self.c.submit(small_job(scene="builtin:cornell-box", spp=0))
        self.assertEqual((e.exception.status, e.exception.code, e.exception.field), (400, "invalid_field", "spp"))
        self.assertTrue(str(e.exception).startswith("spp"), str(e.exception))
        with self.assertRaises(ApiError) as e:
            self.c.submit(small_job(scene="builtin:cornell-box", adaptive="unbiased"))
        self.assertEqual(e.exception.field, "target_error")
        with self.assertRaises(ApiError) as e:
            self.c.job(10**12)
        self.assertEqual(e.exception.code, "not_found")

    def test_wrong_token_and_unreachable_server_are_messages(self):
        with self.assertRaises(ApiError) as e:
            Client(token="wrong").jobs()
        self.assertEqual((e.exception.status, e.exception.code), (401, "unauthorized"))
        self.assertIn("token", str(e.exception))
        with self.assertRaises(TransportError) as e:
            Client("http://127.0.0.1:9", timeout=5).jobs()
        self.assertIn("cannot reach http://127.0.0.1:9", str(e.exception))

    def test_cancel(self):
        job = self.c.submit(small_job(scene="builtin:cornell-box", width=64, height=64, spp=1 << 16, priority=-5))
        st = self.c.cancel(job.id)
        self.assertEqual(st.state, "canceled")
        self.assertEqual(self.c.job(job.id).state, "canceled")

    def test_command_line_submit_status_fetch(self):
        env = dict(os.environ, PYTHONPATH=PKG)
        out_pattern = os.path.join(self.dir, "cli", "out_##.exr")

        def run(*args):
            return subprocess.run([sys.executable, "-m", "tessera_client", *args],
                                  env=env, capture_output=True, text=True, timeout=300)

        r = run("submit", ANIMATED, "--width", "24", "--height", "16", "--spp", "16", "--seed", "5",
                "--fps", "2.4", "--frame-start", "1", "--frame-end", "2", "--wait", "-o", out_pattern)
        self.assertEqual(r.returncode, 0, r.stderr)
        self.assertIn("wrote " + os.path.join(self.dir, "cli", "out_02.exr"), r.stdout)
        job_id = int(r.stdout.split("job ", 1)[1].split()[0])
        r = run("status", str(job_id))
        self.assertEqual(r.returncode, 0, r.stderr)
        self.assertIn(f"job {job_id} done", r.stdout)
        r = run("fetch", str(job_id), "-o", os.path.join(self.dir, "cli", "again_####.exr"))
        self.assertEqual(r.returncode, 0, r.stderr)
        for f in (1, 2):
            with open(os.path.join(self.dir, "cli", f"out_{f:02d}.exr"), "rb") as a, \
                    open(os.path.join(self.dir, "cli", f"again_{f:04d}.exr"), "rb") as b:
                self.assertEqual(a.read(), b.read())
        # Failures are one line, exit 1, no traceback.
        r = run("status", "--token", "wrong")
        self.assertEqual(r.returncode, 1)
        self.assertNotIn("Traceback", r.stderr)
        self.assertIn("unauthorized", r.stderr)
        r = run("submit", "builtin:cornell-box", "--spp", "0")
        self.assertEqual(r.returncode, 1)
        self.assertTrue(r.stderr.startswith("error: spp"), r.stderr)


if __name__ == "__main__":
    unittest.main()
