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
