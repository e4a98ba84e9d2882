"""The glTF export settings Tessera's importer honours, in one place.

Both the add-on's exports and the Blender fixtures (tests/fixtures/blender/make_fixtures.py,
checked against Cycles) use :data:`EXPORT_SETTINGS`, so what the fixtures prove about the
importer holds for what the add-on sends to the farm. Importing this module needs no
``bpy``; :func:`export_glb` does.

Why each setting:

- ``export_format="GLB"``: one self-contained file, which is what ``POST /api/v1/scenes``
  takes (textures embedded).
- ``export_cameras`` / ``export_lights``: a job renders from a glTF camera, and lights are
  KHR_lights_punctual, which the importer reads (docs/scenes.md).
- ``export_yup=True``: glTF is Y-up; the importer expects the standard frame.
- ``export_import_convert_lighting_mode="SPEC"``: Blender's default, physically based light
  units (W -> cd and W/m^2 -> lx at 683 lm/W); the importer divides by 683 again, and
  tests/fixtures/blender's light fixtures check that round trip against Cycles.
- ``export_image_format="AUTO"``: PNG stays PNG, JPEG stays JPEG (the importer decodes both).
- ``export_extras=False``: custom properties mean nothing to the renderer.
- ``export_apply=False``: the fixtures have no modifiers; the add-on overrides it
  (:data:`ADDON_OVERRIDES`), since the importer sees meshes only as exported and would
  otherwise render every modifier (subdivision, mirror, arrays) as absent.
- ``use_renderable=False``: the exporter's default (every object); the add-on overrides
  it, so that an object disabled for rendering in Blender is not rendered on the farm.
- ``export_gpu_instances=False``: Blender's default; the fixture ``gpu_instancing`` turns it
  on to check EXT_mesh_gpu_instancing.

Everything else stays at the exporter's defaults: animations on (Blender's frame F is at
t = F / fps, which is a job's frame F at the scene's fps), no tangents (the importer builds
the MikkTSpace frame the glTF specification prescribes, as Blender does).
"""

#: The exporter's keyword arguments shared by the fixtures and the add-on.
EXPORT_SETTINGS = {
    "export_format": "GLB",
    "export_cameras": True,
    "export_lights": True,
    "export_gpu_instances": False,
    "export_extras": False,
    "export_yup": True,
    "export_apply": False,
    "use_renderable": False,
    "export_import_convert_lighting_mode": "SPEC",
    "export_image_format": "AUTO",
}

#: What the add-on changes for artists' scenes (see the module's documentation).
ADDON_OVERRIDES = {"export_apply": True, "use_renderable": True}


def settings(**overrides):
    """:data:`EXPORT_SETTINGS` with ``overrides`` (which must be exporter options it has)."""
    unknown = set(overrides) - set(EXPORT_SETTINGS)
    if unknown:
        raise KeyError(f"not a shared export setting: {sorted(unknown)}")
    return {**EXPORT_SETTINGS, **overrides}


def export_glb(path, **overrides):
    """Exports the current scene to ``path`` with Blender's glTF exporter and
    :func:`settings`."""
    import bpy

    bpy.ops.export_scene.gltf(filepath=path, **settings(**overrides))
