"""The add-on's bake estimate against real bakes, one row a scene and quality preset
(docs/blender.md, "How good the estimate is"):

    .venv/bin/python sample_scenes/estimate_table.py [--presets draft,fast,default]
        [--scenes bake_test,glass_sphere,vase_mirror,teapot] [--size 100]

Scenes: ``bake_test``, the bake tests' (tests/addon/test_bake.py): a glass NURBS sphere (Glass
BSDF, radius 0.5) and one still camera at (0, -4, 0.5), at the factory render size, exported by
the add-on as the Bake button does; and sample scenes (sample_scenes/NAME.json, their three
cameras) at ``--size`` x ``--size`` pixels. The settings are the add-on's for a new object at
each preset. Per row, one after the other on the same machine: the estimate as the Estimate
button runs it (a worker process), then the bake as the Bake button runs it (a worker
process); the real time is the bake job's, from the worker's start to the cache in place, and
the estimate's own time is its job's. Prints a Markdown table with the load average at each
row. Uses the bpy module (the extension is installed from this checkout into a private
folder, as headless_render.py does).
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import tempfile

import numpy as np

import headless_render as hr

bpy = hr.bpy
PRESETS = ("draft", "fast", "default")
SCENES = ("bake_test", "glass_sphere", "vase_mirror", "teapot")


def parse(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presets", default=",".join(PRESETS),
                    help="comma-separated quality presets (default: all three)")
    ap.add_argument("--scenes", default=",".join(SCENES),
                    help=f"comma-separated scenes (default: {','.join(SCENES)})")
    ap.add_argument("--size", type=int, default=100,
                    help="render size of the sample scenes, pixels a side (default 100)")
    args = ap.parse_args(argv)
    for name, allowed in (("presets", PRESETS), ("scenes", SCENES)):
        got = [p.strip().lower() for p in getattr(args, name).split(",") if p.strip()]
        bad = [p for p in got if p not in allowed]
        if bad or not got:
            ap.error(f"--{name}: expected some of {', '.join(allowed)} (got {got!r})")
        setattr(args, name, got)
    if not 8 <= args.size <= 4096:
        ap.error(f"--size: expected 8 to 4096 (got {args.size})")
    return args


def glass_sphere_scene(folder: str):
    """The bake tests' scene, saved in ``folder``; returns the sphere."""
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "RIRAY"
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=0.5)
    obj = bpy.context.active_object
    compat = importlib.import_module(f"{hr.EXT_MODULE}.riray_addon.compat")
    mat = compat.new_material("Glass")
    nodes = mat.node_tree.nodes
    glass = nodes.new("ShaderNodeBsdfGlass")
    mat.node_tree.links.new(glass.outputs[0], nodes["Material Output"].inputs["Surface"])
    obj.data.materials.append(mat)
    bpy.ops.object.camera_add(location=(0, -4, 0.5), rotation=(math.radians(85), 0, 0))
    scene.camera = bpy.context.active_object
    bpy.context.view_layer.objects.active = obj
    bpy.ops.wm.save_as_mainfile(filepath=os.path.join(folder, "estimate_table.blend"))
    return obj


def job_scene(name: str, obj, preset: str, size: int, mods):
    """(core scene, params) a bake of ``name`` at ``preset`` hands the worker."""
    ops, io, report = mods["operators"], mods["io"], mods["report"]
    obj.riray.quality = preset.upper()
    scene, params, _ = ops.prepare_bake(bpy.context, obj, report.Report())
    if name != "bake_test":
        scene = io.load_scene(os.path.join(hr.HERE, f"{name}.json"))
        params["width"] = params["height"] = size
        params["camera_positions"] = [[float(x) for x in np.asarray(c.matrix_world)[:3, 3]]
                                      for c in scene.cameras]
    return scene, params


def row(name: str, preset: str, scene, params, folder: str, mods) -> str:
    """One table row: the estimate's job, then the bake's job."""
    jobs = mods["jobs"]
    est = jobs.EstimateJob(name, "").start(scene, params, {})
    if est.wait() != "done":
        raise SystemExit(f"the {name} {preset} estimate failed: {est.error}")
    load = os.getloadavg()[0]
    bake = jobs.BakeJob(name, os.path.join(folder, f"{name}_{preset}.rit"))
    if bake.start(scene, params, {}).wait() != "done":
        raise SystemExit(f"the {name} {preset} bake failed: {bake.error}")
    e, t, size = est.estimate, bake.elapsed, bake.bytes
    w, h = params["width"], params["height"]
    return (f"| {name} | {w} x {h} | {preset.capitalize()} | {e['time_s']:.1f} s | {t:.1f} s | "
            f"{100 * (e['time_s'] / t - 1):+.0f} % | {e['bytes'] / 1e6:.3f} MB | "
            f"{size / 1e6:.3f} MB | {100 * (e['bytes'] / size - 1):+.0f} % | {est.elapsed:.1f} s "
            f"| {load:.1f} / {os.getloadavg()[0]:.1f} |")


def main(argv=None) -> None:
    args = parse(argv)
    hr.ensure_addon("")
    mods = {m: importlib.import_module(f"{hr.EXT_MODULE}.riray_addon.{m}")
            for m in ("operators", "jobs", "report")}
    mods["io"] = importlib.import_module(f"{hr.EXT_MODULE}.core.scene.io")
    folder = tempfile.mkdtemp(prefix="riray_estimate_")
    obj = glass_sphere_scene(folder)
    print("| scene | pixels | preset | estimated time | real time | error | estimated size | "
          "real size | error | estimate took | load before / after bake |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|")
    for name in args.scenes:
        for preset in args.presets:
            scene, params = job_scene(name, obj, preset, args.size, mods)
            print(row(name, preset, scene, params, folder, mods), flush=True)


if __name__ == "__main__":
    main()
