"""What the operators and the panel do, apart from drawing: the connection, the job from
the scene, the export, background work and polling, fetching frames.

Network calls never run on Blender's main thread in the interface: they run on a worker
thread, and their results are applied to Blender data by a ``bpy.app.timers`` function on
the main thread (Blender data must not be touched from other threads). In background mode
(``blender -b``, ``import bpy``) there is no interface to keep alive, so the same work runs
inline.
"""

import hashlib
import os
import queue
import tempfile
import threading
import time

import bpy

from ._client import tessera_client as tc
from .gltf_settings import ADDON_OVERRIDES, export_glb
from .props import ADDON_ID

#: Seconds between polls of running jobs.
POLL_SECONDS = 1.5

#: The JobSettings field an API error names, against the panel's property that sets it
#: (the panel draws that property in red).
FIELD_PROPERTIES = {
    "spp": "samples",
    "target_error": "target_error",
    "adaptive": "adaptive",
    "time_limit_seconds": "time_limit",
    "priority": "priority",
    "frames": "frame_start",
    "frames.start": "frame_start",
    "frames.end": "frame_end",
    "camera": "camera",
    "seed": "seed",
}


class UserError(Exception):
    """A problem to tell the user in one line (not the farm's)."""


# ---------------------------------------------------------------- connection


def connection():
    """(server, token, CA file) from the add-on's preferences, each falling back to the
    environment where unset (as ``tessera submit``: TESSERA_SERVER, TESSERA_API_TOKEN)."""
    prefs = None
    addon = bpy.context.preferences.addons.get(ADDON_ID)
    if addon is not None:
        prefs = addon.preferences
    server = (getattr(prefs, "server", "") or "").strip() or os.environ.get("TESSERA_SERVER") or tc.DEFAULT_SERVER
    token = (getattr(prefs, "token", "") or "").strip() or os.environ.get("TESSERA_API_TOKEN") or None
    ca = (getattr(prefs, "ca_file", "") or "").strip()
    ca = bpy.path.abspath(ca) if ca else (os.environ.get("TESSERA_TLS_CA") or None)
    return server, token, ca


def client():
    """A client for the configured coordinator."""
    server, token, ca = connection()
    return tc.Client(server, token, ca)


def describe(e):
    """An exception as one line for the user."""
    if isinstance(e, (tc.TesseraError, UserError)):
        return str(e)
    return f"{type(e).__name__}: {e}"


# ---------------------------------------------------------------- the job


def camera_of(scene):
    cam = scene.tessera.camera or scene.camera
    if cam is None or cam.type != "CAMERA":
        raise UserError("the scene has no camera: set the scene's camera or the Tessera panel's")
    return cam


def frame_range(scene):
    t = scene.tessera
    start, end = (scene.frame_start, scene.frame_end) if t.use_scene_range else (t.frame_start, t.frame_end)
    if start < 0 or end < start:
        raise UserError(f"frames: the range {start} to {end} is not one the farm renders (0 <= start <= end)")
    return start, end


def job_settings(scene):
    """The job of the scene's panel settings, resolution, frame range, fps and camera
    (``scene`` is filled in by the upload)."""
    t = scene.tessera
    r = scene.render
    start, end = frame_range(scene)
    pct = r.resolution_percentage / 100.0
    name = os.path.splitext(os.path.basename(bpy.data.filepath))[0] or "untitled"
    return tc.JobSettings(
        scene="",
        camera=camera_of(scene).name,
        width=max(1, int(r.resolution_x * pct)),
        height=max(1, int(r.resolution_y * pct)),
        spp=t.samples,
        seed=t.seed,
        frames=tc.FrameRange(start, end),
        fps=r.fps / r.fps_base,
        priority=t.priority,
        target_error=t.target_error or None,
        adaptive=t.adaptive,
        time_limit_seconds=t.time_limit or None,
        name=f"{name}: {scene.name}"[:200],
        shutter=shutter(scene),
    )


#: The first bytes of the environment images the farm reads: Radiance RGBE, OpenEXR.
_HDR_MAGIC = (b"#?", bytes([0x76, 0x2F, 0x31, 0x01]))


