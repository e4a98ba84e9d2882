"""``bpy.ops.tessera.*``: quote, submit, fetch, cancel, open in the dashboard.

Usable from scripts and headless (``blender -b file.blend --python-expr
"import bpy; bpy.ops.tessera.submit(wait=True)"``). A failure is reported as one line (in
the interface's status bar and the panel; on standard error in background mode) and the
operator returns ``{'CANCELLED'}``: in background mode it is reported as a warning, since
an error report would make ``bpy.ops`` raise, and a script would end in a traceback for a
network failure or a wrong token. ``scene.tessera.message`` holds the last message either
way.
"""

import sys
import webbrowser

import bpy
from bpy.props import BoolProperty, FloatProperty, IntProperty

from . import core
from ._client import tessera_client as tc


def _fail(op, scene, e):
    msg = core.describe(e)
    core.set_message(scene, msg, e)
    if bpy.app.background:
        print(f"Tessera: {msg}", file=sys.stderr, flush=True)
        op.report({"WARNING"}, msg)
    else:
        op.report({"ERROR"}, msg)
    return {"CANCELLED"}


def _info(op, scene, msg):
    core.set_message(scene, msg)
    if bpy.app.background:
        print(f"Tessera: {msg}", flush=True)
    op.report({"INFO"}, msg)


def _job_for(scene, job_id):
    """The job ``job_id`` of this scene, or its latest for 0."""
    jobs = scene.tessera.jobs
    if job_id:
        return core.find_job(scene, job_id)
    return jobs[-1] if len(jobs) else None


class TESSERA_OT_quote(bpy.types.Operator):
    """Quote the job: the farm renders a short pilot and predicts the seconds and
    worker-seconds to reach each target error (nothing is queued)"""

    bl_idname = "tessera.quote"
    bl_label = "Quote"

    workers: IntProperty(name="Workers", description="The workers the quote assumes (0: the connected ones)", default=0, min=0)

    def execute(self, context):
        scene = context.scene
        t = scene.tessera
        if t.busy:
            return _fail(self, scene, core.UserError("a request is already under way"))
        try:
            s = core.job_settings(scene)
            c = core.client()
            _, data = core.export_scene(scene)
            env = core.world_environment(scene)
        except (core.UserError, tc.TesseraError) as e:
            return _fail(self, scene, e)
        workers = self.workers or None
        t.busy = True
        t.quote_text = ""
        core.set_message(scene, "quoting...")
        scene_name = scene.name
        result = {}

        def finish(q, err):
            sc = bpy.data.scenes.get(scene_name)
            if sc is None:
                return
            sc.tessera.busy = False
            if err is not None:
                result["error"] = err
                core.set_message(sc, f"quote: {core.describe(err)}", err)
                return
            sc.tessera.quote_text = "\n".join(q.lines())
            core.set_message(sc, "")
            result["quote"] = q

        core.run(lambda: c.quote_scene(data, core.lit(c, s, env), workers), finish)
        if core.inline():
            if "error" in result:
                return _fail(self, scene, result["error"])
            _info(self, scene, "quote: " + "; ".join(result["quote"].lines()))
        return {"FINISHED"}


class TESSERA_OT_submit(bpy.types.Operator):
    """Export the scene as glTF, upload it unless the farm has it, and submit its frames
    (with wait: block until the job ends and fetch its frames to the output path)"""

    bl_idname = "tessera.submit"
    bl_label = "Submit"

    wait: BoolProperty(
        name="Wait",
        description="Block until the job ends and fetch its frames (for scripts and background mode)",
        default=False,
    )
    timeout: FloatProperty(name="Timeout", description="With wait: seconds to give up after", default=86400.0, min=1.0)

    def execute(self, context):
        scene = context.scene
        t = scene.tessera
        if t.busy and not self.wait:
            return _fail(self, scene, core.UserError("a request is already under way"))
        try:
            s = core.job_settings(scene)
            c = core.client()
            _, data = core.export_scene(scene)
            env = core.world_environment(scene)
        except (core.UserError, tc.TesseraError) as e:
            return _fail(self, scene, e)
        pattern = core.output_pattern(scene)
        if s.frames.count() > 1 and tc.frame_pattern(pattern) is None:
            return _fail(self, scene, core.UserError(f"the output path {pattern} needs a run of # for the frame number"))
        scene_name, server = scene.name, c.server
        if self.wait:
            return self._submit_and_wait(scene, c, data, s, env, pattern)
        t.busy = True
        core.set_message(scene, "submitting...")
        result = {}

        def finish(st, err):
            sc = bpy.data.scenes.get(scene_name)
            if sc is None:
                return
            sc.tessera.busy = False
            if err is not None:
                result["error"] = err
                core.set_message(sc, f"submit: {core.describe(err)}", err)
                return
            core.add_job(sc, st, pattern, server)
            core.set_message(sc, f"job {st.id} {st.state}")
            core.ensure_timer()

        core.run(lambda: c.submit_scene(data, core.lit(c, s, env)), finish)
        if "error" in result:
            return _fail(self, scene, result["error"])
        return {"FINISHED"}

    def _submit_and_wait(self, scene, c, data, s, env, pattern):
        try:
            st = c.submit_scene(data, core.lit(c, s, env))
        except tc.TesseraError as e:
            return _fail(self, scene, e)
        job = core.add_job(scene, st, pattern, c.server)
        _info(self, scene, f"job {st.id} {st.state}")
        last = [""]

        def progress(status):
            line = status.progress_line()
            if line != last[0]:
                print(line, flush=True)
                last[0] = line

        try:
            done = c.wait(st.id, on_progress=progress, timeout=self.timeout)
        except tc.TesseraError as e:
            return _fail(self, scene, e)
        core.update_job(job, done)
        if done.state != "done":
            return _fail(self, scene, core.UserError(f"job {done.id} ended {done.state}" + (f": {done.error}" if done.error else "")))
        try:
            paths = core.fetch_frames(c, st.id, pattern, job.frame_start, job.frame_end)
        except tc.TesseraError as e:
            return _fail(self, scene, e)
        job.fetched = True
        core.show_image(paths[-1])
        _info(self, scene, f"job {st.id} done: wrote {len(paths)} frame(s), last {paths[-1]}")
        return {"FINISHED"}


