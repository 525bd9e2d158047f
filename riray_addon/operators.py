"""Operators: riray.bake (+ cancel / clear / estimate), riray.export_scene, spline class groups.

``bpy.ops.riray.bake(...)`` takes the tree parameters as options (those given are stored on the
object first). From the UI (invoke) it runs modal: the bake runs in a worker process, a timer
polls it, the panel and the status bar show a progress bar with ETA, Esc or the Cancel button
stops it (any previous cache is kept). From a script (execute) it blocks until the bake ends
unless ``wait=False`` (then a bpy.app.timers function finishes it; in background mode call
``poll_jobs()`` yourself). ``bpy.ops.riray.bake_estimate`` runs the same way: its work (the
cameras' region, a trial bake) in a worker process, never on Blender's main thread.
"""


import json
import os
import re
import time

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, StringProperty

from ..core.scene.io import save_scene
from . import backend, cache, compat
from .export import export_camera, export_scene, object_fingerprint
from .jobs import (ESTIMATES, JOBS, BakeJob, EstimateJob, format_bytes, format_duration,
                   running_job)
from .properties import BAKE_KEYS, QUALITY, QUERY_KEYS, bake_params, scheduler_address
from .report import ExportError, Report

TIMER_S = 0.1
# Deepest viewpoint level a bake may reach: Viewpoint depth + Viewpoint refine (core's rule).
MAX_VIEWPOINT_LEVEL = 10


# --------------------------------------------------------------------------- helpers
def target_object(context, name: str = ""):
    if name:
        obj = bpy.data.objects.get(name)
        if obj is None:
            raise ExportError(f"no object named {name!r}")
        return obj
    obj = context.active_object if hasattr(context, "active_object") else None
    if obj is None:
        raise ExportError("no active object: select the NURBS surface to bake")
    return obj


def _animated(idb) -> bool:
    """Whether keys or drivers can change ``idb`` (an object or its data) from frame to frame."""
    ad = getattr(idb, "animation_data", None)
    return ad is not None and (ad.action is not None or len(ad.drivers) > 0
                               or len(ad.nla_tracks) > 0)


def camera_moves(cam) -> bool:
    """Whether the camera object may stand or look elsewhere on another frame: it, its camera
    data or a parent is animated or constrained, or it hangs from a vertex or bone (whose
    object may deform)."""
    obj = cam
    while obj is not None:
        if _animated(obj) or _animated(obj.data) or len(obj.constraints) > 0:
            return True
        if obj.parent is not None and obj.parent_type != "OBJECT":
            return True
        obj = obj.parent
    return False


def camera_views(context, params: dict, report: Report) -> list:
    """Core cameras for every scene camera at every frame of the range (or the current frame),
    named "<camera> (frame <frame>)", as messages show them: what a camera-driven bake must
    cover. Only when a camera moves are the frames visited: changing frames evaluates the
    whole scene (its heavy, animated environment too) on Blender's main thread."""
    scene = context.scene
    cams = [o for o in scene.objects if o.type == "CAMERA"]
    frames = [scene.frame_current]
    if params.get("use_frame_range") and any(camera_moves(c) for c in cams):
        frames = list(range(scene.frame_start, scene.frame_end + 1, max(1, scene.frame_step)))
    out, keep, seen = [], scene.frame_current, set()
    try:
        for f in frames:
            if f != scene.frame_current:
                scene.frame_set(f)
            dg = context.evaluated_depsgraph_get()
            for c in cams:
                cam = export_camera(c.evaluated_get(dg), scene, report)
                key = (c.name, np.round(np.asarray(cam.matrix_world), 9).tobytes(), cam.kind,
                       cam.lens, cam.ortho_scale, cam.shift_x, cam.shift_y, cam.sensor_fit,
                       cam.sensor_width, cam.sensor_height)
                if key not in seen:                 # a still camera counts once
                    seen.add(key)
                    cam.name = f"{c.name} (frame {f})"
                    out.append(cam)
    finally:
        if scene.frame_current != keep:
            scene.frame_set(keep)
    return out


