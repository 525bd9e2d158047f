"""Blender properties of the add-on (saved in the .blend).

scene.riray      render options (fallback tracing, passes, max events); older files' object
object.riray     the RI-Tree Object mark, bake parameters, cache file, per-spline class
                 groups, bake bookkeeping
material.riray   "join splines/faces with this material into one class", highlight settings
world.riray      ambient irradiance for the environment's diffuse shading
view_layer.riray which extra passes the engine writes

Bake parameters carry the names of ``core.ritree.tree.BakeParams`` where one exists, so
``bake_params(obj)`` maps straight onto it; the rest (thresholds, extrapolation, cameras) are
render-time or viewpoint-selection settings the RI-Tree module reads from the same dict. The
defaults and quality presets are core's (BakeParams, QUALITY_PRESETS, QueryOptions), so a
bake and a render at the defaults match the ``riray`` command line's.
"""


import math

import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty,
                       IntProperty, PointerProperty, StringProperty)

from ..core.ritree.params import QUALITY_PRESETS, BakeParams
from ..core.ritree.query import DEFAULT_MAX_ERROR_DEG, QueryOptions
from ..core.scene.camera import Shot
from ..core.scene.model import RenderSettings
from . import compat

BAKE = BakeParams()             # core's defaults of the settings below
QUERY = QueryOptions()


def _poll_target(_self, obj) -> bool:
    return obj.type in {"SURFACE", "MESH", "CURVE", "META"}


# Bake quality presets by Quality item: core's (riray bake --quality). DEFAULT is the
# properties' defaults.
QUALITY = {name.upper(): values for name, values in QUALITY_PRESETS.items()}
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


DEG = math.pi / 180.0


def _shown_as(stored: str, scale: float, **kw):
    """The panel's field for the saved setting ``stored``: its value times ``scale`` (degrees
    shown as an angle, a fraction as percent). Not saved itself, so files keep ``stored``."""
    return FloatProperty(get=lambda self: getattr(self, stored) * scale,
                         set=lambda self, value: setattr(self, stored, value / scale),
                         subtype="ANGLE" if scale == DEG else "PERCENTAGE", **kw)


class RIRAY_PG_spline_group(bpy.types.PropertyGroup):
    """Class group of one spline (by index): splines with the same group >= 0 form one class."""

    group: IntProperty(name="Class group", default=-1, min=-1, max=999,
                       description="Splines with the same group number (>= 0) are one "
                                   "equivalence class; -1: the spline is its own class")


