"""The extension in real Blender (the ``bpy`` module, headless) against a running farm.

Run with the Python that has ``bpy`` (``pip install bpy==5.0.1``, Python 3.11):
``python -m unittest discover -s clients/blender/tests``. Needs ``TESSERA_SERVER`` and
``TESSERA_API_TOKEN`` (a coordinator started with that token, with a worker),
``TESSERA_BIN`` (the ``tessera`` binary, for reference renders) and
``TESSERA_TEST_DIR`` (a scratch directory); the end-to-end test
``tests/e2e/python_clients.rs`` starts the farm and runs this file. Each test that talks
to the farm prints what it measured (``ROUNDTRIP``, ``QUOTE`` lines) for the test log.
"""

import glob
import hashlib
import os
import subprocess
import sys
import textwrap
import time
import unittest
import zipfile

HERE = os.path.dirname(os.path.abspath(__file__))
BLENDER_DIR = os.path.dirname(HERE)
sys.path.insert(0, BLENDER_DIR)

import bpy  # noqa: E402

import tessera_blender  # noqa: E402

ENV = ("TESSERA_SERVER", "TESSERA_API_TOKEN", "TESSERA_BIN", "TESSERA_TEST_DIR")
LIVE = all(os.environ.get(k) for k in ENV)
W, H, SPP = 32, 24, 16