def world_environment(scene):
    """What lights the scene from around it, as the job's environment (glTF has no
    world, so it does not travel with the export): ``None`` without a world (or a black
    one); else ``(source, strength)``, ``source`` the bytes of the image of an Environment
    Texture node feeding the world's Background (a Radiance ``.hdr`` or OpenEXR file), or
    the Background's colour ``(r, g, b)`` (the world colour without nodes). Other nodes
    between the texture and the Background, and a Mapping node's rotation, are not read."""
    world = scene.world
    if world is None:
        return None
    # Blender 5 always uses a world's nodes (and deprecates the switch); before it a
    # world without them is its colour.
    nodes_off = bpy.app.version < (5, 0, 0) and not world.use_nodes
    if nodes_off or world.node_tree is None:
        colour, strength = tuple(world.color), 1.0
    else:
        out = next(
            (n for n in world.node_tree.nodes if n.type == "OUTPUT_WORLD" and n.is_active_output),
            None,
        ) or next((n for n in world.node_tree.nodes if n.type == "OUTPUT_WORLD"), None)
        links = out.inputs["Surface"].links if out is not None else ()
        if not links:
            return None
        bg = links[0].from_node
        if bg.type != "BACKGROUND":
            raise UserError(
                f"the world's surface is a {bg.bl_label} node: the farm reads a Background node "
                "(a colour, or an Environment Texture)"
            )
        strength = float(bg.inputs["Strength"].default_value)
        colour_links = bg.inputs["Color"].links
        if colour_links and colour_links[0].from_node.type == "TEX_ENVIRONMENT":
            return _environment_image(colour_links[0].from_node.image), strength
        if colour_links:
            raise UserError(
                f"the world's Background colour comes from a {colour_links[0].from_node.bl_label} "
                "node: the farm reads an Environment Texture or a plain colour"
            )
        colour = tuple(bg.inputs["Color"].default_value)[:3]
    if strength <= 0.0 or max(colour) <= 0.0:
        return None
    return tuple(float(c) for c in colour[:3]), strength


def _environment_image(image):
    """The bytes of an Environment Texture's image: packed, or its file."""
    if image is None:
        raise UserError("the world's Environment Texture has no image")
    if image.packed_file is not None:
        data = bytes(image.packed_file.data)
    else:
        path = bpy.path.abspath(image.filepath)
        try:
            with open(path, "rb") as f:
                data = f.read()
        except OSError as e:
            raise UserError(f"reading the world's image {path}: {e.strerror or e}") from None
    if not data.startswith(_HDR_MAGIC):
        raise UserError(
            f"the world's image {image.name} is not a Radiance .hdr or OpenEXR file: the farm "
            "lights scenes with equirectangular HDR images"
        )
    return data


def lit(c, settings, environment):
    """``settings`` with the environment of :func:`world_environment` (its image uploaded
    by ``c``); run with the request, off the interface's thread."""
    if environment is not None:
        source, strength = environment
        settings.environment = c.environment(source, strength)
    return settings


def shutter(scene):
    """Blender's motion blur as the job's shutter, in frames around the frame: Cycles'
    shutter length and position (start, centre or end on the frame); ``None`` without
    motion blur."""
    r = scene.render
    if not r.use_motion_blur:
        return None
    length = r.motion_blur_shutter
    position = getattr(getattr(scene, "cycles", None), "motion_blur_position", "CENTER")
    if position == "START":
        return [0.0, length]
    if position == "END":
        return [-length, 0.0]
    return [-length / 2.0, length / 2.0]


def export_dir():
    d = os.path.join(tempfile.gettempdir(), "tessera-blender")
    os.makedirs(d, exist_ok=True)
    return d


