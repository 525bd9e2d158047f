"""Blender properties of the add-on (saved in the .blend).

scene.riray      the target object, render options (fallback tracing, passes, max events)
object.riray     bake parameters, cache file, per-spline class groups, bake bookkeeping
material.riray   "join splines/faces with this material into one class", highlight settings
world.riray      ambient irradiance for the environment's diffuse shading
view_layer.riray which extra passes the engine writes

Bake parameters carry the names of ``core.ritree.tree.BakeParams`` where one exists, so
``bake_params(obj)`` maps straight onto it; the rest (thresholds, extrapolation, cameras) are
render-time or viewpoint-selection settings the RI-Tree module reads from the same dict.
"""


import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty,
                       IntProperty, PointerProperty, StringProperty)

from ..core.ritree.query import DEFAULT_MAX_ERROR_DEG
from . import compat


def _poll_target(_self, obj) -> bool:
    return obj.type in {"SURFACE", "MESH", "CURVE", "META"}


# Bake quality presets (camera bakes). DEFAULT, the properties' defaults, bakes a sample scene
# for its three cameras in about a minute on two cores; PAPER is the paper's tree.
QUALITY = {
    "DRAFT": {"viewpoint_depth": 3, "direction_depth": 4, "viewpoint_refine": 1,
              "tolerance_deg": 1.0},
    "DEFAULT": {"viewpoint_depth": 4, "direction_depth": 5, "viewpoint_refine": 2,
                "tolerance_deg": 0.5},
    "PAPER": {"viewpoint_depth": 5, "direction_depth": 6, "viewpoint_refine": 2,
              "tolerance_deg": 0.5},
}
_applying = [False]


def _apply_quality(self, _context) -> None:
    """Choosing a preset writes its parameters."""
    if self.quality not in QUALITY:
        return
    _applying[0] = True
    try:
        for key, value in QUALITY[self.quality].items():
            setattr(self, key, value)
    finally:
        _applying[0] = False


def _mark_custom(self, _context) -> None:
    """Editing a preset's parameter by hand makes the quality Custom."""
    preset = QUALITY.get(self.quality)
    if _applying[0] or preset is None:
        return
    if any(abs(getattr(self, k) - v) > 1e-6 for k, v in preset.items()):
        self.quality = "CUSTOM"


class RIRAY_PG_spline_group(bpy.types.PropertyGroup):
    """Class group of one spline (by index): splines with the same group >= 0 form one class."""

    group: IntProperty(name="Class group", default=-1, min=-1, max=999,
                       description="Splines with the same group number (>= 0) are one "
                                   "equivalence class; -1: the spline is its own class")


