"""Render engine "RI-Tree Preview" (bl_idname RIRAY): the scene camera's view, F12 /
bpy.ops.render.render (stills and animations), independent of any viewport.

Per frame: export the scene from the render depsgraph (export.export_scene) with every
specular object (export.specular_objects: marked RI-Tree Object, or with a sharp glass or
mirror material), make one core SceneTracer per object, then render shares of pixels through
core's frame pipeline (render/frame.py: ``shade_share``, the nearest object winning and the
rays leaving one meeting the others); each object's rays are answered by its own baked
RI-Tree (backend.tree_answerer) when a fresh tree exists and loads, else traced exactly (the
user is told, object by object; scene.riray.allow_tracing = False turns that into an error).
Each object's tracer and loaded tree and the environment are kept between frames and renders
while what they are built from is unchanged (reuse.py); the stats say what each frame
exported, built and reused, and each object's traced share.
scene.riray.samples camera rays per pixel (core render/film.py: one is the pixel centre; more
are stratified and filtered with Blackman-Harris, 1.5 px, as Cycles does).
Passes: Combined, "Traced" (the fraction of a pixel's samples that fell back to
tracing: 1 or 0 with one sample) and "Angle Error" (degrees between the output ray used and the
exact one, the mean over the pixel's samples; traces the object rays again).
Progress / cancel through update_progress / test_break; every failure is reported with
self.report({'ERROR'}) - never a silent black frame. Chunks run on scene.riray.render_processes
worker processes (core.parallel.map_chunks: forked children that only run numpy code and
return arrays; automatic = every core on Linux, in-process elsewhere: forking Blender on macOS
is unsafe and Windows has no fork).
"""

from __future__ import annotations

import os
import sys
import time
import traceback

import bpy
import numpy as np

from ..core.parallel import map_chunks
from ..core.render.film import Film
from ..core.render.frame import ExactAnswerer, Specular, shade_share, share_size
from ..core.ritree.answers import OUTSIDE, is_traced
from ..core.trace.patches import PatchTracer
from ..core.trace.scene_tracer import SceneTracer, build_environment
from . import backend, cache, reuse
from .export import export_camera, export_scene, specular_fingerprint, specular_objects
from .properties import query_options
from .report import ExportError, Report

ENGINE_ID = "RIRAY"
# Shares of the frame per worker process: each share is one shade_share call (one RI-Tree
# query and tracer batch); four per worker give progress and Esc steps of about a quarter of a
# worker's work without making the batches small.
SHARES_PER_WORKER = 4
# The last frame rendered by this process (numpy arrays, top row first): tests and scripts.
LAST_RENDER: dict = {}


class _Cancelled(Exception):
    """Esc during a render (raised from the progress callback; stops the worker pool)."""


def render_processes(setting: int) -> int:
    """Worker processes for a render: the setting, or automatically every core on Linux and 1
    elsewhere (forking Blender is unsafe on macOS; Windows has no fork)."""
    if setting > 0:
        return int(setting)
    return max(1, os.cpu_count() or 1) if sys.platform.startswith("linux") else 1


def angle_error_deg(a: np.ndarray, b: np.ndarray, null_a: np.ndarray, null_b: np.ndarray):
    """Angle in degrees between output directions; 0 where both are null, 180 where one is."""
    cos = np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0)
    ang = np.degrees(np.arccos(cos))
    ang = np.where(null_a & null_b, 0.0, ang)
    return np.where(null_a ^ null_b, 180.0, ang)