def checked_params(obj, options: dict | None = None) -> dict:
    """The object's bake parameters (with ``options``, setting -> value, as if set on it),
    refused at once (ExportError in the panel's terms) when core's bake would reject them.
    Viewpoint refinement only applies to camera bakes, so it is off (and not checked)
    otherwise."""
    params = {**bake_params(obj), **(options or {})}
    if not params["bake_for_cameras"]:
        params["viewpoint_refine"] = params["finest_min_traced"] = 0
    label = {k: p.name for k, p in obj.riray.bl_rna.properties.items()}
    vd, refine = params["viewpoint_depth"], params["viewpoint_refine"]
    if vd + refine > MAX_VIEWPOINT_LEVEL:
        raise ExportError(f"{obj.name}: {label['viewpoint_depth']} {vd} + "
                          f"{label['viewpoint_refine']} {refine} is more than "
                          f"{MAX_VIEWPOINT_LEVEL}: lower one of them")
    if params["min_direction_depth"] > params["direction_depth"]:
        raise ExportError(f"{obj.name}: {label['min_direction_depth']} "
                          f"{params['min_direction_depth']} is more than "
                          f"{label['direction_depth']} {params['direction_depth']}")
    try:
        backend.bake_params(params)
    except ValueError as exc:          # a rule the checks above do not know
        raise ExportError(f"{obj.name}: the bake settings are refused: "
                          f"{panel_terms(str(exc), label)}") from None
    return params


def panel_terms(rule: str, label: dict) -> str:
    """Core's refusal of bake parameters in the panel's terms: without its prefix and its dump
    of every parameter, each setting called by its ``label``."""
    rule = rule.split(" (got ")[0].removeprefix("bake parameters: ")
    return re.sub(r"\b[a-z]+(?:_[a-z]+)+\b", lambda m: label.get(m[0], m[0]), rule)


def prepare_bake(context, obj, report: Report):
    """(core scene with the object + cameras, params, meta) for a bake of ``obj``. With "bake
    for scene cameras" the scene's cameras are every camera at every frame of the range, and
    params carries the render size they are seen at."""
    params = checked_params(obj)
    depsgraph = context.evaluated_depsgraph_get()
    scene = export_scene(depsgraph, obj, report, cameras="ALL", environment=False)
    params["width"], params["height"] = scene.render.width, scene.render.height
    if params["bake_for_cameras"]:
        views = camera_views(context, params, report)
        if views:
            scene.cameras = views
        else:
            report.warning("bake for scene cameras: the scene has no camera; baking everywhere")
            params["bake_for_cameras"] = False
            params["viewpoint_refine"] = params["finest_min_traced"] = 0
    params["camera_positions"] = [[float(x) for x in np.asarray(c.matrix_world)[:3, 3]]
                                  for c in scene.cameras]
    meta = {"object": obj.name, "fingerprint": object_fingerprint(obj, depsgraph),
            "params": params, "blend": bpy.data.filepath, "created": time.time(),
            "patches": len(scene.object.patches)}
    return scene, params, meta


def start_bake(context, obj, report: Report | None = None) -> BakeJob:
    report = report if report is not None else Report()
    if running_job(obj.name):
        raise ExportError(f"{obj.name}: a bake is already running")
    path = cache.bake_target(obj)
    cache.check_writable(path)
    scene, params, meta = prepare_bake(context, obj, report)
    obj.riray.specular = True       # it renders through its tree; the others stay as they are
    try:
        job = BakeJob(obj.name, path).start(scene, params, meta, scheduler_address(context))
    except (OSError, ValueError) as exc:     # ValueError: core refuses the exported scene
        raise ExportError(f"{obj.name}: cannot start the bake: {exc}") from None
    JOBS[obj.name] = job
    return job


def finish_job(job: BakeJob, report_fn=None) -> None:
    """Main thread, once a job ended: record the bake on the object and tell the user."""
    obj = bpy.data.objects.get(job.object_name)
    msg_level, msg = "INFO", ""
    if job.state == "done":
        doc = backend.read_header(job.cache_path) or {}
        meta = doc.get("meta", {})
        if obj is not None:
            if not obj.riray.cache_file:
                obj.riray.baked_cache = cache.as_setting(job.cache_path)
            obj.riray.baked_fingerprint = meta.get("fingerprint", "")
            obj.riray.baked_info = json.dumps({"bytes": job.bytes, "seconds": job.elapsed,
                                               "backend": doc.get("backend", "")})
        msg = (f"RI-Tree of {job.object_name} baked in {format_duration(job.elapsed)} "
               f"({format_bytes(job.bytes)}) -> {job.cache_path}")
    elif job.state == "cancelled":
        msg_level, msg = "WARNING", f"bake of {job.object_name} cancelled; previous cache kept"
    else:
        msg_level, msg = "ERROR", f"bake of {job.object_name} failed: {job.error}"
        if job.traceback:
            print(job.traceback)
    print(f"riray: {msg}")
    if report_fn is not None:
        report_fn({msg_level}, msg)
    cache.forget()          # forget memoized headers / fingerprints
    _redraw()


