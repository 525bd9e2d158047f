"""Panels: "Bake RI-Tree" (Properties > Object and the 3D View sidebar, tab "RI-Tree") with its
sub-panels Advanced (tree settings) and Render-time Rules (no re-bake needed), spline classes,
material settings, the engine's render / pass / world settings, and a progress bar in
the status bar while a bake runs."""

from __future__ import annotations

import os

import bpy

from . import cache
from .engine import ENGINE_ID
from .jobs import format_bytes, format_duration
from .materials import is_sharp_specular
from .jobs import ESTIMATES, JOBS
from .operators import estimate_key
from .report import ExportError

TARGET_TYPES = {"SURFACE", "MESH", "CURVE", "META"}


def _job_line(layout, job) -> None:
    eta = job.eta
    text = f"{100 * job.fraction:.0f}%  ETA {format_duration(eta)}" if eta is not None else \
        f"{100 * job.fraction:.0f}%  {job.message}"
    if hasattr(layout, "progress"):
        layout.progress(factor=job.fraction, type="BAR", text=text)
    else:
        layout.label(text=text)


def draw_bake_panel(layout, context) -> None:
    """The object's "Bake RI-Tree" panel: quality, the bake / cancel and estimate rows, the
    cache's state, cameras, cache file and the RI-Tree Object mark; the sub-panels hold the
    rest."""
    obj = context.object
    if obj is None or obj.type not in TARGET_TYPES:
        layout.label(text="Select a NURBS surface, mesh or curve object", icon="INFO")
        return
    p = obj.riray
    layout.prop(p, "quality")
    _draw_actions(layout, obj, p)
    _draw_status(layout.box(), context, obj, p)
    col = layout.column(heading="Cameras")
    col.prop(p, "bake_for_cameras")
    sub = col.row()
    sub.active = p.bake_for_cameras
    sub.prop(p, "use_frame_range")
    layout.prop(p, "cache_file", text="Cache")
    _draw_specular(layout, obj, p)


def _draw_specular(layout, obj, p) -> None:
    """The RI-Tree Object mark; when the object's material makes it one anyway, says so."""
    row = layout.row()
    row.prop(p, "specular")
    if not p.specular and any(is_sharp_specular(s.material) for s in obj.material_slots):
        row.label(text="(glass / mirror material)")


def _draw_actions(layout, obj, p) -> None:
    """Bake and Clear (while baking: the progress bar and Cancel), then the estimate row."""
    job = JOBS.get(obj.name)
    if job is not None and job.running:
        _job_line(layout, job)
        row = layout.row()
        row.label(text=job.message)
        row.operator("riray.bake_cancel", text="Cancel", icon="CANCEL").object = obj.name
    else:
        if job is not None and job.state == "failed":
            layout.label(text=f"Last bake failed: {job.error}", icon="ERROR")
        row = layout.row(align=True)
        row.scale_y = 1.4
        op = row.operator("riray.bake", text="Bake", icon="RENDER_STILL")
        op.object = obj.name
        op.wait = False
        row.operator("riray.bake_clear", text="Clear", icon="TRASH").object = obj.name
    _draw_estimate(layout.row(), obj, p)


def _draw_estimate(row, obj, p) -> None:
    """The estimate row: the estimate for the current settings (or "-") and the button that
    starts one; while one runs, its progress and a button that stops it."""
    est = ESTIMATES.get(obj.name)
    if est is not None and est.running:
        row.label(text=f"Estimating... {100 * est.fraction:.0f}%")
        row.operator("riray.bake_estimate_cancel", text="", icon="CANCEL").object = obj.name
        return
    if p.estimate_time_s >= 0 and p.estimate_key == estimate_key(obj):
        row.label(text=f"Estimate: {format_duration(p.estimate_time_s)}, "
                       f"{format_bytes(p.estimate_bytes)}")
    elif est is not None and est.state == "failed":
        row.label(text=f"Estimate failed: {est.error}", icon="ERROR")
    else:
        row.label(text="Estimate: -")
    op = row.operator("riray.bake_estimate", text="", icon="TIME")
    op.object = obj.name
    op.wait = False


def _draw_status(box, context, obj, p) -> None:
    """Whether the cache is up to date, its size and bake time."""
    try:
        status = cache.tree_status(obj, context.evaluated_depsgraph_get())
    except ExportError as exc:
        status = {"state": "invalid", "message": str(exc), "doc": None, "path": ""}
    icon = {"fresh": "CHECKMARK", "stale": "ERROR", "missing": "BLANK1",
            "invalid": "CANCEL"}[status["state"]]
    label = {"fresh": "RI-Tree up to date", "stale": "RI-Tree is STALE - re-bake",
             "missing": "Not baked", "invalid": "Cache file unreadable"}[status["state"]]
    box.label(text=label, icon=icon)
    if status["doc"]:
        meta = status["doc"].get("meta", {})
        try:
            size = format_bytes(float(os.path.getsize(status["path"])))
        except OSError:
            size = "?"
        box.label(text=f"{size}, baked in {format_duration(meta.get('bake_s'))} "
                       f"({status['doc'].get('backend', '?')})")
    if not bpy.data.filepath and not p.cache_file:
        box.label(text="Save the .blend to keep the cache beside it", icon="INFO")


