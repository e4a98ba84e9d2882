"""Tessera for Blender: quote, submit and fetch renders on a Tessera render farm.

A panel in Render Properties and the operators ``bpy.ops.tessera.quote()``,
``bpy.ops.tessera.submit(wait=False)``, ``bpy.ops.tessera.fetch()``,
``bpy.ops.tessera.cancel()`` and ``bpy.ops.tessera.open_dashboard()``. The scene goes to
the farm as glTF, exported with the settings of :mod:`.gltf_settings`; the farm is
reached through the HTTP API v1 with the vendored Python client. Scripts and tests load
it without installing: ``sys.path.append("clients/blender"); import tessera_blender;
tessera_blender.register()``. Reference: docs/clients.md.
"""

import bpy
from bpy.app.handlers import persistent

from . import core, operators, panel, props


@persistent
def _on_load(_):
    # A file whose jobs were still running when it was saved picks up polling again.
    core.ensure_timer()


def register():
    props.register()
    for c in operators.CLASSES + panel.CLASSES:
        bpy.utils.register_class(c)
    bpy.app.handlers.load_post.append(_on_load)


def unregister():
    core.stop_timer()
    if _on_load in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_on_load)
    for c in reversed(operators.CLASSES + panel.CLASSES):
        bpy.utils.unregister_class(c)
    props.unregister()
