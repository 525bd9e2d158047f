"""Two specular objects as a Blender user makes them, each through its own RI-Tree and against
Cycles (the bpy module; benchmark output, not a test).

    python sample_scenes/two_objects_bench.py [--size 300] [--quality default]
        [--max-events 8] [--max-error 2 [--max-error 0.25 ...]] [--cycles-spp 16]
        [--tessellation 64] [--workers 2] [--out bench_out/two_objects]

The glass_sphere sample's room and far camera (at a 60 mm lens, aimed between the two objects),
emission-only (riray.bench.compare's Whitted scene, built by build_blend.py): its glass NURBS
sphere (Refraction BSDF, IOR 1.5) and beside
it, standing on the table, a mirror NURBS torus added as a user adds one (Surface > NURBS
Torus, a Glossy BSDF at Roughness 0). Both are specular objects by their materials; each is
baked with the add-on at ``--quality`` (the sphere first, then the torus: the second bake must
not change how the first renders), then the frame is rendered with the RI-Tree Preview engine
at one ray per pixel through both trees (once per ``--max-error``, the objects' render-time
*Max error* rule: the add-on's default 2 degrees first) and exactly (the caches moved aside). A path ends after
``--max-events`` reflections and refractions in one object (riray's max events), and a camera
ray meets at most MAX_OBJECT_CHAIN objects (core/render/frame.py); Cycles' bounces cover such
a chain. Cycles renders the Whitted answer point-sampled (``--cycles-spp`` samples at a
0.01 px filter, denoiser off; refraction and sharp reflection are deterministic here, so few
samples converge) from the objects' tessellation at ``--tessellation`` segments per knot span
(at blender_bench's 16 the facets' normals leave the exactly traced torus 23.7 dB from
Cycles, 31.2 dB at 64) and, at 1 spp with one object as a holdout, the mask of that object's
pixels. PSNR per object over its pixels (display-range linear RGB). Writes
OUT/two_objects.json and the pictures.
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
import suzanne_bench  # noqa: E402

from riray.bench.compare import whitted_scene  # noqa: E402
from riray.imageio import write_png  # noqa: E402
from riray.render.frame import MAX_OBJECT_CHAIN  # noqa: E402
from riray.render.interpolated import psnr  # noqa: E402
from riray.scene.samples import build  # noqa: E402

SCENE = "glass_sphere"
VIEW = "far"
TORUS_SCALE = 0.13            # Blender's NURBS torus (major radius 1 m) scaled: 13 cm
TORUS_AT = (0.34, 0.06, 0.92)  # beside the sphere (centre z 0.90), standing on the table
TORUS_TILT_DEG = (72.0, 0.0, 7.0)   # its ring facing the camera
TORUS_COLOR = (0.9, 0.9, 0.9, 1.0)
LENS_MM = 60.0                # the far camera zoomed in on the pair ...
LOOK_AT = (0.20, 0.05, 0.90)  # ... aimed between them


def mirror_material():
    """A sharp mirror: a Glossy BSDF at Roughness 0."""
    mat = build_blend.compat.new_material("torus_mirror")
    nt = mat.node_tree
    for node in [n for n in nt.nodes if n.type != "OUTPUT_MATERIAL"]:
        nt.nodes.remove(node)
    glossy = nt.nodes.new("ShaderNodeBsdfGlossy")
    glossy.inputs["Color"].default_value = TORUS_COLOR
    glossy.inputs["Roughness"].default_value = 0.0
    out = next(n for n in nt.nodes if n.type == "OUTPUT_MATERIAL")
    nt.links.new(glossy.outputs[0], out.inputs["Surface"])
    return mat


def add_torus():
    """The mirror NURBS torus beside the sphere."""
    bpy.ops.surface.primitive_nurbs_surface_torus_add(location=TORUS_AT)
    torus = bpy.context.active_object
    torus.name = "torus"
    # set on the object: the operator's rotation turns the control points as well
    torus.rotation_euler = tuple(math.radians(a) for a in TORUS_TILT_DEG)
    torus.scale = (TORUS_SCALE,) * 3
    torus.data.materials.append(mirror_material())
    bpy.context.view_layer.update()
    return torus


def bake(obj, cache) -> dict:
    t0 = time.perf_counter()
    if bpy.ops.riray.bake(object=obj.name, wait=True) != {"FINISHED"}:
        raise SystemExit(f"two_objects_bench: the bake of {obj.name} did not finish")
    return {"wall_s": time.perf_counter() - t0,
            "cache_bytes": os.path.getsize(cache.cache_path(obj))}


def render(scene, workers: int, path: Path, engine_mod):
    scene.render.engine = "RIRAY"
    scene.riray.samples = 1
    scene.riray.render_processes = workers
    img, wall = blender_bench.render_to_array(scene, path)
    return img, wall, dict(engine_mod.LAST_RENDER.get("stats", {}))


def render_exact(scene, objs, workers: int, path: Path, engine_mod, cache):
    """The frame with every object traced exactly: the caches moved aside meanwhile."""
    paths = [cache.cache_path(o) for o in objs]
    for p in paths:
        os.replace(p, p + ".aside")
    try:
        return render(scene, workers, path, engine_mod)
    finally:
        for p in paths:
            os.replace(p + ".aside", p)


def run(args) -> dict:
    addon = headless_render.ensure_addon(args.zip or factory_bench.fresh_zip())
    cache = importlib.import_module(f"{addon.__name__}.cache")
    engine_mod = importlib.import_module(f"{addon.__name__}.engine")
    sphere = build_blend.build_scene(SCENE, core_scene=whitted_scene(build(SCENE)))
    sphere.name = "sphere"
    scene = bpy.context.scene
    scene.camera = bpy.data.objects[VIEW]
    scene.camera.data.lens = LENS_MM
    factory_bench._look(scene.camera, LOOK_AT)
    torus = add_torus()
    objs = (sphere, torus)
    for obj in objs:
        blender_bench.prepare_object(obj, obj is sphere, args.tessellation)
    r = scene.render
    r.resolution_x = r.resolution_y = args.size
    r.resolution_percentage = 100
    blender_bench.cycles_setup(scene, args.max_events, args.workers)
    c = scene.cycles      # Whitted's answer: a chain of objects, each ending after max events
    c.max_bounces = c.glossy_bounces = c.transmission_bounces = \
        args.max_events * MAX_OBJECT_CHAIN
    scene.riray.max_events = args.max_events
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("two_objects.*.rit"):     # an earlier run's trees: each bake is timed
        old.unlink()
    bpy.ops.wm.save_as_mainfile(filepath=str(out / "two_objects.blend"))
    masks = {o.name: suzanne_bench.holdout_mask(scene, o, out / f"mask_{o.name}.exr")
             for o in objs}
    scene.render.engine = "CYCLES"
    scene.cycles.samples = args.cycles_spp
    scene.cycles.filter_width = blender_bench.POINT_FILTER_PX
    scene.cycles.use_denoising = False
    cyc, cyc_s = blender_bench.render_to_array(scene, out / "cycles.exr")
    for obj in objs:
        obj.riray.quality = args.quality.upper()
    bakes = {sphere.name: bake(sphere, cache)}
    first, _, first_stats = render(scene, args.workers, out / "after_first.exr", engine_mod)
    bakes[torus.name] = bake(torus, cache)
    trees = {}
    for max_error in args.max_error:
        for obj in objs:
            obj.riray.use_max_error, obj.riray.max_error_deg = True, max_error
        trees[max_error] = render(scene, args.workers, out / f"tree_{max_error:g}.exr",
                                  engine_mod)
    tree, tree_s, tree_stats = trees[args.max_error[0]]
    exact, exact_s, exact_stats = render_exact(scene, objs, args.workers, out / "exact.exr",
                                               engine_mod, cache)
    for name, img in (("cycles", cyc), ("tree", tree), ("exact", exact)):
        write_png(out / f"{name}.png", img)
    per = {}
    for obj in objs:
        m = masks[obj.name]
        per[obj.name] = {
            "pixels_cycles": int(m.sum()),
            "psnr_tree_db": psnr(tree[m], cyc[m]), "psnr_exact_db": psnr(exact[m], cyc[m]),
            "psnr_tree_vs_exact_db": psnr(tree[m], exact[m]),
            "traced_fraction": tree_stats["objects"][obj.name]["traced_fraction"],
            "object_pixels": tree_stats["objects"][obj.name]["object_pixels"],
            "bake": bakes[obj.name],
            "by_max_error": [{"max_error_deg": me, "psnr_tree_db": psnr(img[m], cyc[m]),
                              "traced_fraction": st["objects"][obj.name]["traced_fraction"],
                              "solved_fraction_all_objects": st["solved_fraction"]}
                             for me, (img, _, st) in trees.items()]}
    # the sphere's pixels after its own bake and after the torus's: they change only where the
    # sphere shows the torus (now answered through the torus's tree)
    sm = masks[sphere.name]
    per[sphere.name]["psnr_before_vs_after_torus_bake_db"] = psnr(tree[sm], first[sm])
    scalars = lambda d: {k: v for k, v in d.items() if isinstance(v, (int, float, str, bool))}
    return {"quality": args.quality, "max_events": args.max_events,
            "tessellation": args.tessellation,
            "cycles_bounces": args.max_events * MAX_OBJECT_CHAIN,
            "cycles_spp": args.cycles_spp, "size": args.size, "objects": per,
            "tree_render_s": tree_s, "exact_render_s": exact_s, "cycles_s": cyc_s,
            "tree_stats": scalars(tree_stats), "exact_stats": scalars(exact_stats),
            "after_first_bake": {n: o["mode"] for n, o in first_stats["objects"].items()},
            "blender": bpy.app.version_string,
            "machine": platform.processor() or platform.machine(), "cpu_count": os.cpu_count()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=300, choices=range(16, 2049), metavar="PX")
    ap.add_argument("--quality", default="default", choices=("draft", "fast", "default"))
    ap.add_argument("--max-events", type=int, default=8, choices=range(1, 65), metavar="N",
                    help="reflections and refractions per path in one object (riray's max "
                         "events)")
    ap.add_argument("--max-error", type=float, action="append", default=None, metavar="DEG",
                    help="the objects' render-time Max error for a render through the trees "
                         "(repeat for more renders; default 2, the add-on's)")
    ap.add_argument("--tessellation", type=int, default=64, choices=range(4, 257),
                    metavar="N", help="Cycles' segments per knot span of the NURBS objects")
    ap.add_argument("--cycles-spp", type=int, default=16, choices=range(1, 4097), metavar="N",
                    help="Cycles' samples per pixel, all at the pixel centre (the reference)")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                    choices=range(1, 257), metavar="N")
    ap.add_argument("--out", default="bench_out/two_objects")
    ap.add_argument("--zip", default="", help="extension zip (default: built from this checkout)")
    args = ap.parse_args(headless_render.script_args(sys.argv) if argv is None else argv)
    args.max_error = args.max_error or [2.0]
    res = run(args)
    (Path(args.out) / "two_objects.json").write_text(json.dumps(res, indent=1) + "\n")
    for name, o in res["objects"].items():
        print(f"{name}: {o['pixels_cycles']} pixels, {args.quality} bake "
              f"{o['bake']['wall_s']:.0f} s ({o['bake']['cache_bytes'] / 2 ** 20:.2f} MiB), "
              f"traced {100 * o['traced_fraction']:.1f} %; PSNR vs Cycles: tree "
              f"{o['psnr_tree_db']:.2f} dB, exact {o['psnr_exact_db']:.2f} dB (tree vs exact "
              f"{o['psnr_tree_vs_exact_db']:.2f} dB)")
        for row in o["by_max_error"][1:]:
            print(f"  at Max error {row['max_error_deg']:g} deg: tree {row['psnr_tree_db']:.2f} "
                  f"dB, traced {100 * row['traced_fraction']:.1f} % (solved, all objects: "
                  f"{100 * row['solved_fraction_all_objects']:.1f} %)")
    print(f"after the sphere's bake alone: {res['after_first_bake']}; its pixels after the "
          "torus's bake against before: "
          f"{res['objects']['sphere']['psnr_before_vs_after_torus_bake_db']:.2f} dB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