class RIRAY_PG_object(bpy.types.PropertyGroup):
    specular: BoolProperty(name="RI-Tree Object", default=False,
                           description="Render this object as a glass or mirror object, "
                                       "through its own RI-Tree (objects with a sharp Glass, "
                                       "Refraction, Glossy, or transmissive or metallic "
                                       "Principled material are, without this mark; baking "
                                       "an object marks it)")
    quality: EnumProperty(
        name="Quality",
        # The numbers are what a .blend stores: files saved when 1 was Default at depths 4 / 5
        # and 2 was Paper at 5 / 6 open with the same depths, as Fast and Default.
        items=[("DRAFT", "Draft", "Coarsest tree: the quickest bake and smallest cache; more "
                                  "rays are traced exactly at render time", 0),
               ("FAST", "Fast", "About a minute for a sample scene's three cameras on two "
                                "cores: about a third of Default's bake time, under half its "
                                "cache, more rays traced at render time", 1),
               ("DEFAULT", "Default", "The finest preset and the command line's default: "
                                      "the longest bake and biggest cache, the fewest rays "
                                      "traced at render time", 2),
               ("CUSTOM", "Custom", "The depths and tolerance as set under Advanced", 3)],
        default="DEFAULT", update=_apply_quality,
        description="How fine a tree to bake. Finer trees take longer and use more disk and "
                    "memory, and leave fewer rays to trace exactly at render time")
    # ---- tree parameters (names of core BakeParams)
    viewpoint_depth: IntProperty(name="Viewpoint depth", default=BAKE.viewpoint_depth, min=1, max=9,
                                 update=_mark_custom,
                                 description="How finely the camera positions around the object "
                                             "are divided. One more level: about 4 times the "
                                             "bake time and cache size, fewer rays traced at "
                                             "render time")
    direction_depth: IntProperty(name="Direction depth", default=BAKE.direction_depth, min=1,
                                 max=10, update=_mark_custom,
                                 description="How finely the directions seen from each camera "
                                             "position may be divided. One more level: up to 4 "
                                             "times the bake time and cache size where the "
                                             "object needs it, smaller interpolation errors")
    min_direction_depth: IntProperty(name="Min direction depth",
                                     default=BAKE.min_direction_depth, min=0, max=10,
                                     description="Directions are divided at least this finely "
                                                 "everywhere, even where the object looks "
                                                 "simple. Higher: a safer tree, more bake time "
                                                 "and cache")
    tolerance_deg: FloatProperty(name="Angle tolerance (degrees)", default=BAKE.tolerance_deg,
                                 min=1e-4, max=45.0, precision=3, update=_mark_custom,
                                 options={"HIDDEN"},
                                 description="Saved value of Angle tolerance, in degrees")
    tolerance_dist: FloatProperty(name="Distance tolerance (fraction)",
                                  default=BAKE.tolerance_dist,
                                  min=1e-6, max=0.5, precision=4, options={"HIDDEN"},
                                  description="Saved value of Distance tolerance, a fraction of "
                                              "the object's bounding-box diagonal")
    tolerance_angle: _shown_as(
        "tolerance_deg", DEG, name="Angle tolerance", min=1e-4 * DEG, max=45.0 * DEG,
        precision=3, description="The bake divides a region until rays interpolated there "
                                 "leave within this angle of the exact ones. Smaller: more "
                                 "accurate renders, a longer bake and a bigger cache")
    tolerance_dist_percent: _shown_as(
        "tolerance_dist", 100.0, name="Distance tolerance", min=1e-4, max=50.0, precision=3,
        description="... and leave from within this distance of the exact ones, in percent "
                    "of the object's bounding-box diagonal. Smaller: more accurate, a longer "
                    "bake and a bigger cache")
    search_steps: IntProperty(name="Search steps", default=BAKE.search_steps, min=0, max=30,
                              description="Where two surfaces of the object meet inside a "
                                          "region, the bake searches for the edge with this "
                                          "many halvings. More: sharper edges between them, "
                                          "slightly more bake time")
    viewpoint_refine: IntProperty(name="Viewpoint refine", default=BAKE.viewpoint_refine,
                                  min=0, max=4, update=_mark_custom,
                                  description="Extra levels of camera positions, only where the "
                                              "scene cameras' rays would otherwise be traced "
                                              "or come out too inaccurate. Each level: more "
                                              "bake time and cache, fewer rays traced at "
                                              "render time (camera bakes only)")
    finest_min_traced: IntProperty(name="Finest level where traced",
                                   default=BAKE.finest_min_traced, min=0, max=1 << 30,
                                   description="The finest level of camera positions goes only "
                                               "where at least this many camera rays would be "
                                               "traced (0: wherever the other levels would). "
                                               "Higher: a shorter bake and smaller cache, more "
                                               "tracing at render time (camera bakes only)")
    # ---- render-time interpolation rules (core QueryOptions; no re-bake needed)
    policy: EnumProperty(
        name="Policy",
        items=[("RI", "Ray interpolants", "Interpolate every ray that passes the rules below: "
                                          "the fewest rays traced, the fastest renders"),
               ("RAYTREE", "Same surfaces", "Interpolate only where the nearby samples bounce "
                                            "off the same surfaces in the same order: more "
                                            "rays traced, slower renders")],
        default=QUERY.policy.upper(),
        description="Which rule decides whether a ray is interpolated or traced")
    use_angle_threshold: BoolProperty(name="Angle threshold", default=QUERY.angle_deg is not None,
                                      description="Trace a ray whose nearby samples leave the "
                                                  "object further apart than the angle below: "
                                                  "more accurate, more rays traced. Max error "
                                                  "(on by default) reads the errors the bake "
                                                  "measured instead")
    angle_deg: FloatProperty(name="Angle (degrees)", default=20.0, min=0.0, max=180.0,
                             options={"HIDDEN"}, description="Saved value of Angle, in degrees")
    angle: _shown_as("angle_deg", DEG, name="Angle", min=0.0, max=180.0 * DEG, precision=2,
                     description="Largest angle between the nearby samples' rays for which a "
                                 "ray is interpolated. Smaller: more accurate, more rays "
                                 "traced, slower renders")
    use_distance_threshold: BoolProperty(name="Distance threshold",
                                         default=QUERY.distance is not None,
                                         description="Trace a ray whose nearby samples leave the "
                                                     "object further apart than the distance "
                                                     "below: more accurate, more rays traced")
    distance: FloatProperty(name="Distance (fraction)", default=0.05, min=0.0, max=1.0,
                            precision=4, options={"HIDDEN"},
                            description="Saved value of Distance, a fraction of the object's "
                                        "bounding-box diagonal")
    distance_percent: _shown_as(
        "distance", 100.0, name="Distance", min=0.0, max=100.0, precision=2,
        description="Largest distance between where the nearby samples leave the object, in "
                    "percent of its bounding-box diagonal. Smaller: more accurate, more rays "
                    "traced, slower renders")
    use_extrapolation: BoolProperty(name="Extrapolation",
                                    default=QUERY.extrapolation is not None,
                                    description="Also interpolate rays slightly outside their "
                                                "nearby samples (fewer rays traced, less "
                                                "accurate at edges)")
    extrapolation: FloatProperty(name="Extrapolation", default=0.1, min=0.0, max=1.0,
                                 subtype="FACTOR",
                                 description="How far outside the nearby samples a ray may "
                                             "lie, as a share of their spacing. More: fewer "
                                             "rays traced, less accurate at edges")
    use_null_interp: BoolProperty(name="Interpolate null rays", default=QUERY.null_interp,
                                  description="Answer a ray as trapped inside the object when "
                                              "all its nearby samples are, instead of tracing "
                                              "it: faster, but can miss a way out no sample "
                                              "shows")
    use_max_error: BoolProperty(name="Max error", default=QUERY.max_error_deg is not None,
                                description="Interpolate a ray only where the bake measured "
                                            "errors within the angle below around it; trace it "
                                            "elsewhere: rays are traced only where the tree "
                                            "is inaccurate. A tree baked without the scene "
                                            "cameras uses the angle threshold instead (20° "
                                            "unless set)")
    max_error_deg: FloatProperty(name="Max error (degrees)", default=DEFAULT_MAX_ERROR_DEG,
                                 min=0.0, max=180.0, precision=3, options={"HIDDEN"},
                                 description="Saved value of Max error, in degrees")
    max_error: _shown_as("max_error_deg", DEG, name="Max error", min=0.0, max=180.0 * DEG,
                         precision=2,
                         description="Largest error the bake measured that an interpolated "
                                     "ray may have. Smaller: more accurate, more rays traced, "
                                     "slower renders")
    use_mirror_normal: BoolProperty(name="Reflect about normal",
                                    default=QUERY.mirror_rays != "interpolate",
                                    description="Mirrors: reflect the view ray about the "
                                                "interpolated surface normal instead of "
                                                "interpolating the reflected ray. Sharper "
                                                "reflections at about the same cost")
    use_mirror_newton: BoolProperty(name="Exact mirror hits",
                                    default=QUERY.mirror_rays == "newton",
                                    description="Mirrors: find the exact point and normal on "
                                                "the surface before reflecting. Exact "
                                                "reflections, more time per ray; fewer rays "
                                                "are traced")
    use_path_identity: BoolProperty(name="Path identity", default=QUERY.path_identity,
                                    description="Trace a ray whose nearby samples take "
                                                "different paths through the object (hit "
                                                "different surfaces in a different order). "
                                                "Safer at edges, more rays traced")
    use_solve_paths: BoolProperty(name="Solve along sample paths", default=QUERY.solve_paths,
                                  description="A ray that Max error or Path identity would "
                                              "trace, or with too few nearby samples, is "
                                              "first solved exactly along the path of its "
                                              "nearest sample (the same surfaces in the same "
                                              "order); only a ray that leaves that path is "
                                              "traced. Off: trace every such ray")
    many_classes: EnumProperty(
        name="More than two classes",
        items=[("FIRST_HIT", "First hit", "Take the class of the ray's exact first hit "
                                          "(a ray that misses the object is answered "
                                          "exactly). Fewer rays traced"),
               ("TRACE", "Trace", "Trace the ray: exact, more rays traced, slower "
                                  "renders")],
        default=QUERY.many_classes.upper(),
        description="A ray whose nearby samples first hit more than two equivalence "
                    "classes (see Equivalence Classes): take the class of its exact first "
                    "hit, or trace it")
    # ---- viewpoint selection
    bake_for_cameras: BoolProperty(name="Bake for scene cameras", default=True,
                                   description="Bake only what the scene's cameras see. Off: "
                                               "bake every viewpoint around the object, many "
                                               "times the time and cache")
    use_frame_range: BoolProperty(name="Frame range", default=True,
                                  description="Cover the cameras' positions over the whole "
                                              "frame range (else the current frame only): more "
                                              "bake time and cache for a moving camera")
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
    custom_highlight: BoolProperty(name="Custom Highlight", default=False,
                                   description="Use the Highlight and Shininess below for the "
                                               "specular object's highlight instead of the "
                                               "shader's Roughness (which gives none for a "
                                               "sharp surface: it reflects the lights)")
    specular: FloatProperty(name="Highlight", default=0.25, min=0.0, max=10.0,
                            description="Phong highlight weight of the specular object")
    shininess: FloatProperty(name="Shininess", default=96.0, min=1.0, max=10000.0,
                             description="Phong exponent of the highlight")