class TESSERA_OT_fetch(bpy.types.Operator):
    """Download the job's frames as EXR to the scene's output path"""

    bl_idname = "tessera.fetch"
    bl_label = "Fetch"

    job_id: IntProperty(name="Job", description="The job (0: this scene's latest)", default=0, min=0)

    def execute(self, context):
        scene = context.scene
        job = _job_for(scene, self.job_id)
        try:
            c = core.client()
            if job is not None:
                pattern, start, end, job_id = job.output or core.output_pattern(scene), job.frame_start, job.frame_end, job.job_id
            elif self.job_id:
                st = c.job(self.job_id)
                f = st.settings.frames
                pattern, start, end, job_id = core.output_pattern(scene), f.start, f.end, st.id
            else:
                raise core.UserError("this scene has no Tessera job to fetch")
            if end > start and tc.frame_pattern(pattern) is None:
                raise core.UserError(f"the output path {pattern} needs a run of # for the frame number")
        except (core.UserError, tc.TesseraError) as e:
            return _fail(self, scene, e)
        if not core.inline() and job is not None:
            core.fetch_async(scene, job)
            return {"FINISHED"}
        try:
            paths = core.fetch_frames(c, job_id, pattern, start, end)
        except tc.TesseraError as e:
            return _fail(self, scene, e)
        if job is not None:
            job.fetched = True
        core.show_image(paths[-1])
        _info(self, scene, f"job {job_id}: wrote {len(paths)} frame(s), last {paths[-1]}")
        return {"FINISHED"}


class TESSERA_OT_cancel(bpy.types.Operator):
    """Cancel the job on the farm"""

    bl_idname = "tessera.cancel"
    bl_label = "Cancel"

    job_id: IntProperty(name="Job", description="The job (0: this scene's latest)", default=0, min=0)

    def execute(self, context):
        scene = context.scene
        job = _job_for(scene, self.job_id)
        job_id = job.job_id if job is not None else self.job_id
        if not job_id:
            return _fail(self, scene, core.UserError("this scene has no Tessera job to cancel"))
        try:
            st = core.client().cancel(job_id)
        except tc.TesseraError as e:
            return _fail(self, scene, e)
        if job is not None:
            core.update_job(job, st)
        _info(self, scene, f"job {job_id} {st.state}")
        return {"FINISHED"}


class TESSERA_OT_open_dashboard(bpy.types.Operator):
    """Open the job's page of the farm's dashboard in a web browser"""

    bl_idname = "tessera.open_dashboard"
    bl_label = "Open in Dashboard"

    job_id: IntProperty(name="Job", default=0, min=0)

    def execute(self, context):
        scene = context.scene
        try:
            url = core.client().dashboard_url(self.job_id or None)
        except tc.TesseraError as e:
            return _fail(self, scene, e)
        if bpy.app.background:
            print(url)
        elif not bpy.ops.wm.url_open(url=url) == {"FINISHED"}:
            webbrowser.open(url)
        return {"FINISHED"}


class TESSERA_OT_remove_job(bpy.types.Operator):
    """Forget the job in this file (the farm keeps it)"""

    bl_idname = "tessera.remove_job"
    bl_label = "Remove from List"

    index: IntProperty(default=-1)

    def execute(self, context):
        jobs = context.scene.tessera.jobs
        if 0 <= self.index < len(jobs):
            jobs.remove(self.index)
        return {"FINISHED"}


CLASSES = (
    TESSERA_OT_quote,
    TESSERA_OT_submit,
    TESSERA_OT_fetch,
    TESSERA_OT_cancel,
    TESSERA_OT_open_dashboard,
    TESSERA_OT_remove_job,
)