def export_scene(scene):
    """Exports ``scene`` as GLB with the shared settings; returns (path, bytes). The file
    is kept (``scene.tessera.last_export``) so a job can be reproduced with
    ``tessera render``."""
    window = bpy.context.window
    if window is not None and window.scene != scene:
        raise UserError(f"the exporter exports the window's scene, not {scene.name}")
    name = os.path.splitext(os.path.basename(bpy.data.filepath))[0] or "untitled"
    tmp = os.path.join(export_dir(), f"{name}-{scene.name}.{os.getpid()}.glb")
    try:
        export_glb(tmp, **ADDON_OVERRIDES)
    except RuntimeError as e:
        raise UserError(f"the glTF export failed: {e}") from None
    with open(tmp, "rb") as f:
        data = f.read()
    digest = hashlib.sha256(data).hexdigest()
    path = os.path.join(export_dir(), f"{digest}.glb")
    os.replace(tmp, path)
    scene.tessera.last_export = path
    return path, data


def output_pattern(scene):
    """Where the frames go: ``render.filepath`` with a run of ``#`` for the frame number
    (Blender's own rule: without one, four digits are appended) and an ``.exr`` extension."""
    path = bpy.path.abspath(scene.render.filepath or "//")
    if path.endswith(os.sep) or os.path.isdir(path) or not os.path.basename(path):
        path = os.path.join(path, "")
    head, base = os.path.split(path)
    if "#" not in base:
        base += "####"
    if not base.lower().endswith(".exr"):
        base += ".exr"
    return os.path.join(head, base)


# ---------------------------------------------------------------- errors in the panel


def set_message(scene, text, error=None):
    """Shows ``text`` in the panel; an API error's field is remembered so that the panel
    marks the property that set it."""
    t = scene.tessera
    t.message = text
    t.failed = error is not None
    field = getattr(error, "field", None) or ""
    t.error_field = FIELD_PROPERTIES.get(field, field)


# ---------------------------------------------------------------- background work

_done = queue.Queue()
_lock = threading.Lock()
_running = 0


def inline():
    """Whether requests run inline (background mode) rather than on threads (the
    interface). A function, so that a test can take the interface's path headless."""
    return bpy.app.background


def run(work, finish):
    """Runs ``work()`` and then ``finish(result, error)`` on the main thread. In the
    interface ``work`` runs on a thread of its own and ``finish`` on the next timer tick;
    in background mode both run now."""
    global _running
    if inline():
        try:
            r = work()
        except Exception as e:  # noqa: BLE001  (any failure becomes a message)
            finish(None, e)
        else:
            finish(r, None)
        return

    def target():
        global _running
        try:
            r, err = work(), None
        except Exception as e:  # noqa: BLE001
            r, err = None, e
        _done.put((finish, r, err))
        with _lock:
            _running -= 1

    with _lock:
        _running += 1
    threading.Thread(target=target, daemon=True, name="tessera").start()
    ensure_timer()


_last_poll = [0.0]
_polling = [False]


def _tick():
    """The timer: applies finished work, and every POLL_SECONDS polls the running jobs of
    every scene on a thread. Returns the seconds to the next tick, or None to stop."""
    while True:
        try:
            finish, r, err = _done.get_nowait()
        except queue.Empty:
            break
        try:
            finish(r, err)
        except Exception as e:  # noqa: BLE001  (a closed file, a removed scene)
            print(f"tessera: {describe(e)}")
    # Jobs still running, and finished ones whose frames are still to be fetched (once:
    # a failed fetch waits for the Fetch button rather than retrying every poll).
    pending = [(s.name, j.job_id) for s in bpy.data.scenes if hasattr(s, "tessera")
               for j in s.tessera.jobs
               if j.state not in tc.FINAL_STATES or (j.state == "done" and not j.fetched and not j.fetch_error)]
    now = time.monotonic()
    if pending and not _polling[0] and now - _last_poll[0] >= POLL_SECONDS:
        _last_poll[0] = now
        _polling[0] = True
        try:
            # Made here: the preferences are Blender data, read on the main thread only.
            c = client()
        except tc.TesseraError as e:
            _polled(None, e)
        else:
            run(lambda: _poll(c, pending), _polled)
    with _lock:
        busy = _running > 0
    if not pending and not busy and _done.empty():
        return None
    return 0.2 if busy else POLL_SECONDS / 3


def ensure_timer():
    if not bpy.app.background and not bpy.app.timers.is_registered(_tick):
        bpy.app.timers.register(_tick, first_interval=0.1, persistent=True)


