"""The add-on's preferences and the scene's Tessera settings and jobs."""

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

ADDON_ID = __package__


class TesseraPreferences(bpy.types.AddonPreferences):
    """Where the farm is. An empty field falls back to the environment, as
    ``tessera submit`` does, so farm-side and headless scripts need no preferences."""

    bl_idname = ADDON_ID

    server: StringProperty(
        name="Server",
        description="The coordinator's URL, e.g. http://render-farm:8080 (empty: $TESSERA_SERVER, else http://127.0.0.1:8080)",
        default="",
    )
    token: StringProperty(
        name="API token",
        description="The coordinator's API token (empty: $TESSERA_API_TOKEN)",
        default="",
        subtype="PASSWORD",
    )
    ca_file: StringProperty(
        name="CA file",
        description="CA certificate(s) (PEM) an https:// server's certificate must be issued by (empty: the system's)",
        default="",
        subtype="FILE_PATH",
    )

    def draw(self, context):
        col = self.layout.column()
        col.prop(self, "server")
        col.prop(self, "token")
        col.prop(self, "ca_file")
        col.label(text="Empty fields fall back to TESSERA_SERVER and TESSERA_API_TOKEN.")


def _camera_poll(self, obj):
    return obj.type == "CAMERA"


class TesseraJob(bpy.types.PropertyGroup):
    """A job submitted from this file, as last polled."""

    job_id: IntProperty(name="Job")
    server: StringProperty(name="Server")
    state: StringProperty(name="State", default="queued")
    frames_done: IntProperty(name="Frames done")
    frames_total: IntProperty(name="Frames")
    frame_start: IntProperty()
    frame_end: IntProperty()
    error_estimate: FloatProperty(name="Error", default=-1.0)
    eta_seconds: FloatProperty(name="ETA", default=-1.0)
    elapsed_seconds: FloatProperty(name="Elapsed")
    message: StringProperty(name="Message")
    output: StringProperty(name="Output", subtype="FILE_PATH")
    fetched: BoolProperty(name="Fetched")
    fetch_error: StringProperty(name="Fetch error", description="Why the last download of the frames failed")


class TesseraSceneSettings(bpy.types.PropertyGroup):
    """The job the panel submits, its quote, and the jobs of this scene."""

    samples: IntProperty(name="Samples", description="Samples per pixel (spp)", default=64, min=1, max=1048576)
    seed: IntProperty(name="Seed", default=0, min=0)
    target_error: FloatProperty(
        name="Target error",
        description="Stop where the estimated relative error reaches this (0: run every sample)",
        default=0.0, min=0.0, max=1.0, precision=3, step=0.1,
    )
    adaptive: EnumProperty(
        name="Adaptive",
        items=[
            ("off", "Off", "Every pixel gets every sample"),
            ("sequential", "Sequential", "Pixels stop once accurate enough (needs a target error)"),
            ("unbiased", "Unbiased", "A pilot plans each pixel's samples (needs a target error)"),
        ],
        default="off",
    )
    time_limit: FloatProperty(name="Time limit", description="Seconds (0: none)", default=0.0, min=0.0, unit="TIME_ABSOLUTE")
    priority: IntProperty(name="Priority", description="Higher runs first", default=0)
    use_scene_range: BoolProperty(name="Scene frame range", default=True)
    frame_start: IntProperty(name="Start", default=1, min=0)
    frame_end: IntProperty(name="End", default=1, min=0)
    camera: PointerProperty(
        name="Camera", type=bpy.types.Object, poll=_camera_poll,
        description="The camera to render from (empty: the scene's)",
    )
    quote_text: StringProperty(name="Quote")
    message: StringProperty(name="Message")
    failed: BoolProperty(name="Failed", description="Whether the message is an error")
    error_field: StringProperty(name="Field", description="The job field the last error named")
    busy: BoolProperty(name="Busy")
    last_export: StringProperty(name="Last export", subtype="FILE_PATH")
    jobs: CollectionProperty(type=TesseraJob)
    active_job: IntProperty()


CLASSES = (TesseraPreferences, TesseraJob, TesseraSceneSettings)


def register():
    for c in CLASSES:
        bpy.utils.register_class(c)
    bpy.types.Scene.tessera = PointerProperty(type=TesseraSceneSettings)


def unregister():
    del bpy.types.Scene.tessera
    for c in reversed(CLASSES):
        bpy.utils.unregister_class(c)
