"""Render engine "RI-Tree Preview" (bl_idname RIRAY): the scene camera's view, F12 /
bpy.ops.render.render (stills and animations), independent of any viewport.

Per frame: export the scene from the render depsgraph (export.export_scene), build the core
SceneTracer, then render rows of pixels in chunks with core's ``render_pixels``; the object's rays
are answered by the baked RI-Tree (backend.tree_object_fn) when a fresh tree exists and loads,
else traced exactly (the user is told; scene.riray.allow_tracing = False turns that into an
error).
Passes: Combined, "Traced" (1 where an object ray fell back to tracing) and "Angle Error"
(degrees between the output ray used and the exact one; traces the object rays again).
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

from ..core.render.camera import camera_rays
from ..core.parallel import map_chunks
from ..core.render.exact import SceneTracer, render_pixels, share_size
from . import backend, cache
from .export import export_camera, export_scene
from .properties import query_options
from .report import ExportError, Report

ENGINE_ID = "RIRAY"
# Shares of the frame per worker process: each share is one render_pixels call (one RI-Tree
# query and tracer batch); four per worker give progress and Esc steps of about a quarter of a
# worker's work without making the batches small.
SHARES_PER_WORKER = 4
# The last frame rendered by this process (numpy arrays, top row first): tests and scripts.
LAST_RENDER: dict = {}


def resolve_target(scene):
    """The specular object: scene.riray.target, else the only visible SURFACE object."""
    if scene.riray.target is not None:
        return scene.riray.target
    surfaces = [o for o in scene.objects if o.type == "SURFACE" and not o.hide_render]
    return surfaces[0] if len(surfaces) == 1 else None


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
        scene = depsgraph.scene
        view_layer = depsgraph.view_layer
        t_start = time.perf_counter()
        target = resolve_target(scene)
        if target is None:
            raise ExportError("no object to render: set the RI-Tree object in Render Properties "
                              "> RI-Tree (or bake one)")
        cam_obj = self.camera_override or scene.camera
        if cam_obj is None:
            raise ExportError("the scene has no camera")
        self.update_stats("", "RI-Tree Preview: exporting scene")
        report = Report()
        core_scene = export_scene(depsgraph, target, report, cameras="NONE")
        core_scene.cameras = [export_camera(cam_obj.evaluated_get(depsgraph), scene, report)]
        w, h = int(self.resolution_x), int(self.resolution_y)
        if scene.render.use_border:
            report.info("render region (border) ignored: the full frame is rendered")
        report.emit(self.report, "WARNING")

        # -- tree or exact tracing
        st = SceneTracer(core_scene)
        status = cache.tree_status(target, depsgraph, memo=False)
        object_fn, how = None, ""
        if status["state"] == "fresh":
            try:
                tree, doc = backend.load_tree(status["path"])
                object_fn = backend.tree_object_fn(st, tree, doc, query_options(target))
            except (backend.TreeCacheError, OSError) as exc:   # damaged, gone, not this object's
                how = f"the RI-Tree cache cannot be used ({exc})" + (
                    "" if "re-bake" in str(exc) else "; re-bake")
        else:
            how = status["message"]
        if object_fn is None:
            if not scene.riray.allow_tracing:
                raise ExportError(f"{target.name}: {how}; tracing without a tree is switched "
                                  "off (Render Properties > RI-Tree > Trace without tree)")
            self.report({"WARNING"}, f"{target.name}: {how}; the object is traced exactly")
        build_s = time.perf_counter() - t_start

        opts = view_layer.riray
        want_angle = bool(opts.use_pass_angle_error)
        o, d = camera_rays(core_scene.cameras[0], w, h)
        n = len(o)

        def work(a, b):
            """One chunk of pixels: colour, traced flags, angle errors, object time."""
            captured = {}

            def exact_fn(oo, dd, tmax):
                res = st.object_function(oo, dd, tmax)
                captured["res"], captured["traced"] = res, np.ones(len(oo), bool)
                return res, {}

            def tree_fn(oo, dd, tmax):
                res, extra = object_fn(oo, dd, tmax)
                captured["res"] = res
                captured["traced"] = np.asarray(extra.pop("traced", np.zeros(len(oo), bool)),
                                                bool)
                return res, extra

            col, stats, hit = render_pixels(st, o[a:b], d[a:b],
                                            exact_fn if object_fn is None else tree_fn)[:3]
            tr = np.zeros(b - a, np.float32)
            ang = np.zeros(b - a, np.float32)
            if len(hit):
                res = captured["res"]
                tr[hit] = captured["traced"][res.hit]
                if want_angle and object_fn is not None:
                    used = res.take(res.hit)
                    exact = st.object_function(o[a + hit], d[a + hit])
                    ang[hit] = angle_error_deg(used.out_dir, exact.out_dir, used.null,
                                               exact.null)
            return col, tr, ang, stats["object_cpu_s"], len(hit)

        def progress(frac):
            if self.test_break():
                raise _Cancelled
            self.update_progress(frac)
            self.update_stats("", f"RI-Tree Preview: {100 * frac:.0f}%")

        t_render = time.perf_counter()
        procs = render_processes(scene.riray.render_processes)
        try:
            parts = map_chunks(work, n, share_size(n, procs, SHARES_PER_WORKER), procs,
                               progress)
        except _Cancelled:
            self.report({"WARNING"}, "render cancelled")
            return
        color, traced, angle = (np.concatenate([p[i] for p in parts]) for i in range(3))
        obj_time = sum(p[3] for p in parts)
        hits = sum(p[4] for p in parts)
        traced_hits = int(traced.sum())
        render_s = time.perf_counter() - t_render
        frac_traced = traced_hits / hits if hits else 0.0
        stats = {"frame": scene.frame_current, "width": w, "height": h,
                 "object_pixels": hits, "traced_pixels": traced_hits,
                 "traced_fraction": frac_traced, "object_time_s": obj_time,
                 "render_time_s": render_s, "export_build_s": build_s,
                 "tree": status["state"], "mode": "tree" if object_fn else "exact",
                 "processes": procs}
        self._write(scene, view_layer, color, traced, angle, w, h, stats)
        self.update_stats("", f"RI-Tree Preview | traced {100 * frac_traced:.1f}% of "
                              f"{hits} object pixels | object {obj_time:.2f} s | render "
                              f"{render_s:.2f} s | export+build {build_s:.2f} s")

    # ------------------------------------------------------------------ output
    def _write(self, scene, view_layer, color, traced, angle, w, h, stats):
        img = color.reshape(h, w, 3)
        rgba = np.ones((h, w, 4), np.float32)
        rgba[..., :3] = img[::-1]
        result = self.begin_result(0, 0, w, h)
        try:
            layer = result.layers[0]
            layer.passes["Combined"].rect.foreach_set(rgba.ravel())
            extra = {"Traced": traced, "Angle Error": angle}
            for name, arr in extra.items():
                p = layer.passes.find_by_name(name, self.active_view_get())
                if p is not None:
                    p.rect.foreach_set(np.ascontiguousarray(arr.reshape(h, w)[::-1]).ravel())
            try:
                result.stamp_data_add_field("riray traced fraction",
                                            f"{stats['traced_fraction']:.4f}")
                result.stamp_data_add_field("riray render s", f"{stats['render_time_s']:.3f}")
            except (AttributeError, RuntimeError, TypeError):
                pass
        finally:
            self.end_result(result)
        LAST_RENDER.clear()
        LAST_RENDER.update(image=img.copy(), traced=traced.reshape(h, w).copy(),
                           angle=angle.reshape(h, w).copy(), stats=stats)


def get_panels():
    """Built-in panels that should also show for this engine (lights, camera, materials...)."""
    exclude = {"VIEWLAYER_PT_filter", "VIEWLAYER_PT_layer_passes"}
    panels = []
    for panel in bpy.types.Panel.__subclasses__():
        engines = getattr(panel, "COMPAT_ENGINES", None)
        if engines is not None and "BLENDER_RENDER" in engines and panel.__name__ not in exclude:
            panels.append(panel)
    return panels


def register():
    bpy.utils.register_class(RirayRenderEngine)
    for panel in get_panels():
        panel.COMPAT_ENGINES.add(ENGINE_ID)


def unregister():
    for panel in get_panels():
        panel.COMPAT_ENGINES.discard(ENGINE_ID)
    bpy.utils.unregister_class(RirayRenderEngine)