class RirayRenderEngine(bpy.types.RenderEngine):
    bl_idname = ENGINE_ID
    bl_label = "RI-Tree Preview"
    bl_use_preview = False
    bl_use_postprocess = True
    bl_use_shading_nodes_custom = False

    # ------------------------------------------------------------------ passes
    def update_render_passes(self, scene=None, renderlayer=None):
        self.register_pass(scene, renderlayer, "Combined", 4, "RGBA", "COLOR")
        opts = renderlayer.riray
        if opts.use_pass_traced:
            self.register_pass(scene, renderlayer, "Traced", 1, "X", "VALUE")
        if opts.use_pass_angle_error:
            self.register_pass(scene, renderlayer, "Angle Error", 1, "X", "VALUE")

    # ------------------------------------------------------------------ render
    def render(self, depsgraph):
        try:
            self._render(depsgraph)
        except ExportError as exc:
            self.report({"ERROR"}, f"RI-Tree Preview: {exc}")
        except Exception as exc:   # noqa: BLE001 - shown to the user, never a silent frame
            traceback.print_exc()
            self.report({"ERROR"}, f"RI-Tree Preview failed: {type(exc).__name__}: {exc}")

    def _render(self, depsgraph):
        scene, view_layer = depsgraph.scene, depsgraph.view_layer
        t_start = time.perf_counter()
        targets, core_scene = self._export(depsgraph)
        export_s = time.perf_counter() - t_start
        region = render_region(scene.render, int(self.resolution_x), int(self.resolution_y))
        w, h = region[2:]
        frame_parts = reuse.FrameParts(reuse.MEMO)
        keys = [reuse.object_key(o) for o in core_scene.objects]
        shadow_key = keys[0] if len(keys) == 1 else reuse.fingerprint(keys)
        env = frame_parts.get("environment", lambda: reuse.environment_key(core_scene, shadow_key),
                              lambda: build_environment(core_scene))
        objs, statuses = [], []
        for i, (target, key) in enumerate(zip(targets, keys)):
            kind = part_kind(i, target.name)
            tracer = frame_parts.get(f"object{kind}", lambda: key,
                                     lambda: PatchTracer(core_scene.objects[i]))
            st = SceneTracer(core_scene.view(i), tracer=tracer, env=env)
            answerer, status = self._answerer(depsgraph, target, st, frame_parts, key, kind)
            objs.append(Specular(st, answerer))
            statuses.append(status)
        build_s = time.perf_counter() - t_start - export_s
        film = region_film(core_scene.cameras[0], int(self.resolution_x),
                           int(self.resolution_y), region, scene.riray.samples)
        want_angle = bool(view_layer.riray.use_pass_angle_error) and any(
            o.answerer is not None for o in objs)
        through = [o.answerer is not None for o in objs]
        objs = [Specular(o.st, o.answerer or ExactAnswerer(o.st)) for o in objs]

        def work(a, b):
            """One share of rays: its pixels' colour, traced and angle sums; object time and
            ray counts per object."""
            rays = film.rays(a, b)
            share = shade_share(objs[0].st, *rays, objs[0].answerer, objs[1:])
            color, tr, ang, counts = _passes(objs, share, rays, want_angle)
            part = film.develop(a, b, {"color": color}, {"traced": tr, "angle": ang})
            return part, share.stats["object_cpu_s"], share.stats.get("solved_along_path", 0), \
                counts

        t_render = time.perf_counter()
        procs = render_processes(scene.riray.render_processes)
        try:
            parts = map_chunks(work, film.n_rays,
                               share_size(film.n_rays, procs, SHARES_PER_WORKER), procs,
                               self._progress)
        except _Cancelled:
            self.report({"WARNING"}, "render cancelled")
            return
        dev = film.join(p[0] for p in parts)
        color = dev.images["color"].reshape(-1, 3)
        traced, angle = ((dev.box[k].ravel() / film.samples).astype(np.float32)
                         for k in ("traced", "angle"))
        counts = np.sum([p[3] for p in parts], axis=0) if parts else np.zeros((len(objs), 3))
        hits, n_traced, outside = (int(x) for x in counts.sum(axis=0))
        solved = sum(p[2] for p in parts)
        per_object = {t.name: object_stats(c, ok, st["state"])
                      for t, c, ok, st in zip(targets, counts, through, statuses)}
        stats = {"frame": scene.frame_current, "width": w, "height": h,
                 "samples": film.samples, "object_pixels": hits, "traced_pixels": n_traced,
                 "traced_fraction": n_traced / hits if hits else 0.0,
                 "solved_along_path": solved, "solved_fraction": solved / hits if hits else 0.0,
                 "outside_fraction": outside / hits if hits else 0.0,
                 "object_time_s": sum(p[1] for p in parts),
                 "render_time_s": time.perf_counter() - t_render, "export_s": export_s,
                 "build_s": build_s, "build_parts_s": frame_parts.seconds,
                 "reused": frame_parts.reused, "objects": per_object,
                 "tree": _common(o["tree"] for o in per_object.values()),
                 "mode": _common(o["mode"] for o in per_object.values()),
                 "processes": procs}
        self._write((color, traced, angle), region, stats)
        self.update_stats("", status_line(stats))
        for name, o in per_object.items():
            if o["outside_fraction"]:
                self.report({"WARNING"}, outside_message(
                    name, core_scene.cameras[0].name, {**o, "frame": stats["frame"]}))

    def _export(self, depsgraph):
        """(the specular objects, the core scene with the render camera); ExportError if the
        scene has none of either."""
        scene = depsgraph.scene
        targets = specular_objects(depsgraph)
        if not targets:
            raise ExportError("no specular object to render: give an object a sharp glass or "
                              "mirror material, or tick RI-Tree Object in its Object "
                              "Properties > Bake RI-Tree panel")
        cam_obj = self.camera_override or scene.camera
        if cam_obj is None:
            raise ExportError("the scene has no camera")
        self.update_stats("", "RI-Tree Preview: exporting scene")
        report = Report()
        core_scene = export_scene(depsgraph, targets, report, cameras="NONE")
        core_scene.cameras = [export_camera(cam_obj.evaluated_get(depsgraph), scene, report)]
        if cam_obj.type == "CAMERA" and cam_obj.data.dof.use_dof:
            report.warning(f"camera {cam_obj.name}: depth of field is not rendered (everything "
                           "is in focus)")
        report.emit(self.report, "WARNING")
        return targets, core_scene

    def _answerer(self, depsgraph, target, st, frame_parts, obj_key, kind=""):
        """(the tree's answerer, or None to trace the object exactly; the cache status). The
        loaded tree comes from ``frame_parts`` (reuse.py: kept while the file and the object,
        ``obj_key``, are unchanged; ``kind``: the object's part_kind), with the occlusion
        proxy of the object's tracer."""
        status = cache.tree_status(target, depsgraph, memo=False,
                                   current=specular_fingerprint(st.scene.object))
        how = status["message"]
        if status["state"] == "fresh":
            path, options = status["path"], query_options(target)
            try:
                tree = frame_parts.get(f"tree{kind}", lambda: reuse.tree_key(path, obj_key),
                                       lambda: backend.load_tree(path)[0])
                if options["solve_paths"]:      # kept on the tracer (a cached_property)
                    frame_parts.timed(f"proxy{kind}", lambda: st.tracer.occlusion_proxy,
                                      reused="occlusion_proxy" in vars(st.tracer))
                return frame_parts.timed(f"query{kind}", lambda: backend.tree_answerer(
                    st, tree, options)), status
            except (backend.TreeCacheError, OSError) as exc:   # damaged, gone, not this object's
                how = f"the RI-Tree cache cannot be used ({exc})" + (
                    "" if "re-bake" in str(exc) else "; re-bake")
        if not depsgraph.scene.riray.allow_tracing:
            raise ExportError(f"{target.name}: {how}; tracing without a tree is switched "
                              "off (Render Properties > RI-Tree > Trace without tree)")
        self.report({"WARNING"}, f"{target.name}: {how}; the object is traced exactly")
        return None, status

    def _progress(self, frac):
        if self.test_break():
            raise _Cancelled
        self.update_progress(frac)
        self.update_stats("", f"RI-Tree Preview: {100 * frac:.0f}%")

    # ------------------------------------------------------------------ output
    def _write(self, images, region, stats):
        """Combined, Traced and Angle Error passes (``images``: flat colour, traced, angle
        arrays of the ``region``'s pixels, top row first) and the stamp fields."""
        (color, traced, angle), (w, h) = images, region[2:]
        img = color.reshape(h, w, 3)
        rgba = np.ones((h, w, 4), np.float32)
        rgba[..., :3] = img[::-1]
        result = self.begin_result(0, 0, w, h)      # the region's own pixel coordinates
        try:
            layer = result.layers[0]
            layer.passes["Combined"].rect.foreach_set(rgba.ravel())
            extra = {"Traced": traced, "Angle Error": angle}
            for name, arr in extra.items():
                p = layer.passes.find_by_name(name, self.active_view_get())
                if p is not None:
                    p.rect.foreach_set(np.ascontiguousarray(arr.reshape(h, w)[::-1]).ravel())
        finally:
            self.end_result(result)
        # The frame's own result (not the pixels' one) carries the metadata saved with images.
        final = self.get_result()
        final.stamp_data_add_field("riray traced fraction", f"{stats['traced_fraction']:.4f}")
        final.stamp_data_add_field("riray render s", f"{stats['render_time_s']:.3f}")
        LAST_RENDER.clear()
        LAST_RENDER.update(image=img.copy(), traced=traced.reshape(h, w).copy(),
                           angle=angle.reshape(h, w).copy(), stats=stats)