def poll_jobs() -> bool:
    """Poll every running bake and estimate, finishing the ones that ended; True while any
    still runs."""
    any_running = False
    for jobs, finish in ((JOBS, finish_job), (ESTIMATES, finish_estimate)):
        for job in list(jobs.values()):
            if job.running:
                if job.poll() == "running":
                    any_running = True
                else:
                    finish(job)
    _redraw()
    return any_running


def _timer_poll():
    return TIMER_S if poll_jobs() else None


def _redraw() -> None:
    wm = getattr(bpy.context, "window_manager", None)
    if wm is None:
        return
    for win in wm.windows:
        for area in win.screen.areas:
            if area.type in {"PROPERTIES", "VIEW_3D", "STATUSBAR"}:
                area.tag_redraw()


# --------------------------------------------------------------------------- operators
def _param_props():
    """Operator options mirroring the object's bake parameters (see properties), without the
    object's update callbacks (the options are copied onto the object, see _apply_options)."""
    from .properties import RIRAY_PG_object as PG
    ann = PG.__annotations__
    return {k: ann[k].function(**{o: v for o, v in ann[k].keywords.items() if o != "update"})
            for k in BAKE_KEYS + QUERY_KEYS}


class _JobModal:
    """invoke / modal of an operator that runs a job in a worker process (a bake, an
    estimate): from the UI, modal with a timer, Esc cancels; in the background or from a
    script without a window, ``execute``. The operator gives ``_start(context)`` (the job, or
    ExportError) and ``_finish(job)`` (its report)."""

    _timer = None
    _job = None

    def invoke(self, context, event):
        if context.window is None or bpy.app.background:
            return self.execute(context)
        try:
            self._job = self._start(context)
        except ExportError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        wm = context.window_manager
        self._timer = wm.event_timer_add(TIMER_S, window=context.window)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC" and event.value == "PRESS":
            job.cancel()
            return {"RUNNING_MODAL"}
        if event.type == "TIMER":
            job.poll()
            _redraw()
            if not job.running:
                context.window_manager.event_timer_remove(self._timer)
                self._finish(job)
                return {"FINISHED"} if job.state == "done" else {"CANCELLED"}
        return {"PASS_THROUGH"}


class RIRAY_OT_bake(_JobModal, bpy.types.Operator):
    """Bake the RI-Tree of the object in a worker process (Esc cancels)"""
    bl_idname = "riray.bake"
    bl_label = "Bake RI-Tree"
    bl_options = {"REGISTER"}

    object: StringProperty(name="Object", default="",
                           description="Object to bake (empty: the active object)")
    cache_file: StringProperty(name="Cache file", default="", subtype="FILE_PATH",
                               options=compat.BLEND_RELATIVE,
                               description="Cache file (empty: the object's setting)")
    wait: BoolProperty(name="Wait", default=True,
                       description="From scripts: block until the bake ends")
    __annotations__.update(_param_props())

    def _apply_options(self, obj) -> None:
        """Store the options given on the object; refused ones (ExportError) leave it as it
        was. Values Blender remembers from an earlier call do not count as given."""
        keys = ("quality",) + tuple(k for k in BAKE_KEYS + QUERY_KEYS if k != "quality")
        given = {k: getattr(self, k) for k in keys
                 if self.properties.is_property_set(k, ghost=False)}
        checked_params(obj, {**QUALITY.get(given.get("quality"), {}), **given})
        for k, v in given.items():      # a preset first, then the parameters given with it
            setattr(obj.riray, k, v)
        if self.cache_file:
            obj.riray.cache_file = self.cache_file

    def _start(self, context):
        obj = target_object(context, self.object)
        self._apply_options(obj)
        report = Report()
        job = start_bake(context, obj, report)
        report.emit(self.report, "WARNING")
        return job

    def execute(self, context):
        try:
            job = self._start(context)
        except ExportError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if not self.wait:
            if not bpy.app.timers.is_registered(_timer_poll):
                bpy.app.timers.register(_timer_poll, first_interval=TIMER_S)
            return {"FINISHED"}
        wm = context.window_manager
        wm.progress_begin(0, 1000)
        last = [0.0]

        def show(j):
            wm.progress_update(int(1000 * j.fraction))
            if time.time() - last[0] > 2.0:
                last[0] = time.time()
                print(f"riray: baking {j.object_name}: {100 * j.fraction:.0f}% "
                      f"ETA {format_duration(j.eta)}  {j.message}", flush=True)
        try:
            job.wait(on_progress=show)
        except KeyboardInterrupt:
            job.cancel()
            job.wait()
        finally:
            wm.progress_end()
        self._finish(job)
        return {"FINISHED"} if job.state == "done" else {"CANCELLED"}

    def _finish(self, job) -> None:
        finish_job(job, self.report)


