"""A camera animation rendered with the "RI-Tree Preview" engine, through the tree and exactly
(the bpy module; benchmark output, not a test).

    python sample_scenes/animation_bench.py [--scene glass_sphere] [--frames 24] [--arc 20]
        [--hold 0] [--material sample|dielectric] [--main-chain] [--no-exact]
        [--quality default] [--size 960x540] [--work DIR] [--out animation_bench.json]

The sample scene is built in Blender (build_blend.py); its close camera circles the object
(an arc of ``--arc`` degrees at the close camera's distance and height, aimed at the object's
centre by a Track To constraint) over the first FRAMES - HOLD frames and stands still at the
arc's end for the last HOLD frames. ``--material dielectric`` gives the object a Glass BSDF
(Fresnel reflection at every crossing) instead of the sample's own material. The object is
baked with the add-on's settings at ``--quality`` for the frame range (every distinct camera
position); with ``--hold`` it is first baked for the moving frames alone (the distinct camera
positions), to compare the two bakes' wall time and cache size. Then the animation is
rendered in one Blender session through the tree and exactly (the cache moved aside: the
engine then traces with a warning); ``--main-chain`` adds an exact pass in which a
dielectric's crossings leave no Fresnel reflections (the light the tree's interpolated rays
carry), ``--no-exact`` renders through the tree only.

Per frame: wall seconds from render_pre to render_post, the engine's stats (export, build of
the parts not kept, the object's CPU, traced share, share outside the baked region, what was
reused) and, from the saved 8-bit PNG frames (view transform Standard, Blender's default
dither), the share of pixels whose value in some channel differs by more than 8/255 and the
PSNR: tree against exact, and each exact frame against the one before it. Prints tables and
writes the rows as JSON.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import platform
import resource
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import headless_render  # noqa: E402  (sets a private BLENDER_USER_RESOURCES before bpy)

import bpy  # noqa: E402
import build_blend  # noqa: E402
import numpy as np  # noqa: E402
from mathutils import Vector  # noqa: E402

# A pixel "differs" when one of its 8-bit channels differs by more than this many levels.
DIFF_LEVELS = 8


def animate_camera(scene, obj, frames: int, arc_deg: float, hold: int = 0) -> None:
    """The scene's close camera circles ``obj``'s centre by ``arc_deg`` over the first
    ``frames - hold`` frames, then stands at the arc's end for ``hold`` frames."""
    cam = bpy.data.objects["close"]
    scene.camera = cam
    centre = obj.matrix_world @ (sum((Vector(c) for c in obj.bound_box), Vector()) / 8.0)
    start = cam.location.copy()
    rel = start - centre
    radius, height = math.hypot(rel.x, rel.y), rel.z
    a0 = math.atan2(rel.y, rel.x)
    target = bpy.data.objects.new("riray_anim_target", None)
    scene.collection.objects.link(target)
    target.location = centre
    track = cam.constraints.new("TRACK_TO")
    track.target, track.track_axis, track.up_axis = target, "TRACK_NEGATIVE_Z", "UP_Y"
    scene.frame_start, scene.frame_end = 1, frames
    moving = frames - hold
    for f in range(1, frames + 1):
        a = a0 + math.radians(arc_deg) * (min(f, moving) - 1) / max(moving - 1, 1)
        cam.location = (centre.x + radius * math.cos(a), centre.y + radius * math.sin(a),
                        centre.z + height)
        cam.keyframe_insert("location", frame=f)
    scene.frame_set(1)


def set_dielectric(obj) -> None:
    """Give ``obj`` a clear Glass BSDF (the sample's IOR 1.5): a dielectric for riray."""
    mat = build_blend.object_material(build_blend.samples.dielectric_material())
    obj.data.materials[0] = mat


def render_animation(engine_mod, folder: Path) -> list[dict]:
    """Render the frame range into ``folder`` (PNG); per frame the engine's stats, the wall
    seconds and the Traced pass (kept in memory: 1 on every object pixel when exact)."""
    rows, t = [], {}
    scene = bpy.context.scene
    folder.mkdir(parents=True, exist_ok=True)
    scene.render.filepath = str(folder / "frame_")
    scene.render.image_settings.file_format = "PNG"

    def pre(*_args):
        t["start"] = time.perf_counter()

    def post(*_args):
        stats = dict(engine_mod.LAST_RENDER["stats"])
        stats["wall_s"] = time.perf_counter() - t["start"]
        stats["traced_mask"] = engine_mod.LAST_RENDER["traced"] > 0.5
        rows.append(stats)

    bpy.app.handlers.render_pre.append(pre)
    bpy.app.handlers.render_post.append(post)
    try:
        if bpy.ops.render.render(animation=True) != {"FINISHED"}:
            raise SystemExit("animation_bench: the render did not finish")
    finally:
        bpy.app.handlers.render_pre.remove(pre)
        bpy.app.handlers.render_post.remove(post)
    for row in rows:
        row["image"] = str(folder / f"frame_{row['frame']:04d}.png")
    return rows


