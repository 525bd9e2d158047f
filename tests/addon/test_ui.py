"""The panels' draw code against a recording layout (background Blender has no UI to draw
into): every property it shows exists, the states (not baked / up to date / stale / baking)
draw, and the status bar shows a running bake with its progress and cancel button."""

import time

import pytest


class Layout:
    """Accepts UILayout calls, checks prop() targets, records labels / operators / progress."""

    def __init__(self, log=None):
        self.log = log if log is not None else []

    def __getattr__(self, name):
        if name in ("row", "column", "box", "split"):
            return lambda *a, **k: Layout(self.log)
        raise AttributeError(name)

    def prop(self, data, prop, **kw):
        assert prop in data.bl_rna.properties.keys(), prop
        self.log.append(("prop", prop))

    def label(self, text="", **kw):
        self.log.append(("label", text))

    def operator(self, idname, **kw):
        self.log.append(("operator", idname))
        return type("Props", (), {})()

    def progress(self, factor=0.0, type="BAR", text=""):
        self.log.append(("progress", factor, text))

    def template_list(self, *a, **k):
        self.log.append(("list",))


def _texts(log):
    return " | ".join(str(x[1]) for x in log if x[0] in ("label", "progress"))


def test_bake_panel_states(bl, tmp_path):
    bpy = bl.bpy
    ui = bl.ui
    bpy.ops.surface.primitive_nurbs_surface_torus_add()
    obj = bpy.context.active_object
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "ui.blend"))
    log = []
    ui.draw_bake_panel(Layout(log), bpy.context)
    props = {x[1] for x in log if x[0] == "prop"}
    assert {"viewpoint_depth", "direction_depth", "tolerance_deg", "angle_deg", "max_error_deg",
            "use_max_error", "use_path_identity", "use_mirror_normal", "use_mirror_newton",
            "bake_for_cameras", "use_frame_range", "cache_file"} <= props
    ops = {x[1] for x in log if x[0] == "operator"}
    assert {"riray.bake", "riray.bake_clear", "riray.bake_estimate"} <= ops
    assert "Not baked" in _texts(log)
    bpy.ops.riray.bake_estimate()
    log = []
    ui.draw_bake_panel(Layout(log), bpy.context)
    assert "Estimate: " in _texts(log) and "Estimate: -" not in _texts(log)
    # baking: progress bar with ETA and a cancel button, here and in the status bar
    bpy.ops.riray.bake(viewpoint_depth=6, direction_depth=6, wait=False)
    job = bl.jobs.JOBS[obj.name]
    t0 = time.time()
    while job.poll() == "running" and job.fraction < 0.02 and time.time() - t0 < 60:
        time.sleep(0.05)
    log = []
    ui.draw_bake_panel(Layout(log), bpy.context)
    bar = [x for x in log if x[0] == "progress"]
    assert bar and 0 < bar[0][1] < 1 and "ETA" in bar[0][2]
    assert ("operator", "riray.bake_cancel") in log
    status = Layout()
    ui.draw_statusbar(type("Header", (), {"layout": status})(), bpy.context)
    assert any(x[0] == "progress" for x in status.log)
    bpy.ops.riray.bake_cancel()
    job.wait(timeout=30)
    bl.operators.poll_jobs()
    assert job.state == "cancelled"
    # up to date, then stale
    bpy.ops.riray.bake(viewpoint_depth=1, direction_depth=1)
    log = []
    ui.draw_bake_panel(Layout(log), bpy.context)
    assert "RI-Tree up to date" in _texts(log)
    obj.rotation_euler.z = 0.5
    bpy.context.view_layer.update()
    bl.cache._on_depsgraph_update(None)
    log = []
    ui.draw_bake_panel(Layout(log), bpy.context)
    assert "STALE" in _texts(log)


@pytest.mark.parametrize("panel", ["RIRAY_PT_render", "RIRAY_PT_passes", "RIRAY_PT_world",
                                   "RIRAY_PT_material", "RIRAY_PT_classes"])
def test_other_panels_draw(bl, panel):
    bpy = bl.bpy
    bpy.ops.surface.primitive_nurbs_surface_sphere_add()
    obj = bpy.context.active_object
    obj.data.materials.append(bpy.data.materials.new("m"))
    bpy.context.scene.world = bpy.data.worlds.new("w")
    cls = getattr(bpy.types, panel)
    ctx = type("Ctx", (), {"scene": bpy.context.scene, "view_layer": bpy.context.view_layer,
                           "world": bpy.context.scene.world, "object": obj,
                           "material": obj.data.materials[0], "engine": "RIRAY"})()
    fake = type("P", (), {"layout": Layout()})()
    cls.draw(fake, ctx)
    assert fake.layout.log


# Built-in panels RI-Tree Preview must show, by role; each role lists the panels it may be
# (engine-specific names differ between Blender versions; every one present must list RIRAY).
REQUIRED_PANELS = {
    "material slots": ("EEVEE_MATERIAL_PT_context_material",),
    "material surface": ("EEVEE_MATERIAL_PT_surface",),
    "world surface": ("EEVEE_WORLD_PT_surface",),
    "light": ("DATA_PT_EEVEE_light",),
    "camera": ("DATA_PT_camera", "DATA_PT_lens"),
    "depth of field": ("DATA_PT_camera_dof",),
    "passes": ("VIEWLAYER_PT_layer_passes",),
    "output": ("RENDER_PT_format", "RENDER_PT_output", "RENDER_PT_frame_range"),
}
# Panels whose settings riray ignores or shows elsewhere.
UNWANTED_PANELS = ("DATA_PT_light", "DATA_PT_spot", "MATERIAL_PT_preview",
                   "EEVEE_MATERIAL_PT_volume", "EEVEE_WORLD_PT_volume",
                   "EEVEE_MATERIAL_PT_settings", "RENDER_PT_eevee_sampling")


def _riray_panels(bpy):
    return {name for names in REQUIRED_PANELS.values() for name in names
            if "RIRAY" in getattr(getattr(bpy.types, name, None), "COMPAT_ENGINES", ())}


def test_builtin_panels_list_the_engine(blender):
    """Material slots and surface, world surface, light, camera with depth of field, passes
    and output show with RI-Tree Preview after register, and no longer after unregister;
    panels of settings riray ignores do not."""
    bpy = blender.bpy
    for role, names in REQUIRED_PANELS.items():
        present = [n for n in names if hasattr(bpy.types, n)]
        assert present, f"{role}: none of {names} in this Blender"
        for name in present:
            assert "RIRAY" in getattr(bpy.types, name).COMPAT_ENGINES, (role, name)
    for name in UNWANTED_PANELS:
        panel = getattr(bpy.types, name, None)
        assert panel is None or "RIRAY" not in panel.COMPAT_ENGINES, name
    assert bpy.types.RIRAY_PT_passes.bl_parent_id == "VIEWLAYER_PT_layer_passes"
    blender.addon.unregister()
    try:
        assert not _riray_panels(bpy)
        assert not [p.__name__ for p in bpy.types.Panel.__subclasses__()
                    if "RIRAY" in getattr(p, "COMPAT_ENGINES", ())
                    and not p.__name__.startswith("RIRAY_")]
    finally:
        blender.addon.register()
    assert _riray_panels(bpy) == {n for names in REQUIRED_PANELS.values() for n in names
                                  if hasattr(bpy.types, n)}