def outside_message(name: str, camera: str, stats: dict) -> str:
    """The warning for a frame whose object rays left the region the tree was baked for."""
    return (f"{name}: {100 * stats['outside_fraction']:.0f}% of its pixels lie outside the "
            f"region its RI-Tree was baked for (camera {camera}, frame {stats['frame']}) and "
            "were traced exactly: bake again with this camera in place, or with Bake for "
            "scene cameras > Frame range on for an animation")


def status_line(stats: dict) -> str:
    """The status bar's summary of a rendered frame's ``stats``."""
    hits = stats["object_pixels"]
    extra = (f" | solved along path {100 * stats['solved_fraction']:.1f}%"
             if stats["solved_along_path"] else "")
    if stats["outside_fraction"]:
        extra += f" | outside the baked region {100 * stats['outside_fraction']:.1f}%"
    reused = ", ".join(stats["reused"]) or "nothing"
    objects = stats.get("objects", {})
    if len(objects) > 1:
        extra = " (" + ", ".join(f"{name} {100 * o['traced_fraction']:.1f}%"
                                 for name, o in objects.items()) + ")" + extra
    return (f"RI-Tree Preview | traced {100 * stats['traced_fraction']:.1f}% of {hits} object "
            f"pixels{extra} | object {stats['object_time_s']:.2f} s | render "
            f"{stats['render_time_s']:.2f} s | export {stats['export_s']:.2f} s | build "
            f"{stats['build_s']:.2f} s (reused {reused})")