def stop_timer():
    if bpy.app.timers.is_registered(_tick):
        bpy.app.timers.unregister(_tick)


def _poll(c, pending):
    out = []
    for scene_name, job_id in pending:
        try:
            out.append((scene_name, c.job(job_id), None))
        except tc.TesseraError as e:
            out.append((scene_name, job_id, e))
    return out


def _polled(results, err):
    _polling[0] = False
    if err is not None:
        for s in bpy.data.scenes:
            if hasattr(s, "tessera") and s.tessera.jobs:
                set_message(s, describe(err), err)
        return
    for scene_name, st, e in results:
        scene = bpy.data.scenes.get(scene_name)
        if scene is None:
            continue
        if e is not None:
            set_message(scene, f"job {st}: {describe(e)}", e)
            continue
        job = find_job(scene, st.id)
        if job is None:
            continue
        update_job(job, st)
        if st.state == "done" and not job.fetched and not _fetching.get((scene_name, st.id)):
            _fetching[(scene_name, st.id)] = True
            fetch_async(scene, job)


_fetching = {}


def find_job(scene, job_id):
    for j in scene.tessera.jobs:
        if j.job_id == job_id:
            return j
    return None


def update_job(job, st):
    """Copies a polled status into the job's row."""
    job.state = st.state
    job.frames_done = st.frames_done
    job.frames_total = st.frames_total
    job.error_estimate = -1.0 if st.error_estimate is None else st.error_estimate
    job.eta_seconds = -1.0 if st.eta_seconds is None else st.eta_seconds
    job.elapsed_seconds = st.elapsed_seconds
    job.message = st.error or st.stop_reason or ""


def add_job(scene, st, output, server):
    t = scene.tessera
    job = t.jobs.add()
    job.job_id = st.id
    job.server = server
    job.frame_start = st.settings.frames.start
    job.frame_end = st.settings.frames.end
    job.output = output
    update_job(job, st)
    t.active_job = len(t.jobs) - 1
    return job


# ---------------------------------------------------------------- fetching frames


def fetch_frames(c, job_id, pattern, start, end):
    """Downloads frames ``start..end`` of the job as EXR; returns the paths."""
    return c.download_frames(job_id, pattern, tc.FrameRange(start, end), "exr")


def fetch_async(scene, job):
    """Downloads the job's frames on a thread, then shows the last one."""
    scene_name, job_id = scene.name, job.job_id
    pattern, start, end = job.output or output_pattern(scene), job.frame_start, job.frame_end
    job.fetch_error = ""
    try:
        c = client()
    except tc.TesseraError as e:
        job.fetch_error = describe(e)
        set_message(scene, f"fetching job {job_id}: {describe(e)}", e)
        return

    def finish(paths, err):
        _fetching.pop((scene_name, job_id), None)
        s = bpy.data.scenes.get(scene_name)
        if s is None:
            return
        j = find_job(s, job_id)
        if err is not None:
            if j is not None:
                j.fetch_error = describe(err)
            set_message(s, f"fetching job {job_id}: {describe(err)}", err)
            return
        if j is not None:
            j.fetched = True
        set_message(s, f"job {job_id}: wrote {len(paths)} frame(s), last {paths[-1]}")
        show_image(paths[-1])

    run(lambda: fetch_frames(c, job_id, pattern, start, end), finish)


def show_image(path):
    """Loads ``path`` (reloading an image already loaded from it) and shows it in an Image
    Editor: the first one open, else a new window's."""
    img = bpy.data.images.load(path, check_existing=True)
    img.reload()
    if bpy.app.background:
        return img
    wm = bpy.context.window_manager
    for window in wm.windows:
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR":
                area.spaces.active.image = img
                return img
    try:
        bpy.ops.wm.window_new()
        area = bpy.context.window_manager.windows[-1].screen.areas[0]
        area.type = "IMAGE_EDITOR"
        area.spaces.active.image = img
    except (RuntimeError, IndexError, AttributeError):
        pass  # the image is loaded; a window is a convenience
    return img