class RIRAY_PG_world(bpy.types.PropertyGroup):
    ambient: FloatProperty(name="Ambient (W/m²)", default=0.0, min=0.0, soft_max=10.0,
                           description="Constant ambient irradiance added to the lights for "
                                       "the environment's diffuse surfaces, in watts per "
                                       "square metre")


class RIRAY_PG_view_layer(bpy.types.PropertyGroup):
    use_pass_traced: BoolProperty(name="Traced", default=True,
                                  description="Mask of the object rays that fell back to tracing")
    use_pass_angle_error: BoolProperty(name="Angle Error", default=False,
                                       description="Angle (degrees) between the output ray used "
                                                   "and the exact one (traces every object ray "
                                                   "a second time)")


class RIRAY_PG_scene(bpy.types.PropertyGroup):
    # Files saved when a scene rendered one specular object name it here: that object is still
    # rendered as one (export.specular_objects); not shown, nothing sets it.
    target: PointerProperty(name="Object", type=bpy.types.Object, poll=_poll_target,
                            description="The specular object of files saved by earlier "
                                        "versions (rendered as one; each object's own RI-Tree "
                                        "Object mark now says it)")
    allow_tracing: BoolProperty(name="Trace without tree", default=True,
                                description="Trace an object exactly when it has no RI-Tree or "
                                            "its tree is stale (else the render fails)")
    samples: IntProperty(name="Samples", default=Shot.samples, min=1, max=4096, soft_max=64,
                         description="Camera rays per pixel: 1 is the pixel centre; more "
                                     "smooth the edges (anti-aliasing), the render time "
                                     "grows with the count")
    render_processes: IntProperty(name="Processes", default=0, min=0, max=256,
                                  description="Worker processes for RI-Tree Preview renders "
                                              "(0: automatic - every core on Linux, one "
                                              "elsewhere, where forking Blender is unsafe)")
    max_events: IntProperty(name="Max events", default=RenderSettings.max_events, min=1, max=64,
                            description="Reflections and refractions followed through the "
                                        "object before a ray is given up (black). More: "
                                        "longer light paths inside the glass, slower "
                                        "bakes and renders")


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
              "max_error_deg", "use_path_identity", "use_solve_paths", "many_classes",
              "use_mirror_normal", "use_mirror_newton")


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
            "solve_paths": bool(p.use_solve_paths),
            "many_classes": p.many_classes.lower(),
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