class RIRAY_OT_bake_cancel(bpy.types.Operator):
    """Stop the running bake; the previous cache is kept"""
    bl_idname = "riray.bake_cancel"
    bl_label = "Cancel Bake"

    object: StringProperty(name="Object", default="", description="Empty: every running bake")

    def execute(self, context):
        n = 0
        for name, job in JOBS.items():
            if job.running and (not self.object or name == self.object):
                job.cancel()
                n += 1
        if not n:
            self.report({"INFO"}, "no bake is running")
        return {"FINISHED"}


class RIRAY_OT_bake_clear(bpy.types.Operator):
    """Delete the object's RI-Tree cache file"""
    bl_idname = "riray.bake_clear"
    bl_label = "Clear RI-Tree"

    object: StringProperty(name="Object", default="")

    def execute(self, context):
        try:
            obj = target_object(context, self.object)
        except ExportError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        job = running_job(obj.name)
        if job is not None:
            self.report({"ERROR"}, "a bake is running; cancel it first")
            return {"CANCELLED"}
        path = cache.cache_path(obj)
        if os.path.exists(path):
            os.remove(path)
            self.report({"INFO"}, f"removed {path}")
        obj.riray.baked_cache = ""
        obj.riray.baked_fingerprint = ""
        obj.riray.baked_info = ""
        cache.forget()
        return {"FINISHED"}


class RIRAY_OT_bake_estimate(_JobModal, bpy.types.Operator):
    """Estimate bake time and cache size: a small trial bake in a worker process (Esc cancels);
    the result shows in the panel when it is ready"""
    bl_idname = "riray.bake_estimate"
    bl_label = "Estimate"

    object: StringProperty(name="Object", default="")
    wait: BoolProperty(name="Wait", default=True,
                       description="From scripts: block until the estimate is ready")

    def execute(self, context):
        try:
            job = self._start(context)
        except ExportError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if not self.wait:
            if not bpy.app.timers.is_registered(_timer_poll):
                bpy.app.timers.register(_timer_poll, first_interval=TIMER_S)
            return {"FINISHED"}
        try:
            job.wait()
        except KeyboardInterrupt:
            job.cancel()
            job.wait()
        self._finish(job)
        return {"FINISHED"} if job.state == "done" else {"CANCELLED"}

    def _start(self, context):
        return start_estimate(context, target_object(context, self.object))

    def _finish(self, job) -> None:
        finish_estimate(job, self.report)


class RIRAY_OT_bake_estimate_cancel(bpy.types.Operator):
    """Stop the running estimate"""
    bl_idname = "riray.bake_estimate_cancel"
    bl_label = "Cancel Estimate"

    object: StringProperty(name="Object", default="", description="Empty: every estimate")

    def execute(self, context):
        for name, job in ESTIMATES.items():
            if not self.object or name == self.object:
                job.cancel()
        return {"FINISHED"}


def estimate_key(obj) -> str:
    return json.dumps(bake_params(obj), sort_keys=True)


def start_estimate(context, obj) -> EstimateJob:
    """Export what a bake of ``obj`` would (checked as for a bake) and start its estimate in
    a worker process; an estimate of ``obj`` still running is cancelled first."""
    scene, params, _ = prepare_bake(context, obj, Report())
    old = ESTIMATES.get(obj.name)
    if old is not None:
        old.cancel()
    try:
        job = EstimateJob(obj.name, estimate_key(obj)).start(scene, params, {})
    except (OSError, ValueError) as exc:
        raise ExportError(f"{obj.name}: cannot start the estimate: {exc}") from None
    ESTIMATES[obj.name] = job
    return job