def read_png(path: str) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a saved frame, top row first."""
    from PIL import Image
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def differ(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels where some channel of the 8-bit images differs by more than
    DIFF_LEVELS."""
    return np.abs(a.astype(np.int16) - b.astype(np.int16)).max(axis=2) > DIFF_LEVELS


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two 8-bit images (peak 255; inf where equal)."""
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else 10.0 * math.log10(255.0 ** 2 / mse)


def compare_frames(tree_rows: list[dict], exact_rows: list[dict],
                   main_rows: list[dict] | None = None) -> list[dict]:
    """Per frame: tree against exact (share of differing pixels, how many of them are object
    pixels or traced through the tree, PSNR), exact against the previous exact frame, and with
    ``main_rows`` tree and exact against the exact main chain."""
    out, prev = [], None
    for i, (tr, ex) in enumerate(zip(tree_rows, exact_rows)):
        a, b = read_png(tr["image"]), read_png(ex["image"])
        bad = differ(a, b)
        row = {"frame": tr["frame"], "pixels": int(bad.size),
               "differ_tree_exact": int(bad.sum()),
               "differ_on_object": int((bad & ex["traced_mask"]).sum()),
               "differ_traced_in_tree": int((bad & tr["traced_mask"]).sum()),
               "object_pixels": int(ex["traced_mask"].sum()),
               "psnr_tree_exact": psnr(a, b)}
        if prev is not None:
            row["differ_exact_prev"] = int(differ(b, prev).sum())
            row["psnr_exact_prev"] = psnr(b, prev)
        if main_rows is not None:
            m = read_png(main_rows[i]["image"])
            row["differ_tree_main"] = int(differ(a, m).sum())
            row["psnr_tree_main"] = psnr(a, m)
            row["differ_main_exact"] = int(differ(m, b).sum())
            row["psnr_main_exact"] = psnr(m, b)
        out.append(row)
        prev = b
    return out


def summary(rows: list[dict]) -> dict:
    """Mean per frame over the frames after the first (the first builds what the others
    reuse), and the first frame alone; wall seconds except the object's CPU seconds (summed
    over the render processes)."""
    later = rows[1:] or rows
    mean = lambda k: sum(r[k] for r in later) / len(later)
    return {"first_frame_wall_s": rows[0]["wall_s"], "wall_s": mean("wall_s"),
            "export_s": mean("export_s"), "build_s": mean("build_s"),
            "object_time_s": mean("object_time_s"), "render_time_s": mean("render_time_s"),
            "max_traced_fraction": max(r["traced_fraction"] for r in rows),
            "max_outside_fraction": max(r["outside_fraction"] for r in rows),
            "frames_outside": sum(1 for r in rows if r["outside_fraction"] > 0),
            "frames_reusing_all": sum(1 for r in later if len(r["reused"]) >= 3)}


def cpu_seconds() -> float:
    """CPU seconds of this process and of its finished child processes (the bake worker and
    its own workers): what a bake costs whatever else the machine runs."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(
        resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def bake(obj, addon) -> dict:
    """Bake ``obj`` with its settings for the scene's frame range: wall seconds, CPU seconds
    (the bake's processes together), the cache's size in bytes and the number of camera
    positions baked for (from the cache's header)."""
    cache = importlib.import_module(f"{addon.__name__}.cache")
    backend = importlib.import_module(f"{addon.__name__}.backend")
    t0, c0 = time.perf_counter(), cpu_seconds()
    if bpy.ops.riray.bake(object=obj.name, wait=True) != {"FINISHED"}:
        raise SystemExit("animation_bench: the bake did not finish")
    wall, cpu = time.perf_counter() - t0, cpu_seconds() - c0
    scene, path = bpy.context.scene, cache.cache_path(obj)
    params = (backend.read_header(path) or {}).get("meta", {}).get("params", {})
    return {"wall_s": wall, "cpu_s": cpu, "cache_bytes": os.path.getsize(path),
            "frames": [scene.frame_start, scene.frame_end],
            "camera_positions": len(params.get("camera_positions", []))}


