"""The add-on's bake estimate against real bakes, one row a quality preset (docs/blender.md,
"How good the estimate is"):

    .venv/bin/python sample_scenes/estimate_table.py [--presets draft,fast,default]

The scene is the bake tests' (tests/addon/test_bake.py): a glass NURBS sphere (Glass BSDF,
radius 0.5) and one still camera at (0, -4, 0.5), at the factory render size. Per preset: the
estimate of what the Estimate button measures, then a blocking bake through the operator; the
real time is the bake job's (the worker's start to the cache in place). Presets run one after
another. Prints a Markdown table. Uses the bpy module (the extension is installed from this
checkout into a private folder, as headless_render.py does).
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import tempfile

import headless_render as hr

bpy = hr.bpy
PRESETS = ("draft", "fast", "default")


def parse(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presets", default=",".join(PRESETS),
                    help="comma-separated quality presets (default: all three)")
    args = ap.parse_args(argv)
    args.presets = [p.strip().lower() for p in args.presets.split(",") if p.strip()]
    bad = [p for p in args.presets if p not in PRESETS]
    if bad or not args.presets:
        ap.error(f"--presets: expected some of {', '.join(PRESETS)} (got {args.presets!r})")
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


def row(obj, preset: str, mods) -> str:
    """One table row: the estimate, then a real bake at ``preset``."""
    ops, jobs, backend, report = mods
    obj.riray.quality = preset.upper()
    scene, params, _ = ops.prepare_bake(bpy.context, obj, report.Report())
    est = backend.estimate_bake(scene, params)
    if bpy.ops.riray.bake(object=obj.name, wait=True) != {"FINISHED"}:
        raise SystemExit(f"the {preset} bake failed")
    job = jobs.JOBS[obj.name]
    t, size = job.elapsed, job.bytes
    return (f"| {preset.capitalize()} | {est['time_s']:.1f} s | {t:.1f} s | "
            f"{100 * (est['time_s'] / t - 1):+.0f} % | {est['bytes'] / 1e6:.3f} MB | "
            f"{size / 1e6:.3f} MB | {100 * (est['bytes'] / size - 1):+.0f} % |")


def main(argv=None) -> None:
    args = parse(argv)
    hr.ensure_addon("")
    mods = [importlib.import_module(f"{hr.EXT_MODULE}.riray_addon.{m}")
            for m in ("operators", "jobs", "backend", "report")]
    obj = glass_sphere_scene(tempfile.mkdtemp(prefix="riray_estimate_"))
    r = bpy.context.scene.render
    print(f"glass NURBS sphere, one camera, {r.resolution_x} x {r.resolution_y}")
    print("| preset | estimated time | real time | error | estimated size | real size | error |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for preset in args.presets:
        print(row(obj, preset, mods), flush=True)


if __name__ == "__main__":
    main()