def build_scene(out_pattern):
    """A small animated scene: a cube moving over a floor, a point light, a camera."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    s = bpy.context.scene
    s.render.resolution_x, s.render.resolution_y, s.render.resolution_percentage = W, H, 100
    s.render.fps, s.render.fps_base = 24, 1.0
    s.frame_start, s.frame_end = 1, 3
    s.render.filepath = out_pattern

    bpy.ops.mesh.primitive_plane_add(size=6.0, location=(0, 0, 0))
    floor = bpy.context.active_object
    m = bpy.data.materials.new("Floor")
    m.use_nodes = True
    m.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.7, 0.7, 0.7, 1)
    floor.data.materials.append(m)

    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(-1.0, 0, 0.5))
    cube = bpy.context.active_object
    cube.name = "Mover"
    m = bpy.data.materials.new("Red")
    m.use_nodes = True
    m.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.8, 0.1, 0.1, 1)
    cube.data.materials.append(m)
    cube.keyframe_insert("location", frame=1)
    cube.location = (1.0, 0.0, 0.5)
    cube.keyframe_insert("location", frame=3)

    light = bpy.data.lights.new("Key", "POINT")
    light.energy = 800.0
    lo = bpy.data.objects.new("Key", light)
    lo.location = (2.0, -2.0, 4.0)
    s.collection.objects.link(lo)

    cam = bpy.data.cameras.new("Cam")
    cam.angle = 0.9
    co = bpy.data.objects.new("Shot", cam)
    co.location = (0.0, -6.0, 3.0)
    co.rotation_euler = (1.1, 0.0, 0.0)
    s.collection.objects.link(co)
    s.camera = co
    t = s.tessera
    t.samples = SPP
    t.seed = 3
    return s


def radiance_hdr(path, width=16, height=8):
    """Writes a small equirectangular Radiance .hdr (flat RGBE scanlines): a blue sky over
    brown ground."""
    import math

    out = bytearray(f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {height} +X {width}\n".encode())
    for y in range(height):
        for x in range(width):
            c = (0.4 + x / 16, 0.6, 1.0) if y < height // 2 else (0.3, 0.2, 0.15)
            mantissa, e = math.frexp(max(c))
            scale = mantissa * 256.0 / max(c)
            out += bytes([min(255, int(v * scale)) for v in c] + [e + 128])
    with open(path, "wb") as f:
        f.write(out)
    return path


def set_world(scene, colour=(0.2, 0.3, 0.4), strength=1.0, image=None):
    """A world of nodes: a Background of ``colour``, or of an Environment Texture of the
    image file ``image``, at ``strength``, into the World Output."""
    w = bpy.data.worlds.new("Sky")
    if bpy.app.version < (5, 0, 0):
        w.use_nodes = True
    nodes, links = w.node_tree.nodes, w.node_tree.links
    nodes.clear()
    bg = nodes.new("ShaderNodeBackground")
    out = nodes.new("ShaderNodeOutputWorld")
    links.new(bg.outputs["Background"], out.inputs["Surface"])
    bg.inputs["Color"].default_value = (*colour, 1.0)
    bg.inputs["Strength"].default_value = strength
    if image is not None:
        tex = nodes.new("ShaderNodeTexEnvironment")
        tex.image = bpy.data.images.load(image)
        links.new(tex.outputs["Color"], bg.inputs["Color"])
    scene.world = w
    return w


def sha(path):
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


class Extension(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        tessera_blender.register()

    @classmethod
    def tearDownClass(cls):
        tessera_blender.unregister()

    def setUp(self):
        self.env = {k: os.environ.get(k) for k in ("TESSERA_API_TOKEN", "TESSERA_SERVER")}

    def tearDown(self):
        for k, v in self.env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v

    def test_operators_are_registered(self):
        for op in ("quote", "submit", "fetch", "cancel", "open_dashboard"):
            self.assertTrue(hasattr(bpy.ops.tessera, op), op)
        self.assertTrue(hasattr(bpy.types, "TESSERA_PT_render"))

    def test_the_panel_draws_every_state(self):
        # No window headless: the panel's draw code runs against a layout that accepts
        # every call, so a wrong property or operator name in it fails here.
        import types

        from tessera_blender import panel

        class Layout:
            def __getattr__(self, name):
                return lambda *a, **k: Layout()

        class Owner:
            layout = Layout()

        s = build_scene("/tmp/shots/shot_####.exr")
        t = s.tessera
        panel.TESSERA_PT_render.draw(Owner(), types.SimpleNamespace(scene=s))
        t.message, t.failed, t.error_field = "target_error: needs a target", True, "target_error"
        t.quote_text = "3 frame(s)\n5%: 1.0 s"
        job = t.jobs.add()
        job.job_id, job.state, job.eta_seconds, job.error_estimate, job.message = 5, "running", 130.0, 0.02, "x"
        t.use_scene_range, t.camera = False, s.camera
        panel.TESSERA_PT_render.draw(Owner(), types.SimpleNamespace(scene=s))
        panel.TESSERA_UL_jobs.draw_item(Owner(), None, Layout(), None, job, 0, None, "")
        t.jobs.clear()

    def test_output_pattern_follows_blenders_rule(self):
        from tessera_blender import core

        s = build_scene("/tmp/shots/shot_##.exr")
        self.assertEqual(core.output_pattern(s), "/tmp/shots/shot_##.exr")
        s.render.filepath = "/tmp/shots/"
        self.assertEqual(core.output_pattern(s), "/tmp/shots/####.exr")
        s.render.filepath = "/tmp/shots/take"
        self.assertEqual(core.output_pattern(s), "/tmp/shots/take####.exr")

    def test_job_settings_come_from_the_scene(self):
        from tessera_blender import core

        s = build_scene("/tmp/shots/shot_####.exr")
        s.render.resolution_percentage = 50
        s.render.fps, s.render.fps_base = 30, 1.001
        j = core.job_settings(s)
        self.assertEqual((j.width, j.height, j.camera, j.spp, j.seed), (W // 2, H // 2, "Shot", SPP, 3))
        self.assertEqual((j.frames.start, j.frames.end), (1, 3))
        self.assertAlmostEqual(j.fps, 30 / 1.001, places=4)  # fps_base is a float32
        self.assertIsNone(j.shutter)
        s.render.use_motion_blur = True
        s.render.motion_blur_shutter = 0.5
        self.assertEqual(core.job_settings(s).shutter, [-0.25, 0.25])
        s.tessera.use_scene_range = False
        s.tessera.frame_start, s.tessera.frame_end = 2, 1
        with self.assertRaises(core.UserError):
            core.job_settings(s)

    def test_the_world_is_the_jobs_environment(self):
        from tessera_blender import core

        s = build_scene("/tmp/shots/shot_####.exr")
        s.world = None
        self.assertIsNone(core.world_environment(s))
        set_world(s, colour=(0.25, 0.5, 0.75), strength=2.0)
        self.assertEqual(core.world_environment(s), ((0.25, 0.5, 0.75), 2.0))
        set_world(s, colour=(0.0, 0.0, 0.0))
        self.assertIsNone(core.world_environment(s), "a black world lights nothing")
        d = os.environ.get("TESSERA_TEST_DIR") or "/tmp"
        hdr = radiance_hdr(os.path.join(d, "world-sky.hdr"))
        set_world(s, strength=1.5, image=hdr)
        with open(hdr, "rb") as f:
            self.assertEqual(core.world_environment(s), (f.read(), 1.5))
        png = os.path.join(d, "world-sky.png")
        bpy.data.images.new("flat", 4, 2).save(filepath=png)
        set_world(s, image=png)
        with self.assertRaises(core.UserError) as e:
            core.world_environment(s)
        self.assertIn("not a Radiance .hdr or OpenEXR", str(e.exception))

    @unittest.skipUnless(LIVE, "needs " + ", ".join(ENV))
    def test_the_worlds_environment_texture_lights_the_farm_job_as_tessera_render(self):
        d = os.path.join(os.environ["TESSERA_TEST_DIR"], "world")
        os.makedirs(d, exist_ok=True)
        s = build_scene(os.path.join(d, "world_####.exr"))
        s.frame_start = s.frame_end = 1
        hdr = radiance_hdr(os.path.join(d, "sky.hdr"))
        set_world(s, strength=1.5, image=hdr)
        self.assertEqual(bpy.ops.tessera.submit(wait=True), {"FINISHED"}, s.tessera.message)
        farm = os.path.join(d, "world_0001.exr")
        local = os.path.join(d, "local.exr")
        subprocess.run(
            [os.environ["TESSERA_BIN"], "render", s.tessera.last_export, "--camera", "Shot",
             "--width", str(W), "--height", str(H), "--spp", str(SPP), "--seed", "3", "--fps", "24",
             "--frame", "1", "--environment", hdr, "--environment-strength", "1.5", "-o", local],
            check=True, capture_output=True,
        )
        self.assertEqual(sha(farm), sha(local), "the farm's frame under the world differs")

    @unittest.skipUnless(LIVE, "needs " + ", ".join(ENV))
    def test_three_frames_round_trip_byte_identical_to_tessera_render(self):
        d = os.path.join(os.environ["TESSERA_TEST_DIR"], "roundtrip")
        s = build_scene(os.path.join(d, "shot_####.exr"))
        t0 = time.monotonic()
        self.assertEqual(bpy.ops.tessera.quote(), {"FINISHED"}, s.tessera.message)
        quote_seconds = time.monotonic() - t0
        quote = s.tessera.quote_text
        t0 = time.monotonic()
        self.assertEqual(bpy.ops.tessera.submit(wait=True), {"FINISHED"}, s.tessera.message)
        wall = time.monotonic() - t0
        job = s.tessera.jobs[-1]
        self.assertEqual((job.state, job.frames_done, job.frames_total, job.fetched), ("done", 3, 3, True))
        frames = sorted(glob.glob(os.path.join(d, "shot_*.exr")))
        self.assertEqual([os.path.basename(p) for p in frames], ["shot_0001.exr", "shot_0002.exr", "shot_0003.exr"])
        glb = s.tessera.last_export
        self.assertTrue(os.path.isfile(glb), glb)
        self.assertEqual(os.path.basename(glb), sha(glb) + ".glb")
        for f, farm in zip((1, 2, 3), frames):
            local = os.path.join(d, f"local_{f}.exr")
            subprocess.run(
                [os.environ["TESSERA_BIN"], "render", glb, "--camera", "Shot", "--width", str(W),
                 "--height", str(H), "--spp", str(SPP), "--seed", "3", "--fps", "24",
                 "--frame", str(f), "-o", local],
                check=True, capture_output=True,
            )
            print(f"ROUNDTRIP frame {f}: farm {os.path.getsize(farm)} bytes sha256 {sha(farm)}; "
                  f"tessera render {os.path.getsize(local)} bytes sha256 {sha(local)}", flush=True)
            self.assertEqual(sha(farm), sha(local), f"frame {f}")
        # The cube moves: the frames are three different images.
        self.assertEqual(len({sha(p) for p in frames}), 3)
        # The last frame is loaded as an image.
        self.assertIn("shot_0003.exr", [os.path.basename(i.filepath) for i in bpy.data.images])
        print(f"ROUNDTRIP scene {os.path.getsize(glb)} bytes sha256 {sha(glb)}", flush=True)
        print("QUOTE " + " | ".join(quote.split("\n")) + f" | quote took {quote_seconds:.1f} s; "
              f"submit+wait+fetch took {wall:.1f} s", flush=True)

    @unittest.skipUnless(LIVE, "needs " + ", ".join(ENV))
    def test_the_interfaces_path_submits_on_a_thread_and_polls_on_the_timer(self):
        # What the panel's buttons do in the interface, driven headless: the operators
        # return at once, requests run on threads, and the timer function (called here as
        # Blender's event loop would) applies their results, polls and fetches the frames.
        from tessera_blender import core

        d = os.path.join(os.environ["TESSERA_TEST_DIR"], "interface")
        s = build_scene(os.path.join(d, "ui_####.exr"))
        s.frame_end = 2
        saved = core.inline
        core.inline = lambda: False
        try:
            self.assertEqual(bpy.ops.tessera.quote(), {"FINISHED"})
            # The quote is under way on its thread; the panel's buttons wait for it.
            self.assertTrue(s.tessera.busy)
            self.assertEqual(bpy.ops.tessera.submit(), {"CANCELLED"})
            deadline = time.monotonic() + 120
            while s.tessera.busy and time.monotonic() < deadline:
                core._tick()
                time.sleep(0.05)
            self.assertEqual(bpy.ops.tessera.submit(), {"FINISHED"}, s.tessera.message)
            while time.monotonic() < deadline:
                core._tick()
                if not s.tessera.busy and len(s.tessera.jobs) and s.tessera.jobs[-1].fetched:
                    break
                time.sleep(0.05)
        finally:
            core.inline = saved
        self.assertTrue(s.tessera.quote_text.startswith("2 frame(s)"), s.tessera.quote_text)
        job = s.tessera.jobs[-1]
        self.assertEqual((job.state, job.frames_done, job.fetched), ("done", 2, True), s.tessera.message)
        self.assertEqual(sorted(os.listdir(d)), ["ui_0001.exr", "ui_0002.exr"])
        self.assertIn("wrote 2 frame(s)", s.tessera.message)

    @unittest.skipUnless(LIVE, "needs " + ", ".join(ENV))
    def test_quote_fills_the_panel_and_queues_nothing(self):
        from tessera_blender import core

        s = build_scene(os.path.join(os.environ["TESSERA_TEST_DIR"], "quote", "q_####.exr"))
        s.tessera.target_error = 0.05
        before = [j.id for j in core.client().jobs(200)]
        self.assertEqual(bpy.ops.tessera.quote(), {"FINISHED"}, s.tessera.message)
        lines = s.tessera.quote_text.split("\n")
        self.assertTrue(lines[0].startswith(f"3 frame(s), {SPP} spp"), lines)
        self.assertTrue(any(line.startswith("5%: ") for line in lines), lines)
        self.assertEqual(before, [j.id for j in core.client().jobs(200)])
        self.assertEqual(len(s.tessera.jobs), 0)

    @unittest.skipUnless(LIVE, "needs " + ", ".join(ENV))
    def test_api_errors_name_the_field_in_the_panel(self):
        s = build_scene(os.path.join(os.environ["TESSERA_TEST_DIR"], "err", "e_####.exr"))
        s.tessera.adaptive = "unbiased"  # without a target error: refused, naming target_error
        self.assertEqual(bpy.ops.tessera.submit(), {"CANCELLED"})
        self.assertEqual(s.tessera.error_field, "target_error")
        self.assertTrue(s.tessera.failed)
        self.assertIn("target_error", s.tessera.message)
        self.assertEqual(len(s.tessera.jobs), 0)

    @unittest.skipUnless(LIVE, "needs " + ", ".join(ENV))
    def test_wrong_token_and_unreachable_server_are_messages_not_tracebacks(self):
        # A script as a farm of farms would run it: a fresh interpreter, the add-on from
        # clients/blender, the wrong token from the environment.
        script = textwrap.dedent(f"""
            import sys
            sys.path.insert(0, {BLENDER_DIR!r})
            import bpy, tessera_blender
            tessera_blender.register()
            bpy.ops.mesh.primitive_cube_add()
            cam = bpy.data.objects.new("C", bpy.data.cameras.new("C"))
            bpy.context.scene.collection.objects.link(cam)
            bpy.context.scene.camera = cam
            r = bpy.ops.tessera.submit(wait=True)
            print("RESULT", sorted(r), bpy.context.scene.tessera.message)
        """)
        for env, expect in (
            ({"TESSERA_API_TOKEN": "wrong"}, "unauthorized"),
            ({"TESSERA_SERVER": "http://127.0.0.1:9"}, "cannot reach http://127.0.0.1:9"),
        ):
            p = subprocess.run([sys.executable, "-c", script], env=dict(os.environ, **env),
                               capture_output=True, text=True, timeout=120)
            self.assertEqual(p.returncode, 0, p.stderr)
            self.assertNotIn("Traceback", p.stderr + p.stdout)
            self.assertIn("RESULT ['CANCELLED']", p.stdout)
            self.assertIn(expect, p.stdout)
            self.assertIn(f"Tessera: ", p.stderr)
            print(f"MESSAGE {[ln for ln in p.stderr.splitlines() if ln.startswith('Tessera: ')][-1]}")


class ExtensionZip(unittest.TestCase):
    """The zip clients/blender/build.py makes passes Blender's own validator (the code of
    ``blender --command extension validate``, which the bpy module ships as
    ``addons_core/bl_pkg/cli/blender_ext.py``), and installs and works as an extension."""

    def test_zip_validates_and_installs(self):
        out = os.environ.get("TESSERA_TEST_DIR") or os.path.join(BLENDER_DIR, "dist")
        zpath = subprocess.run([sys.executable, os.path.join(BLENDER_DIR, "build.py"), "-o", out],
                               check=True, capture_output=True, text=True).stdout.strip()
        with zipfile.ZipFile(zpath) as z:
            names = z.namelist()
        self.assertIn("blender_manifest.toml", names)
        self.assertIn("vendor/tessera_client/client.py", names)
        self.assertIn("gltf_settings.py", names)
        cli = os.path.join(bpy.utils.system_resource("SCRIPTS"), "addons_core", "bl_pkg", "cli", "blender_ext.py")
        self.assertTrue(os.path.isfile(cli), cli)
        p = subprocess.run([sys.executable, cli, "validate", zpath], capture_output=True, text=True)
        print(f"VALIDATE {zpath}: {p.stdout.strip()} {p.stderr.strip()}", flush=True)
        self.assertEqual(p.returncode, 0, p.stdout + p.stderr)
        # Installed from the zip into a throwaway user directory, the extension loads its
        # vendored client (not the repository's) and registers its operators.
        user = os.path.join(out, "blender-user")
        script = textwrap.dedent(f"""
            import os, sys
            sys.path[:] = [p for p in sys.path if "clients" not in p]
            import bpy
            bpy.ops.extensions.package_install_files(filepath={zpath!r}, repo="user_default", enable_on_install=True)
            mod = sys.modules["bl_ext.user_default.tessera"]
            from bl_ext.user_default.tessera import _client
            print("CLIENT", _client.tessera_client.__file__)
            print("OPS", hasattr(bpy.ops.tessera, "submit"), hasattr(bpy.types, "TESSERA_PT_render"))
        """)
        p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                           env=dict(os.environ, BLENDER_USER_RESOURCES=user, PYTHONPATH=""))
        self.assertEqual(p.returncode, 0, p.stdout + p.stderr)
        self.assertIn("OPS True True", p.stdout, p.stdout + p.stderr)
        client_file = [ln for ln in p.stdout.splitlines() if ln.startswith("CLIENT ")][0]
        self.assertIn(os.path.join("tessera", "vendor", "tessera_client"), client_file)


if __name__ == "__main__":
    unittest.main()