def bake_distinct(obj, addon, moving: int) -> dict:
    """A bake for the moving frames alone (the distinct camera positions), the scene's frame
    range restored afterwards."""
    scene = bpy.context.scene
    end = scene.frame_end
    scene.frame_end = moving
    try:
        return bake(obj, addon)
    finally:
        scene.frame_end = end


def strip_masks(rows: list[dict]) -> list[dict]:
    """The rows without their per-pixel arrays (for the JSON)."""
    return [{k: v for k, v in r.items() if k != "traced_mask"} for r in rows]


def run(args, w: int, h: int) -> dict:
    addon = headless_render.ensure_addon("")
    cache = importlib.import_module(f"{addon.__name__}.cache")
    engine_mod = importlib.import_module(f"{addon.__name__}.engine")
    obj = build_blend.build_scene(args.scene)
    if args.material == "dielectric":
        set_dielectric(obj)
    scene = bpy.context.scene
    animate_camera(scene, obj, args.frames, args.arc, args.hold)
    obj.riray.quality = args.quality.upper()
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = w, h, 100
    r.engine = "RIRAY"
    folder = Path(args.work).resolve()
    folder.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(folder / f"{args.scene}_anim.blend"))
    res = {"scene": args.scene, "material": args.material, "frames": args.frames,
           "hold": args.hold, "arc_deg": args.arc, "quality": args.quality, "size": [w, h],
           "blender": bpy.app.version_string,
           "machine": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
           "load_average_start": os.getloadavg()}
    if args.hold:
        res["bake_distinct"] = bake_distinct(obj, addon, args.frames - args.hold)
    res["bake"] = bake(obj, addon)
    tree_rows = render_animation(engine_mod, folder / "tree")
    res["tree"] = summary(tree_rows)
    path = cache.cache_path(obj)
    exact_rows = main_rows = None
    if args.exact:
        os.replace(path, path + ".aside")
        try:
            exact_rows = render_animation(engine_mod, folder / "exact")
            if args.main_chain:
                main_rows = render_main_chain(addon, engine_mod, folder / "main_chain")
        finally:
            os.replace(path + ".aside", path)
        res["exact"] = summary(exact_rows)
        res["tree_over_exact_wall"] = res["tree"]["wall_s"] / res["exact"]["wall_s"]
        res["compare"] = compare_frames(tree_rows, exact_rows, main_rows)
    res["load_average_end"] = os.getloadavg()
    res["tree_frames"] = strip_masks(tree_rows)
    res["exact_frames"] = strip_masks(exact_rows or [])
    return res


def render_main_chain(addon, engine_mod, folder: Path) -> list[dict]:
    """The exact pass with a dielectric's later crossings leaving no Fresnel reflections (the
    chain keeps all its light): what the tree's interpolated rays carry."""
    package = addon.__name__.rpartition(".")[0]           # the extension: riray_addon, core
    objectfn = importlib.import_module(f"{package}.core.trace.objectfn")
    branches = objectfn.FresnelBranches
    split, trace = branches.split, branches.trace
    branches.split = lambda self, *a, **k: None
    branches.trace = lambda self, tracer, material, shade, n, *a, **k: np.zeros((n, 3))
    try:
        return render_animation(engine_mod, folder)
    finally:
        branches.split, branches.trace = split, trace


