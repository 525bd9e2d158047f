"""The panels' draw code against a recording layout (background Blender has no UI to draw
into): every property it shows exists, the states (not baked / up to date / stale / baking)
draw, and the status bar shows a running bake with its progress and cancel button."""

import math
import re
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
    props = [x[1] for x in log if x[0] == "prop"]
    assert props == ["quality", "bake_for_cameras", "use_frame_range", "cache_file", "specular"]
    ops = [x[1] for x in log if x[0] == "operator"]
    assert ops == ["riray.bake", "riray.bake_clear", "riray.bake_estimate"]
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


ADVANCED = ["viewpoint_depth", "direction_depth", "min_direction_depth", "tolerance_angle",
            "tolerance_dist_percent", "search_steps", "viewpoint_refine", "finest_min_traced"]
RULES = ["policy", "use_max_error", "max_error", "use_angle_threshold", "angle",
         "use_distance_threshold", "distance_percent", "use_extrapolation", "extrapolation",
         "use_null_interp", "use_path_identity", "use_solve_paths", "many_classes",
         "use_mirror_normal", "use_mirror_newton"]


def _draw(bpy, panel, obj):
    ctx = type("Ctx", (), {"object": obj, "scene": bpy.context.scene})()
    fake = type("P", (), {"layout": Layout()})()
    getattr(bpy.types, panel).draw(fake, ctx)
    return fake.layout


@pytest.mark.parametrize("suffix,parent", [("", "RIRAY_PT_bake_object"),
                                           ("_view3d", "RIRAY_PT_bake_view3d")])
def test_bake_sub_panels(bl, suffix, parent):
    """Advanced and Render-time Rules hang under the bake panel, in the Properties editor and
    the sidebar alike, closed, split into label and field, with the settings in that order."""
    bpy = bl.bpy
    bpy.ops.surface.primitive_nurbs_surface_sphere_add()
    obj = bpy.context.active_object
    for panel, expected in (("RIRAY_PT_bake_advanced", ADVANCED),
                            ("RIRAY_PT_render_rules", RULES)):
        cls = getattr(bpy.types, panel + suffix)
        assert cls.bl_parent_id == parent and "DEFAULT_CLOSED" in cls.bl_options
        layout = _draw(bpy, panel + suffix, obj)
        assert [x[1] for x in layout.log if x[0] == "prop"] == expected
        assert layout.use_property_split
    rules = _texts(_draw(bpy, "RIRAY_PT_render_rules" + suffix, obj).log)
    assert "no re-bake" in rules


def test_panel_fields_have_units(bl):
    """Every float the bake panels show has a unit: angles in degrees (an angle field), box-
    diagonal fractions in percent; the saved degree and fraction values stay under their old
    names, hidden, and the fields read and write them."""
    bpy = bl.bpy
    bpy.ops.surface.primitive_nurbs_surface_sphere_add()
    obj = bpy.context.active_object
    props = obj.riray.bl_rna.properties
    shown = ADVANCED + RULES
    floats = [k for k in shown if props[k].type == "FLOAT"]
    assert {props[k].subtype for k in floats} <= {"ANGLE", "PERCENTAGE", "FACTOR"}
    assert {k for k in floats if props[k].subtype == "ANGLE"} == {"tolerance_angle", "angle",
                                                                     "max_error"}
    for k, p in props.items():
        if p.type == "FLOAT" and k.endswith("_deg"):
            assert p.is_hidden, k
    p = obj.riray
    p.max_error = math.radians(3.0)
    assert p.max_error_deg == pytest.approx(3.0)
    p.tolerance_deg = 0.25
    assert p.tolerance_angle == pytest.approx(math.radians(0.25))
    assert p.quality == "CUSTOM"
    p.distance_percent = 7.5
    assert p.distance == pytest.approx(0.075)
    assert p.tolerance_dist_percent == pytest.approx(100 * p.tolerance_dist)


# Words by which a tooltip says what a setting costs or saves.
TRADE_WORDS = ("time", "cache", "traced", "slower", "faster", "longer", "shorter", "cost")


def _tooltips(prop):
    """The tooltip of a property and of each of its menu items."""
    items = [i.description for i in prop.enum_items] if prop.type == "ENUM" else []
    return [prop.description] + items


def test_tooltips_speak_plainly_and_name_the_trade(bl):
    """Every setting of the add-on's panels has a tooltip in plain words (no paper, section
    numbers, authors or internal names), and each bake and render-time setting says what it
    trades: bake or render time, cache size, rays traced."""
    bpy = bl.bpy
    bpy.ops.surface.primitive_nurbs_surface_sphere_add()
    obj = bpy.context.active_object
    groups = (obj.riray, bpy.context.scene.riray, bpy.context.view_layer.riray)
    plain = re.compile(r"paper|Bala|hash|\d+\.\d+\)|\b[a-z]+_[a-z_]+\b", re.IGNORECASE)
    for group in groups:
        for key, prop in group.bl_rna.properties.items():
            if key in ("rna_type", "name") or prop.is_hidden or prop.type == "COLLECTION":
                continue
            for text in _tooltips(prop):
                assert text and not plain.search(text), (key, text)
    props = obj.riray.bl_rna.properties
    for key in ["quality"] + ADVANCED + RULES + ["bake_for_cameras", "use_frame_range"]:
        text = " ".join(_tooltips(props[key])).lower()
        assert any(w in text for w in TRADE_WORDS), (key, text)


def test_spline_list_rows(bl):
    """The class list names each row by its spline's index."""
    bpy = bl.bpy
    bpy.ops.surface.primitive_nurbs_surface_sphere_add()
    groups = bpy.context.active_object.riray
    for value in (0, 0, 3):
        groups.spline_groups.add().group = value
    layout = Layout()
    bpy.types.RIRAY_UL_splines.draw_item(None, bpy.context, layout, groups,
                                         groups.spline_groups[2], 0, groups, "spline_groups_index")
    assert ("label", "Spline 2") in layout.log and ("prop", "group") in layout.log


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