class RIRAY_PG_object(bpy.types.PropertyGroup):
    quality: EnumProperty(
        name="Quality",
        items=[("DRAFT", "Draft", "Depths 3 / 4, refine 1, tolerance 1 deg: a quick look"),
               ("DEFAULT", "Default", "Depths 4 / 5, refine 2, tolerance 0.5 deg: about a "
                                      "minute for a sample scene's cameras on two cores"),
               ("PAPER", "Paper", "Depths 5 / 6, refine 2, tolerance 0.5 deg: the paper's "
                                  "tree, several times slower"),
               ("CUSTOM", "Custom", "The depths and tolerance as set below")],
        default="DEFAULT", update=_apply_quality,
        description="Bake preset: sets viewpoint / direction depth, viewpoint refine and "
                    "bake tolerance")
    # ---- tree parameters (names of core BakeParams)
    viewpoint_depth: IntProperty(name="Viewpoint depth", default=4, min=1, max=9,
                                 update=_mark_custom,
                                 description="Depth of the viewpoint quadtrees on the faces of "
                                             "the object's bounding box (paper: 5)")
    direction_depth: IntProperty(name="Direction depth", default=5, min=1, max=10,
                                 update=_mark_custom,
                                 description="Maximum depth of the direction quadtrees "
                                             "(paper: 6)")
    min_direction_depth: IntProperty(name="Min direction depth", default=1, min=0, max=10,
                                     description="Direction trees are split at least this deep")
    tolerance_deg: FloatProperty(name="Bake tolerance", default=0.5, min=1e-4, max=45.0,
                                 precision=3, subtype="NONE", update=_mark_custom,
                                 description="Split a cell while the interpolated output ray at "
                                             "its midpoint misses the traced one by more than "
                                             "this angle (degrees)")
    tolerance_dist: FloatProperty(name="Distance tolerance", default=0.002, min=1e-6, max=0.5,
                                  precision=4,
                                  description="... or its origin / first hit by more than this "
                                              "fraction of the object's box diagonal")
    search_steps: IntProperty(name="Search steps", default=4, min=0, max=30,
                              description="Binary-search steps for the extra samples of "
                                          "two-class cells (paper 4.3)")
    viewpoint_refine: IntProperty(name="Viewpoint refine", default=2, min=0, max=4,
                                  update=_mark_custom,
                                  description="Camera bakes: extra viewpoint levels where the "
                                              "cameras' rays lack interpolants")
    finest_min_traced: IntProperty(name="Finest level where traced", default=0, min=0,
                                   max=1 << 30,
                                   description="Camera bakes: the finest viewpoint level splits "
                                               "only cells through which at least this many "
                                               "camera rays would be traced (0: by the rule of "
                                               "the other levels; 20 puts the costliest level "
                                               "where tracing costs most)")
    # ---- render-time interpolation rules (core QueryOptions; no re-bake needed)
    policy: EnumProperty(
        name="Policy",
        items=[("RI", "Ray interpolants", "The paper's rules"),
               ("RAYTREE", "Ray tree", "Bala et al.'s ray-tree rule")],
        default="RI")
    use_angle_threshold: BoolProperty(name="Angle threshold", default=False,
                                      description="The paper's rule: trace when interpolants' "
                                                  "output rays are further apart than the "
                                                  "angle below (Max error is the default)")
    angle_deg: FloatProperty(name="Angle", default=20.0, min=0.0, max=180.0,
                             description="Pairwise angle threshold between interpolants "
                                         "(degrees)")
    use_distance_threshold: BoolProperty(name="Distance threshold", default=False,
                                         description="Trace when interpolants' output origins are "
                                                     "further apart than the distance below")
    distance: FloatProperty(name="Distance", default=0.05, min=0.0, max=1.0, precision=4,
                            description="Pairwise distance threshold, fraction of the object's "
                                        "box diagonal")
    use_extrapolation: BoolProperty(name="Extrapolation", default=False,
                                    description="Allow extrapolating slightly outside the "
                                                "interpolants' triangle")
    extrapolation: FloatProperty(name="Extrapolation", default=0.1, min=0.0, max=1.0,
                                 description="Allowed barycentric distance below 0")
    use_null_interp: BoolProperty(name="Interpolate null rays", default=False,
                                  description="A ray whose interpolants are all trapped "
                                              "(null) is answered null instead of traced "
                                              "(faster; a trapped region can hide an exit "
                                              "no sample shows)")
    use_max_error: BoolProperty(name="Max error", default=True,
                                description="Interpolate a ray only where the errors the bake "
                                            "measured in its four direction leaves and its "
                                            "viewpoint cell are within the angle below, else "
                                            "trace it (a tree baked without cameras has no "
                                            "viewpoint-cell errors: it uses the angle "
                                            "threshold, 20 degrees unless set)")
    max_error_deg: FloatProperty(name="Max error", default=DEFAULT_MAX_ERROR_DEG, min=0.0,
                                 max=180.0,
                                 precision=3,
                                 description="Largest baked error of an interpolated ray "
                                             "(degrees)")
    use_mirror_normal: BoolProperty(name="Reflect about normal", default=True,
                                    description="Mirrors: a ray whose usable samples all "
                                                "reflect once leaves along the view ray "
                                                "reflected about its normal (interpolated, or "
                                                "exact with Exact mirror hits), instead of "
                                                "the interpolated output ray")
    use_mirror_newton: BoolProperty(name="Exact mirror hits", default=True,
                                    description="With Reflect about normal, where those "
                                                "samples share one NURBS patch: reflect at "
                                                "the exact hit Newton's method finds from the "
                                                "interpolated patch parameters (exact "
                                                "reflections, more time per ray; also answers "
                                                "such rays outside the error tolerance "
                                                "unless the bake saw their path change)")
    use_path_identity: BoolProperty(name="Path identity", default=False,
                                    description="Trace a ray whose usable samples follow "
                                                "different paths (ray-tree hash), or whose "
                                                "leaves or viewpoint cell the bake saw change "
                                                "path")
    # ---- viewpoint selection
    bake_for_cameras: BoolProperty(name="Bake for scene cameras", default=True,
                                   description="Only bake the viewpoint cells the scene cameras "
                                               "look from (over the frame range)")
    use_frame_range: BoolProperty(name="Frame range", default=True,
                                  description="Include camera positions over the scene's frame "
                                              "range (else the current frame only)")
    # ---- cache
    cache_file: StringProperty(name="Cache file", subtype="FILE_PATH", default="",
                               options=compat.BLEND_RELATIVE,
                               description="RI-Tree cache file; empty: //<blend>.<object>.rit "
                                           "beside the .blend")
    baked_cache: StringProperty(name="Baked cache", default="", options={"HIDDEN"},
                                description="Where the last bake went when no cache file is "
                                            "set (followed on rename and save)")
    baked_fingerprint: StringProperty(name="Baked fingerprint", default="",
                                      options={"HIDDEN"},
                                      description="Fingerprint of geometry/transform/material "
                                                  "at bake time")
    baked_info: StringProperty(name="Bake info", default="", options={"HIDDEN"})
    # ---- estimate (filled by riray.estimate)
    estimate_time_s: FloatProperty(default=-1.0, options={"HIDDEN"})
    estimate_bytes: FloatProperty(default=-1.0, options={"HIDDEN"})
    estimate_key: StringProperty(default="", options={"HIDDEN"})
    # ---- classes
    spline_groups: CollectionProperty(type=RIRAY_PG_spline_group)
    spline_groups_index: IntProperty(default=0, options={"HIDDEN"})