def table(res: dict) -> str:
    lines = ["| mode | first frame wall s | later frames: wall s | export wall s | build wall s | "
             "object CPU s | max traced | frames outside the baked region | "
             "frames reusing tracer, tree, environment |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for mode in ("tree", "exact"):
        if mode not in res:
            continue
        s = res[mode]
        lines.append(f"| {mode} | {s['first_frame_wall_s']:.2f} | {s['wall_s']:.2f} | "
                     f"{s['export_s']:.3f} | {s['build_s']:.3f} | {s['object_time_s']:.2f} | "
                     f"{100 * s['max_traced_fraction']:.1f} % | {s['frames_outside']} | "
                     f"{s['frames_reusing_all']} of {res['frames'] - 1} |")
    return "\n".join(lines)


def bake_table(res: dict) -> str:
    lines = ["| bake for | frames | camera positions | wall s | CPU s | cache MB |",
             "|---|---:|---:|---:|---:|---:|"]
    rows = [("the frame range", res["bake"])]
    if "bake_distinct" in res:
        rows.insert(0, ("the distinct positions", res["bake_distinct"]))
    for what, b in rows:
        lines.append(f"| {what} | {b['frames'][0]}-{b['frames'][1]} | "
                     f"{b['camera_positions']} | {b['wall_s']:.1f} | {b['cpu_s']:.1f} | "
                     f"{b['cache_bytes'] / 1e6:.2f} |")
    if "bake_distinct" in res:
        d, b = res["bake_distinct"], res["bake"]
        lines.append(f"\nframe range / distinct positions: wall {b['wall_s'] / d['wall_s']:.2f}x, "
                     f"CPU {b['cpu_s'] / d['cpu_s']:.2f}x, size "
                     f"{b['cache_bytes'] / d['cache_bytes']:.2f}x")
    return "\n".join(lines)


def compare_table(res: dict) -> str:
    main = "differ_tree_main" in res["compare"][0]
    head = ("| frame | object pixels | differ tree/exact | on object | traced in tree | "
            "PSNR tree/exact dB | differ exact/previous | PSNR exact/previous dB |")
    if main:
        head += " differ tree/main chain | differ main chain/exact |"
    lines = [head, "|" + "---:|" * (head.count("|") - 1)]
    pct = lambda n, row: f"{n} ({100 * n / row['pixels']:.3f} %)"
    for c in res["compare"]:
        prev = (f"{pct(c['differ_exact_prev'], c)} | {c['psnr_exact_prev']:.1f}"
                if "differ_exact_prev" in c else "- | -")
        line = (f"| {c['frame']} | {c['object_pixels']} | {pct(c['differ_tree_exact'], c)} | "
                f"{c['differ_on_object']} | {c['differ_traced_in_tree']} | "
                f"{c['psnr_tree_exact']:.1f} | {prev} |")
        if main:
            line += f" {pct(c['differ_tree_main'], c)} | {pct(c['differ_main_exact'], c)} |"
        lines.append(line)
    worst = max(c["differ_tree_exact"] / c["pixels"] for c in res["compare"])
    lines.append(f"\nworst frame: {100 * worst:.3f} % of pixels differ from exact by more than "
                 f"{DIFF_LEVELS}/255")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="glass_sphere")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--arc", type=float, default=20.0,
                    help="degrees the camera travels around the object (default 20)")
    ap.add_argument("--hold", type=int, default=0,
                    help="last frames the camera stands still at the arc's end (default 0); "
                         "also bakes for the moving frames alone, to compare")
    ap.add_argument("--material", default="sample", choices=("sample", "dielectric"),
                    help="the object's material: the sample's, or a clear Glass BSDF")
    ap.add_argument("--main-chain", action="store_true",
                    help="also render exactly without a dielectric's Fresnel reflections")
    ap.add_argument("--exact", action=argparse.BooleanOptionalAction, default=True,
                    help="render exactly too (default: yes)")
    ap.add_argument("--quality", default="default", choices=("draft", "fast", "default"),
                    help="the add-on's bake Quality (default: default)")
    ap.add_argument("--size", default="960x540", help="WIDTHxHEIGHT in pixels")
    ap.add_argument("--work", default="build/animation_bench",
                    help="folder for the .blend, its cache and the frames")
    ap.add_argument("--out", default="animation_bench.json")
    args = ap.parse_args(headless_render.script_args(sys.argv) if argv is None else argv)
    if args.frames - args.hold < 2 or args.hold < 0:
        print("animation_bench: the camera must move over at least 2 frames "
              "(--frames minus --hold, --hold >= 0)", file=sys.stderr)
        return 2
    if args.main_chain and not args.exact:
        print("animation_bench: --main-chain needs the exact pass (drop --no-exact)",
              file=sys.stderr)
        return 2
    size = args.size.lower().split("x")
    if len(size) != 2 or not all(s.isdigit() and int(s) > 0 for s in size):
        print(f"animation_bench: --size {args.size}: expected WIDTHxHEIGHT, e.g. 960x540",
              file=sys.stderr)
        return 2
    res = run(args, int(size[0]), int(size[1]))
    print(f"{res['scene']} ({res['material']} material), {res['frames']} frames "
          f"({res['hold']} held) over {res['arc_deg']:g} deg at {res['size'][0]} x "
          f"{res['size'][1]}, quality {res['quality']}, Blender {res['blender']}; load average "
          f"{res['load_average_start'][0]:.1f} at the start, {res['load_average_end'][0]:.1f} "
          "at the end")
    print(bake_table(res))
    print(table(res))
    if "compare" in res:
        print(f"later frames, tree / exact wall: {res['tree_over_exact_wall']:.2f}")
        print(compare_table(res))
    Path(args.out).write_text(json.dumps(res, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