def render_region(render, width: int, height: int) -> tuple[int, int, int, int]:
    """(x, y, width, height) in pixels, bottom-up as Blender counts them, of what is rendered:
    the render region (border) when it is on, as Blender rounds it, else the whole frame."""
    if not render.use_border:
        return 0, 0, width, height
    x0, x1 = int(render.border_min_x * width), int(render.border_max_x * width)
    y0, y1 = int(render.border_min_y * height), int(render.border_max_y * height)
    return x0, y0, max(x1 - x0, 1), max(y1 - y0, 1)


def region_film(camera, width: int, height: int, region, samples: int) -> Film:
    """The film of the ``region``'s pixels (bottom-up, as Blender counts them) of the frame,
    ``samples`` camera rays per pixel."""
    x0, y0, w, h = region
    return Film(camera, width, height, samples, (x0, height - y0 - h, w, h))


def part_kind(index: int, name: str) -> str:
    """The suffix of a specular object's parts in reuse.MEMO: none for the first object (a
    scene of one keeps the names "object", "tree", ...), " [NAME]" for the others."""
    return "" if index == 0 else f" [{name}]"


def _common(values) -> str:
    """The one value of ``values``, or "mixed" when they differ."""
    values = set(values)
    return values.pop() if len(values) == 1 else "mixed"


