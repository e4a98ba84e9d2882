"""The Tessera panel in Render Properties: the job's settings, Quote and Submit, and this
scene's jobs as last polled (``core`` polls them on a timer; drawing never waits on the
network)."""

import bpy

from . import core


def _fmt_seconds(s):
    if s < 0:
        return "-"
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.0f} min"
    return f"{s / 3600:.1f} h"


class TESSERA_UL_jobs(bpy.types.UIList):
    """One row per job: id, state, frames done, error estimate, ETA."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_property, index=0, flt_flag=0):
        row = layout.row(align=True)
        row.label(text=f"#{item.job_id}")
        row.label(text=item.state)
        row.label(text=f"{item.frames_done}/{item.frames_total}")
        row.label(text="-" if item.error_estimate < 0 else f"{item.error_estimate * 100:.2f}%")
        row.label(text=_fmt_seconds(item.eta_seconds) if item.state == "running" else ("fetched" if item.fetched else ""))


class TESSERA_PT_render(bpy.types.Panel):
    """Quote, submit and follow renders on a Tessera farm."""

    bl_label = "Tessera"
    bl_idname = "TESSERA_PT_render"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        scene = context.scene
        t = scene.tessera
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False

        server, token, _ = core.connection()
        layout.label(text=f"{server}" + ("" if token else " (no token)"), icon="URL")

        col = layout.column()
        for prop in ("samples", "target_error", "adaptive", "time_limit", "priority"):
            row = col.row()
            row.alert = t.error_field == prop
            row.prop(t, prop)
        col.prop(t, "use_scene_range")
        sub = col.column(align=True)
        if t.use_scene_range:
            sub.label(text=f"Frames {scene.frame_start} to {scene.frame_end} at {scene.render.fps / scene.render.fps_base:g} fps")
        else:
            for prop in ("frame_start", "frame_end"):
                row = sub.row()
                row.alert = t.error_field == prop
                row.prop(t, prop)
        row = col.row()
        row.alert = t.error_field == "camera"
        row.prop(t, "camera", text="Camera")
        if t.camera is None:
            col.label(text=f"Scene camera: {scene.camera.name if scene.camera else 'none'}")

        row = layout.row(align=True)
        row.enabled = not t.busy
        row.operator("tessera.quote", icon="TIME")
        row.operator("tessera.submit", icon="RENDER_ANIMATION")

        if t.message:
            box = layout.box()
            box.alert = t.failed
            for line in _wrap(t.message):
                box.label(text=line)
        if t.quote_text:
            box = layout.box()
            box.label(text="Quote", icon="TIME")
            for line in t.quote_text.split("\n"):
                box.label(text=line)

        if len(t.jobs):
            layout.label(text="Jobs: id, state, frames, error, ETA")
            layout.template_list("TESSERA_UL_jobs", "", t, "jobs", t, "active_job", rows=3)
            if 0 <= t.active_job < len(t.jobs):
                job = t.jobs[t.active_job]
                row = layout.row(align=True)
                op = row.operator("tessera.open_dashboard", icon="URL")
                op.job_id = job.job_id
                op = row.operator("tessera.fetch", icon="IMPORT")
                op.job_id = job.job_id
                op = row.operator("tessera.cancel", icon="CANCEL")
                op.job_id = job.job_id
                op = row.operator("tessera.remove_job", text="", icon="X")
                op.index = t.active_job
                if job.message:
                    for line in _wrap(job.message):
                        layout.label(text=line)


def _wrap(text, width=60):
    out = []
    for para in text.split("\n"):
        words, line = para.split(), ""
        for w in words:
            if line and len(line) + 1 + len(w) > width:
                out.append(line)
                line = w
            else:
                line = f"{line} {w}" if line else w
        out.append(line)
    return out


CLASSES = (TESSERA_UL_jobs, TESSERA_PT_render)
