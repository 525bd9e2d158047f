"""How long pressing Bake or Estimate holds Blender's main thread before the worker starts
(docs/blender.md, "Never freezes the UI"):

    .venv/bin/python sample_scenes/bake_main_thread.py [--operator bake|estimate]
        [--faces 200000] [--wave] [--size 1920x1080] [--top 15]

The scene: a UV sphere of about ``--faces`` faces (radius 20) as the environment, with a Wave
modifier (it changes every frame) when ``--wave`` is given, a NURBS sphere as the object, one
still camera, frames 1-250, Draft quality, rendered at ``--size`` pixels.
``bpy.ops.riray.bake(wait=False)`` (or ``bake_estimate(wait=False)``, what the panel's
buttons run) runs under cProfile; prints its wall time and the slowest calls, then lets the
worker run to its end (an estimate: the seconds it took and its result) or cancels it (a
bake). Uses the bpy module (the extension is installed from this checkout into a private
folder, as headless_render.py does).
"""

from __future__ import annotations

import argparse
import cProfile
import importlib
import math
import os
import pstats
import tempfile
import time

import headless_render as hr

bpy = hr.bpy


def parse(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--faces", type=int, default=200_000,
                    help="faces of the environment's UV sphere (default 200000)")
    ap.add_argument("--wave", action="store_true",
                    help="give the environment a Wave modifier (it changes every frame)")
    ap.add_argument("--operator", choices=("bake", "estimate"), default="bake",
                    help="the button pressed (default bake)")
    ap.add_argument("--size", default="1920x1080", help="render size WxH (default 1920x1080)")
    ap.add_argument("--top", type=int, default=15, help="profile lines printed (default 15)")
    args = ap.parse_args(argv)
    if not 1_000 <= args.faces <= 10_000_000:
        ap.error(f"--faces: expected 1000 to 10000000 (got {args.faces})")
    try:
        args.size = tuple(int(v) for v in args.size.lower().split("x"))
    except ValueError:
        args.size = ()
    if len(args.size) != 2 or not all(4 <= v <= 16384 for v in args.size):
        ap.error(f"--size: expected WxH, each 4 to 16384 (got {args.size!r})")
    return args


def build_scene(faces: int, wave: bool, size: tuple):
    """The environment sphere, the NURBS sphere (returned) and a camera, saved to a temporary
    folder."""
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "RIRAY"
    scene.render.resolution_x, scene.render.resolution_y = size
    rings = 200
    bpy.ops.mesh.primitive_uv_sphere_add(segments=max(3, faces // rings), ring_count=rings,
                                         radius=20)
    if wave:
        bpy.context.active_object.modifiers.new("Wave", "WAVE")
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=0.5)
    obj = bpy.context.active_object
    obj.riray.quality = "DRAFT"
    bpy.ops.object.camera_add(location=(0, -4, 0.5), rotation=(math.radians(85), 0, 0))
    scene.camera = bpy.context.active_object
    bpy.context.view_layer.objects.active = obj
    folder = tempfile.mkdtemp(prefix="riray_main_thread_")
    bpy.ops.wm.save_as_mainfile(filepath=os.path.join(folder, "main_thread.blend"))
    bpy.context.evaluated_depsgraph_get()          # the scene evaluated, as in a UI session
    return obj


def main(argv=None) -> None:
    args = parse(argv)
    hr.ensure_addon("")
    jobs = importlib.import_module(f"{hr.EXT_MODULE}.riray_addon.jobs")
    obj = build_scene(args.faces, args.wave, args.size)
    env = next(o for o in bpy.data.objects if o.type == "MESH")
    print(f"environment: {len(env.data.polygons)} faces{' + Wave' if args.wave else ''}; "
          f"{args.operator}, {args.size[0]} x {args.size[1]}, load average "
          f"{os.getloadavg()[0]:.1f}")
    op = bpy.ops.riray.bake if args.operator == "bake" else bpy.ops.riray.bake_estimate
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    op(object=obj.name, wait=False)
    prof.disable()
    print(f"main thread before the worker runs: {time.perf_counter() - t0:.3f} s")
    pstats.Stats(prof).sort_stats("cumulative").print_stats(args.top)
    if args.operator == "bake":
        job = jobs.JOBS[obj.name]
        job.cancel()
        job.wait(timeout=30)
        return
    ops = importlib.import_module(f"{hr.EXT_MODULE}.riray_addon.operators")
    job = jobs.ESTIMATES[obj.name]
    while ops.poll_jobs():
        time.sleep(0.05)
    print(f"estimate {job.state} after {job.elapsed:.1f} s in the worker: "
          f"{obj.riray.estimate_time_s:.1f} s, {obj.riray.estimate_bytes / 1e6:.3f} MB")


if __name__ == "__main__":
    main()
