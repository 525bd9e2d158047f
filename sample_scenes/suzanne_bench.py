"""A smooth glass mesh as a Blender user makes it, through its RI-Tree and against Cycles (the
bpy module; benchmark output, not a test).

    python sample_scenes/suzanne_bench.py [--levels 2] [--size 300] [--quality default]
        [--max-events 16] [--cycles-spp 256] [--workers 2] [--out bench_out/suzanne]

The glass_sphere sample's room and close camera, emission-only (riray.bench.compare's
Whitted scene, built by build_blend.py), with the sphere replaced by Suzanne at its place and
size, facing the camera: a Subdivision Surface modifier at ``--levels``, shaded smooth, and a
glass Principled BSDF (Transmission 1, Roughness 0, IOR 1.5). The object is baked with the add-on at ``--quality``
and rendered with the RI-Tree Preview engine at one ray per pixel, through the tree and
exactly (the cache moved aside). Paths end after ``--max-events`` reflections and refractions
in both renderers (riray's max events, Cycles' bounces). Cycles renders the Whitted answer
point-sampled (``--cycles-spp`` samples at a 0.01 px filter, denoiser off: Cycles picks
reflection or refraction at random at each crossing of the glass, so 16 samples leave noise
about 30 dB from the converged image) and, at 1 spp with the object as a holdout, the mask of
Suzanne's pixels. PSNR over those pixels (display-range linear RGB). Writes OUT/suzanne.json
and the pictures.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import headless_render  # noqa: E402  (sets a private BLENDER_USER_RESOURCES before bpy)

import blender_bench  # noqa: E402
import bpy  # noqa: E402
import build_blend  # noqa: E402
import factory_bench  # noqa: E402
import numpy as np  # noqa: E402
from mathutils import Vector  # noqa: E402

from riray.bench.compare import whitted_scene  # noqa: E402
from riray.imageio import write_png  # noqa: E402
from riray.render.interpolated import psnr  # noqa: E402
from riray.scene.samples import build  # noqa: E402

SCENE = "glass_sphere"
VIEW = "close"
SUZANNE_SIZE = 1.0            # Suzanne's width over the sphere's diameter


def glass_material():
    """A glass Principled BSDF: Transmission 1, Roughness 0, IOR 1.5."""
    mat = build_blend.compat.new_material("suzanne_glass")
    node = next(n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
    node.inputs["Transmission Weight"].default_value = 1.0
    node.inputs["Roughness"].default_value = 0.0
    node.inputs["IOR"].default_value = 1.5
    return mat


def replace_with_suzanne(sphere, levels: int):
    """Suzanne where ``sphere`` was, as wide as it, facing the scene camera."""
    lo = Vector(np.min([sphere.matrix_world @ Vector(c) for c in sphere.bound_box], axis=0))
    hi = Vector(np.max([sphere.matrix_world @ Vector(c) for c in sphere.bound_box], axis=0))
    centre, width = (lo + hi) / 2, max(hi - lo)
    bpy.data.objects.remove(sphere)
    bpy.ops.mesh.primitive_monkey_add(size=width * SUZANNE_SIZE / 2.73 * 2, location=centre)
    suz = bpy.context.active_object
    suz.name = "Suzanne"
    to_cam = bpy.context.scene.camera.location - centre
    suz.rotation_euler = (0.0, 0.0, math.atan2(to_cam.y, to_cam.x) + math.pi / 2)
    mod = suz.modifiers.new("Subdivision", "SUBSURF")
    mod.levels = mod.render_levels = levels
    bpy.ops.object.shade_smooth()
    suz.data.materials.append(glass_material())
    bpy.context.view_layer.update()
    return suz


def holdout_mask(scene, obj, path: Path) -> np.ndarray:
    """(H, W) bool: the pixels whose centre ray meets ``obj`` first (Cycles, object holdout)."""
    scene.render.engine = "CYCLES"
    scene.cycles.samples, scene.cycles.filter_width = 1, blender_bench.POINT_FILTER_PX
    scene.cycles.use_denoising = False
    scene.render.film_transparent, obj.is_holdout = True, True
    scene.render.image_settings.color_mode = "RGBA"
    try:
        scene.render.image_settings.file_format = "OPEN_EXR"
        scene.render.image_settings.color_depth = "32"
        scene.render.filepath = str(path)
        bpy.ops.render.render(write_still=True)
        img = bpy.data.images.load(str(path))
        w, h = img.size
        px = np.empty(w * h * 4, np.float32)
        img.pixels.foreach_get(px)
        bpy.data.images.remove(img)
    finally:
        scene.render.film_transparent, obj.is_holdout = False, False
    alpha = px.reshape(h, w, 4)[::-1, :, 3]
    return alpha < 0.5


def render_riray(scene, obj, workers: int, path: Path, engine_mod):
    scene.render.engine = "RIRAY"
    scene.riray.target = obj
    scene.riray.samples = 1
    scene.riray.render_processes = workers
    img, wall = blender_bench.render_to_array(scene, path)
    return img, wall, dict(engine_mod.LAST_RENDER.get("stats", {}))


def mesh_stats(obj) -> dict:
    dg = bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(dg)
    me = ev.to_mesh()
    me.calc_loop_triangles()
    edges = {}
    for p in me.polygons:
        for e in p.edge_keys:
            edges[e] = edges.get(e, 0) + 1
    out = {"triangles": len(me.loop_triangles), "vertices": len(me.vertices),
           "boundary_edges": sum(1 for c in edges.values() if c == 1)}
    ev.to_mesh_clear()
    return out


def run(args) -> dict:
    addon = headless_render.ensure_addon(args.zip or factory_bench.fresh_zip())
    cache = importlib.import_module(f"{addon.__name__}.cache")
    engine_mod = importlib.import_module(f"{addon.__name__}.engine")
    core = whitted_scene(build(SCENE))
    sphere = build_blend.build_scene(SCENE, core_scene=core)
    scene = bpy.context.scene
    scene.camera = bpy.data.objects[VIEW]
    suz = replace_with_suzanne(sphere, args.levels)
    r = scene.render
    r.resolution_x = r.resolution_y = args.size
    r.resolution_percentage = 100
    blender_bench.cycles_setup(scene, args.max_events, args.workers)
    c = scene.cycles                # the same path length in both renderers: Whitted's answer
    c.max_bounces = c.glossy_bounces = c.transmission_bounces = args.max_events
    scene.riray.max_events = args.max_events
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(out / "suzanne.blend"))
    mask = holdout_mask(scene, suz, out / "mask.exr")
    scene.render.engine = "CYCLES"
    scene.cycles.samples = args.cycles_spp
    scene.cycles.filter_width = blender_bench.POINT_FILTER_PX
    scene.cycles.use_denoising = False      # the denoiser blurs what the glass shows
    cyc, cyc_s = blender_bench.render_to_array(scene, out / "cycles.exr")
    suz.riray.quality = args.quality.upper()
    t0 = time.perf_counter()
    if bpy.ops.riray.bake(object=suz.name, wait=True) != {"FINISHED"}:
        raise SystemExit("suzanne_bench: the bake did not finish")
    bake = {"wall_s": time.perf_counter() - t0,
            "cache_bytes": os.path.getsize(cache.cache_path(suz))}
    tree, tree_s, tree_stats = render_riray(scene, suz, args.workers, out / "tree.exr",
                                            engine_mod)
    traced_px = np.asarray(engine_mod.LAST_RENDER["traced"]) > 0
    path = cache.cache_path(suz)
    os.replace(path, path + ".aside")
    try:
        exact, exact_s, exact_stats = render_riray(scene, suz, args.workers,
                                                   out / "exact.exr", engine_mod)
    finally:
        os.replace(path + ".aside", path)
    for name, img in (("cycles", cyc), ("tree", tree), ("exact", exact)):
        write_png(out / f"{name}.png", img)
    write_png(out / "traced.png", np.repeat(traced_px[..., None], 3, axis=2).astype(float))
    scalars = lambda d: {k: v for k, v in d.items() if isinstance(v, (int, float, str, bool))}
    return {"levels": args.levels, "quality": args.quality,
            "max_events": args.max_events, "cycles_spp": args.cycles_spp,
            "size": args.size, "mesh": mesh_stats(suz), "object_pixels_cycles": int(mask.sum()),
            "psnr_tree_db": psnr(tree[mask], cyc[mask]),
            "psnr_exact_db": psnr(exact[mask], cyc[mask]),
            "psnr_tree_vs_exact_db": psnr(tree[mask], exact[mask]),
            "traced_fraction": tree_stats.get("traced_fraction"),
            "solved_fraction": tree_stats.get("solved_fraction"),
            "tree_render_s": tree_s, "exact_render_s": exact_s, "cycles_s": cyc_s,
            "bake": bake, "tree_stats": scalars(tree_stats), "exact_stats": scalars(exact_stats),
            "blender": bpy.app.version_string,
            "machine": platform.processor() or platform.machine(), "cpu_count": os.cpu_count()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--levels", type=int, default=2, choices=range(0, 5), metavar="N",
                    help="Subdivision Surface levels (0..4)")
    ap.add_argument("--size", type=int, default=300, choices=range(16, 2049), metavar="PX")
    ap.add_argument("--quality", default="default", choices=("draft", "fast", "default"))
    ap.add_argument("--max-events", type=int, default=16, choices=range(1, 65), metavar="N",
                    help="reflections and refractions per path (riray's max events, Cycles' "
                         "bounces)")
    ap.add_argument("--cycles-spp", type=int, default=256, choices=range(1, 4097), metavar="N",
                    help="Cycles' samples per pixel, all at the pixel centre (the reference)")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                    choices=range(1, 257), metavar="N")
    ap.add_argument("--out", default="bench_out/suzanne")
    ap.add_argument("--zip", default="", help="extension zip (default: built from this checkout)")
    args = ap.parse_args(headless_render.script_args(sys.argv) if argv is None else argv)
    res = run(args)
    (Path(args.out) / "suzanne.json").write_text(json.dumps(res, indent=1) + "\n")
    print(f"Suzanne (subdivision {args.levels}, {res['mesh']['triangles']} "
          f"triangles, {res['mesh']['boundary_edges']} boundary edges), {args.size} px, "
          f"{args.quality} bake {res['bake']['wall_s']:.0f} s: traced "
          f"{100 * res['traced_fraction']:.1f} %, solved {100 * res['solved_fraction']:.1f} %; "
          f"PSNR over its {res['object_pixels_cycles']} pixels vs Cycles: tree "
          f"{res['psnr_tree_db']:.2f} dB, exact {res['psnr_exact_db']:.2f} dB "
          f"(tree vs exact {res['psnr_tree_vs_exact_db']:.2f} dB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