def draw_advanced(layout, p) -> None:
    """Tree settings the quality preset sets, and the finer ones it leaves alone."""
    col = layout.column(align=True)
    col.prop(p, "viewpoint_depth")
    col.prop(p, "direction_depth")
    col.prop(p, "min_direction_depth", text="Min")
    col = layout.column(align=True)
    col.prop(p, "tolerance_angle")
    col.prop(p, "tolerance_dist_percent")
    layout.prop(p, "search_steps")
    col = layout.column(align=True)
    col.active = p.bake_for_cameras
    col.prop(p, "viewpoint_refine")
    sub = col.row()
    sub.active = p.bake_for_cameras and p.viewpoint_refine > 0
    sub.prop(p, "finest_min_traced")


def draw_render_rules(layout, p) -> None:
    """When a ray is interpolated and when it is traced: read at render time, no re-bake."""
    layout.label(text="Used at render time: no re-bake needed", icon="INFO")
    layout.prop(p, "policy")
    for use, value in (("use_max_error", "max_error"), ("use_angle_threshold", "angle"),
                       ("use_distance_threshold", "distance_percent"),
                       ("use_extrapolation", "extrapolation")):
        row = layout.row(heading=p.bl_rna.properties[use].name)
        row.prop(p, use, text="")
        sub = row.row()
        sub.active = getattr(p, use)
        sub.prop(p, value, text="")
    col = layout.column(heading="Rays")
    col.prop(p, "use_null_interp")
    col.prop(p, "use_path_identity")
    col.prop(p, "use_solve_paths")
    layout.prop(p, "many_classes")
    col = layout.column(heading="Mirrors")
    col.prop(p, "use_mirror_normal")
    sub = col.row()
    sub.active = p.use_mirror_normal
    sub.prop(p, "use_mirror_newton")


def _split(layout):
    layout.use_property_split = True
    layout.use_property_decorate = False
    return layout


def _is_target(obj) -> bool:
    return obj is not None and obj.type in TARGET_TYPES


class RIRAY_PT_bake_object(bpy.types.Panel):
    bl_label = "Bake RI-Tree"
    bl_idname = "RIRAY_PT_bake_object"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "object"

    @classmethod
    def poll(cls, context):
        return _is_target(context.object)

    def draw(self, context):
        draw_bake_panel(_split(self.layout), context)


class RIRAY_PT_bake_view3d(bpy.types.Panel):
    bl_label = "Bake RI-Tree"
    bl_idname = "RIRAY_PT_bake_view3d"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "RI-Tree"

    def draw(self, context):
        draw_bake_panel(_split(self.layout), context)


class _BakeSubPanel:
    """A closed sub-panel of the bake panel, shown for objects that can be baked."""
    bl_options = {"DEFAULT_CLOSED"}

    @classmethod
    def poll(cls, context):
        return _is_target(context.object)


class _InProperties(_BakeSubPanel):
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "object"
    bl_parent_id = "RIRAY_PT_bake_object"


class _InSidebar(_BakeSubPanel):
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "RI-Tree"
    bl_parent_id = "RIRAY_PT_bake_view3d"


class _Advanced:
    """The Advanced sub-panel's content (the tree's settings), in either editor."""
    bl_label = "Advanced"

    def draw(self, context):
        draw_advanced(_split(self.layout), context.object.riray)


class _RenderRules:
    """The Render-time Rules sub-panel's content, in either editor."""
    bl_label = "Render-time Rules"

    def draw(self, context):
        draw_render_rules(_split(self.layout), context.object.riray)


class RIRAY_PT_bake_advanced(_Advanced, _InProperties, bpy.types.Panel):
    bl_idname = "RIRAY_PT_bake_advanced"


class RIRAY_PT_bake_advanced_view3d(_Advanced, _InSidebar, bpy.types.Panel):
    bl_idname = "RIRAY_PT_bake_advanced_view3d"


class RIRAY_PT_render_rules(_RenderRules, _InProperties, bpy.types.Panel):
    bl_idname = "RIRAY_PT_render_rules"


class RIRAY_PT_render_rules_view3d(_RenderRules, _InSidebar, bpy.types.Panel):
    bl_idname = "RIRAY_PT_render_rules_view3d"


def _spline_number(groups, item) -> int:
    return next(i for i, g in enumerate(groups) if g == item)