def finish_estimate(job: EstimateJob, report_fn=None) -> None:
    """Main thread, once an estimate ended: show it on the object (for the settings it was
    asked for) or tell why not."""
    obj = bpy.data.objects.get(job.object_name)
    if job.state == "done" and obj is not None:
        est = job.estimate
        obj.riray.estimate_time_s = est["time_s"]
        obj.riray.estimate_bytes = est["bytes"]
        obj.riray.estimate_key = job.key
        level, msg = "INFO", (f"estimate for {job.object_name}: "
                              f"{format_duration(est['time_s'])}, {format_bytes(est['bytes'])}")
    elif job.state == "failed":
        level, msg = "ERROR", f"estimate of {job.object_name} failed: {job.error}"
        if job.traceback:
            print(job.traceback)
    else:
        level, msg = "INFO", f"estimate of {job.object_name} cancelled"
    if report_fn is not None:
        report_fn({level}, msg)
    _redraw()


class RIRAY_OT_export_scene(bpy.types.Operator):
    """Export the object and its environment as a riray JSON scene (images as .npy beside it)"""
    bl_idname = "riray.export_scene"
    bl_label = "Export riray Scene"

    filepath: StringProperty(name="File", subtype="FILE_PATH", default="//riray_scene.json",
                             options=compat.BLEND_RELATIVE)
    object: StringProperty(name="Object", default="")

    def execute(self, context):
        try:
            obj = target_object(context, self.object)
            report = Report()
            scene = export_scene(context.evaluated_depsgraph_get(), obj, report)
        except ExportError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        path = os.path.abspath(bpy.path.abspath(self.filepath))
        write_scene_json(scene, path)
        report.emit(self.report, "WARNING")
        self.report({"INFO"}, f"wrote {path}")
        return {"FINISHED"}

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}


def write_scene_json(scene, path: str) -> None:
    """save_scene, writing in-memory images (textures, world, graph image nodes) as .npy files
    beside the JSON."""
    from ..core.imageio import write_float_image
    from ..core.scene.io import in_memory_images
    stem = os.path.splitext(path)[0]
    folder = os.path.dirname(path)
    os.makedirs(folder, exist_ok=True)
    for i, (pixels, set_path) in enumerate(in_memory_images(scene)):
        name = f"{os.path.basename(stem)}_img{i}.npy"
        write_float_image(os.path.join(folder, name), pixels)
        set_path(name)
    save_scene(scene, path)


class RIRAY_OT_spline_groups_sync(bpy.types.Operator):
    """Make one class-group entry per spline of the object"""
    bl_idname = "riray.spline_groups_sync"
    bl_label = "Sync Spline List"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return context.object is not None and context.object.type == "SURFACE"

    def execute(self, context):
        obj = context.object
        groups = obj.riray.spline_groups
        n = len(obj.data.splines)
        while len(groups) < n:
            groups.add()
        while len(groups) > n:
            groups.remove(len(groups) - 1)
        return {"FINISHED"}


class RIRAY_OT_spline_groups_join(bpy.types.Operator):
    """Put all splines in one class, or give every spline its own class"""
    bl_idname = "riray.spline_groups_set"
    bl_label = "Set Spline Classes"
    bl_options = {"REGISTER", "UNDO"}

    mode: EnumProperty(items=[("JOIN", "Join All", "All splines form one class"),
                              ("SPLIT", "Split All", "Every spline is its own class")])

    @classmethod
    def poll(cls, context):
        return context.object is not None and context.object.type == "SURFACE"

    def execute(self, context):
        bpy.ops.riray.spline_groups_sync()
        for item in context.object.riray.spline_groups:
            item.group = 0 if self.mode == "JOIN" else -1
        return {"FINISHED"}


CLASSES = (RIRAY_OT_bake, RIRAY_OT_bake_cancel, RIRAY_OT_bake_clear, RIRAY_OT_bake_estimate,
           RIRAY_OT_bake_estimate_cancel,
           RIRAY_OT_export_scene, RIRAY_OT_spline_groups_sync, RIRAY_OT_spline_groups_join)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for job in list(JOBS.values()) + list(ESTIMATES.values()):
        job.cancel()
    if bpy.app.timers.is_registered(_timer_poll):
        bpy.app.timers.unregister(_timer_poll)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)