def object_stats(counts, through_tree: bool, tree_state: str) -> dict:
    """One specular object's share of a frame from its (pixels, traced, outside the baked
    region) ray counts."""
    hits, traced, outside = (int(x) for x in counts)
    return {"object_pixels": hits, "traced_pixels": traced,
            "traced_fraction": traced / hits if hits else 0.0,
            "outside_fraction": outside / hits if hits else 0.0,
            "mode": "tree" if through_tree else "exact", "tree": tree_state}


def _passes(objs, share, rays, want_angle: bool):
    """A rendered share's pass values: (colour, traced flag, angle error in degrees against
    exact tracing when ``want_angle``, (objects, 3) counts of each object's rays: those it is
    the nearest hit of, traced, outside its tree's region)."""
    n = len(share.color)
    tr = np.zeros(n, np.float32)
    ang = np.zeros(n, np.float32)
    counts = np.zeros((len(share.objects), 3), np.int64)
    for k, (obj, o) in enumerate(zip(objs, share.objects)):
        hit, codes = o.hit, o.answer.answer
        if codes is None:
            tr[hit] = 1.0
            counts[k] = len(hit), len(hit), 0
            continue
        tr[hit] = is_traced(codes)[o.won]
        counts[k] = len(hit), int(tr[hit].sum()), np.count_nonzero(codes[o.won] == OUTSIDE)
        if want_angle and len(hit):
            used = o.answer.rays.take(o.won)
            exact = obj.st.object_function(rays[0][hit], rays[1][hit])
            ang[hit] = angle_error_deg(used.out_dir, exact.out_dir, used.null, exact.null)
    return share.color, tr, ang, counts


# Built-in panels that show for every engine (they list BLENDER_RENDER) but whose settings
# riray replaces or ignores: the light panel with the light type only (DATA_PT_EEVEE_light has
# colour and power) and the spot shape (spot lights render as point lights).
EXCLUDED_PANELS = {"DATA_PT_light", "DATA_PT_spot"}
# Engine-specific built-in panels whose settings riray reads: material slots, material and
# world Surface, the light's colour and power, depth of field (exported, reported as not
# rendered), and the view layer's Passes (RI-Tree's passes are drawn inside it).
EXTRA_PANELS = ("EEVEE_MATERIAL_PT_context_material", "EEVEE_MATERIAL_PT_surface",
                "EEVEE_WORLD_PT_surface", "DATA_PT_EEVEE_light", "DATA_PT_camera_dof",
                "VIEWLAYER_PT_layer_passes")


def get_panels():
    """Built-in panels that also show for this engine (output, camera, lights, materials...)."""
    every = [p for p in bpy.types.Panel.__subclasses__() if hasattr(p, "COMPAT_ENGINES")]
    # Some panels share one engine set (the node editor's copies of the light panels).
    excluded = {id(p.COMPAT_ENGINES) for p in every if p.__name__ in EXCLUDED_PANELS}
    panels = []
    for panel in every:
        engines = panel.COMPAT_ENGINES
        if id(engines) in excluded:
            continue
        if "BLENDER_RENDER" in engines or panel.__name__ in EXTRA_PANELS:
            panels.append(panel)
    return panels


@bpy.app.handlers.persistent
def _forget_parts(*_args):
    """Another file was loaded: let go of the parts kept from renders (reuse.MEMO)."""
    reuse.MEMO.clear()


def register():
    bpy.utils.register_class(RirayRenderEngine)
    for panel in get_panels():
        panel.COMPAT_ENGINES.add(ENGINE_ID)
    bpy.app.handlers.load_post.append(_forget_parts)


def unregister():
    if _forget_parts in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_forget_parts)
    reuse.MEMO.clear()
    for panel in get_panels():
        panel.COMPAT_ENGINES.discard(ENGINE_ID)
    bpy.utils.unregister_class(RirayRenderEngine)