class RIRAY_PG_material(bpy.types.PropertyGroup):
    join_class: BoolProperty(name="Join into one class", default=False,
                             description="All splines / faces of the specular object using this "
                                         "material form one equivalence class")
    specular: FloatProperty(name="Highlight", default=0.25, min=0.0, max=10.0,
                            description="Phong highlight weight of the specular object")
    shininess: FloatProperty(name="Shininess", default=96.0, min=1.0, max=10000.0,
                             description="Phong exponent of the highlight")


class RIRAY_PG_world(bpy.types.PropertyGroup):
    ambient: FloatProperty(name="Ambient", default=0.0, min=0.0, soft_max=10.0,
                           description="Constant ambient irradiance (W/m^2) added to the lights "
                                       "for the environment's diffuse surfaces")


class RIRAY_PG_view_layer(bpy.types.PropertyGroup):
    use_pass_traced: BoolProperty(name="Traced", default=True,
                                  description="Mask of the object rays that fell back to tracing")
    use_pass_angle_error: BoolProperty(name="Angle Error", default=False,
                                       description="Angle (degrees) between the output ray used "
                                                   "and the exact one (traces every object ray "
                                                   "a second time)")


class RIRAY_PG_scene(bpy.types.PropertyGroup):
    target: PointerProperty(name="Object", type=bpy.types.Object, poll=_poll_target,
                            description="The reflective/refractive object rendered with its "
                                        "RI-Tree (empty: the active object when baking)")
    allow_tracing: BoolProperty(name="Trace without tree", default=True,
                                description="Trace the object exactly when it has no RI-Tree or "
                                            "the tree is stale (else the render fails)")
    render_processes: IntProperty(name="Processes", default=0, min=0, max=256,
                                  description="Worker processes for RI-Tree Preview renders "
                                              "(0: automatic - every core on Linux, one "
                                              "elsewhere, where forking Blender is unsafe)")
    max_events: IntProperty(name="Max events", default=8, min=1, max=64,
                            description="Reflections/refractions followed before a ray becomes "
                                        "the null ray")


# The add-on's id in Blender's preferences: the extension package (this package's parent).
ADDON_ID = __package__.rpartition(".")[0]


class RIRAY_AP_preferences(bpy.types.AddonPreferences):
    """Add-on preferences (saved with Blender's preferences, not in the .blend)."""
    bl_idname = ADDON_ID

    scheduler: StringProperty(
        name="Scheduler address", default="",
        description="Bake on a Dask cluster: a running scheduler's address (tcp://host:8786) or "
                    "local:N (N worker processes on this machine). Empty: bake here. Needs Dask "
                    "in the bake worker's Python and riray[cluster] on every worker "
                    "(docs/cluster.md)")

    def draw(self, _context):
        self.layout.prop(self, "scheduler")


def scheduler_address(context) -> str:
    """The preference's scheduler address, stripped ("" where the add-on has no preferences)."""
    addon = context.preferences.addons.get(ADDON_ID)
    return addon.preferences.scheduler.strip() if addon and addon.preferences else ""


CLASSES = (RIRAY_PG_spline_group, RIRAY_PG_object, RIRAY_PG_material, RIRAY_PG_world,
           RIRAY_PG_view_layer, RIRAY_PG_scene, RIRAY_AP_preferences)
OWNERS = ((bpy.types.Scene, RIRAY_PG_scene), (bpy.types.Object, RIRAY_PG_object),
          (bpy.types.Material, RIRAY_PG_material), (bpy.types.World, RIRAY_PG_world),
          (bpy.types.ViewLayer, RIRAY_PG_view_layer))


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    for owner, group in OWNERS:
        owner.riray = PointerProperty(type=group)
    bpy.app.handlers.load_post.append(_adopt_on_load)