class RIRAY_UL_splines(bpy.types.UIList):
    def draw_item(self, _context, layout, data, item, _icon, _active_data, _active_propname):
        row = layout.row(align=True)
        row.label(text=f"Spline {_spline_number(data.spline_groups, item)}",
                  icon="SURFACE_DATA")
        row.prop(item, "group", text="Class")


class RIRAY_PT_classes(bpy.types.Panel):
    bl_label = "Equivalence Classes"
    bl_idname = "RIRAY_PT_classes"
    bl_parent_id = "RIRAY_PT_bake_object"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "object"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        obj = context.object
        layout = self.layout
        if obj.type != "SURFACE":
            layout.label(text="Mesh faces: classes split at sharp edges and flat faces")
            return
        layout.label(text="Splines with the same class group (>= 0) form one class")
        if len(obj.riray.spline_groups) != len(obj.data.splines):
            layout.operator("riray.spline_groups_sync", icon="FILE_REFRESH")
        layout.template_list("RIRAY_UL_splines", "", obj.riray, "spline_groups", obj.riray,
                             "spline_groups_index", rows=3)
        row = layout.row(align=True)
        row.operator("riray.spline_groups_set", text="Join All").mode = "JOIN"
        row.operator("riray.spline_groups_set", text="Split All").mode = "SPLIT"


class RIRAY_PT_material(bpy.types.Panel):
    bl_label = "RI-Tree"
    bl_idname = "RIRAY_PT_material"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "material"
    bl_options = {"DEFAULT_CLOSED"}

    @classmethod
    def poll(cls, context):
        return context.material is not None

    def draw(self, context):
        m = context.material.riray
        self.layout.use_property_split = True
        self.layout.prop(m, "join_class")
        self.layout.prop(m, "custom_highlight")
        col = self.layout.column()
        col.active = m.custom_highlight
        col.prop(m, "specular")
        col.prop(m, "shininess")


class _EnginePanel:
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    COMPAT_ENGINES = {ENGINE_ID}

    @classmethod
    def poll(cls, context):
        return context.engine in cls.COMPAT_ENGINES


class RIRAY_PT_render(_EnginePanel, bpy.types.Panel):
    bl_label = "RI-Tree"
    bl_idname = "RIRAY_PT_render"
    bl_context = "render"

    def draw(self, context):
        s = context.scene.riray
        layout = self.layout
        layout.use_property_split = True
        layout.prop(s, "allow_tracing")
        layout.prop(s, "samples")
        layout.prop(s, "render_processes")
        layout.prop(s, "max_events")
        from . import engine
        st = engine.LAST_RENDER.get("stats")
        if st:
            layout.label(text=f"Last frame {st['frame']}: traced "
                              f"{100 * st['traced_fraction']:.1f}% of {st['object_pixels']} "
                              f"object pixels, {st['render_time_s']:.2f} s")
            objects = st.get("objects", {})
            for name, o in objects.items() if len(objects) > 1 else ():
                layout.label(text=f"    {name}: traced {100 * o['traced_fraction']:.1f}% "
                                  f"of {o['object_pixels']} ({o['mode']})")


class RIRAY_PT_passes(_EnginePanel, bpy.types.Panel):
    bl_label = "RI-Tree"
    bl_idname = "RIRAY_PT_passes"
    bl_context = "view_layer"
    bl_parent_id = "VIEWLAYER_PT_layer_passes"

    def draw(self, context):
        v = context.view_layer.riray
        self.layout.prop(v, "use_pass_traced")
        self.layout.prop(v, "use_pass_angle_error")


class RIRAY_PT_world(_EnginePanel, bpy.types.Panel):
    bl_label = "RI-Tree Environment"
    bl_idname = "RIRAY_PT_world"
    bl_context = "world"

    @classmethod
    def poll(cls, context):
        return super().poll(context) and context.world is not None

    def draw(self, context):
        self.layout.prop(context.world.riray, "ambient")


def draw_statusbar(self, context):
    for job in JOBS.values():
        if job.running:
            row = self.layout.row(align=True)
            row.label(text=f"RI-Tree {job.object_name}")
            _job_line(row, job)
            row.operator("riray.bake_cancel", text="", icon="CANCEL").object = job.object_name


CLASSES = (RIRAY_PT_bake_object, RIRAY_PT_bake_view3d, RIRAY_PT_bake_advanced,
           RIRAY_PT_bake_advanced_view3d, RIRAY_PT_render_rules, RIRAY_PT_render_rules_view3d,
           RIRAY_UL_splines, RIRAY_PT_classes,
           RIRAY_PT_material, RIRAY_PT_render, RIRAY_PT_passes, RIRAY_PT_world)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.STATUSBAR_HT_header.append(draw_statusbar)


def unregister():
    bpy.types.STATUSBAR_HT_header.remove(draw_statusbar)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)