def unregister():
    if _adopt_on_load in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_adopt_on_load)
    for owner, _ in OWNERS:
        del owner.riray
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)


# --------------------------------------------------------------------------- helpers
# Keys of core.ritree.tree.BakeParams, then the add-on's own bake options.
BAKE_KEYS = ("viewpoint_depth", "viewpoint_refine", "finest_min_traced", "direction_depth",
             "min_direction_depth", "tolerance_deg", "tolerance_dist", "search_steps", "quality",
             "bake_for_cameras", "use_frame_range")
QUERY_KEYS = ("policy", "use_angle_threshold", "angle_deg", "use_distance_threshold", "distance",
              "use_extrapolation", "extrapolation", "use_null_interp", "use_max_error",
              "max_error_deg", "use_path_identity", "use_mirror_normal", "use_mirror_newton")


def query_options(obj) -> dict:
    """The render-time rules as core.ritree.query.QueryOptions keyword arguments."""
    p = obj.riray
    return {"policy": p.policy.lower(),
            "angle_deg": float(p.angle_deg) if p.use_angle_threshold else None,
            "distance": float(p.distance) if p.use_distance_threshold else None,
            "extrapolation": float(p.extrapolation) if p.use_extrapolation else None,
            "null_interp": bool(p.use_null_interp),
            "max_error_deg": float(p.max_error_deg) if p.use_max_error else None,
            "path_identity": bool(p.use_path_identity),
            "mirror_rays": ("newton" if p.use_mirror_newton else "reflect")
            if p.use_mirror_normal else "interpolate"}


def bake_params(obj) -> dict:
    """The object's tree parameters as a plain (JSON-able) dict: BakeParams fields, the
    viewpoint options, and "query" (QueryOptions kwargs, stored with the tree)."""
    p = obj.riray
    out = {k: getattr(p, k) for k in BAKE_KEYS}
    out["query"] = query_options(obj)
    return out


def spline_group(obj, index: int) -> int:
    groups = obj.riray.spline_groups
    return groups[index].group if index < len(groups) else -1


# --------------------------------------------------------------------------- custom properties
def adopt_custom_properties() -> int:
    """Take over riray settings that scripts wrote as a custom property ``id["riray"]`` (a dict,
    e.g. sample_scenes/build_blend.py run without the add-on). Returns the number of
    data-blocks whose settings were adopted or repaired.

    From 5.0 such a dict is a custom property apart from the registered settings: it is copied
    into them and removed unless the registered settings already hold some of its keys (then it
    is what Blender keeps of a file saved before 5.0, and the registered copy wins). Before 5.0 the
    dict *is* the registered storage, so only values stored with a type the property does not
    read (an enum item's name, an integral float) are written again through the property."""
    n = 0
    for coll in (bpy.data.scenes, bpy.data.objects, bpy.data.materials, bpy.data.worlds):
        for idb in coll:
            legacy = compat.custom_property(idb, "riray")
            stored = compat.registered_storage(idb, "riray")
            held = set(stored.keys()) if hasattr(stored, "keys") else set()
            if hasattr(legacy, "keys") and not held & set(legacy.keys()):
                _assign(idb, legacy.to_dict())
                del idb["riray"]
                n += 1
            stored = compat.registered_storage(idb, "riray")
            if hasattr(stored, "keys") and _repair(idb, stored):
                n += 1
    return n


def _assign(idb, values: dict) -> None:
    for key, value in values.items():
        try:
            if key == "spline_groups":
                idb.riray.spline_groups.clear()
                for item in value:
                    idb.riray.spline_groups.add().group = int(item.get("group", -1))
            else:
                setattr(idb.riray, key, value)
        except (AttributeError, TypeError, ValueError) as exc:
            print(f"riray: {idb.name}: custom property riray.{key} not adopted ({exc})")


def _repair(idb, stored) -> bool:
    """Rewrite values in the shared storage that Blender would drop as mistyped."""
    props = idb.riray.bl_rna.properties
    bad = {}
    for key in list(stored.keys()):
        value, prop = stored[key], props.get(key)
        if prop is None:
            continue
        if (prop.type == "ENUM" and isinstance(value, str)) or \
                (prop.type == "FLOAT" and isinstance(value, int) and not prop.is_array):
            bad[key] = value
            del stored[key]
    _assign(idb, bad)
    return bool(bad)


@bpy.app.handlers.persistent
def _adopt_on_load(*_args):
    adopt_custom_properties()
