"""A camera animation rendered with the "RI-Tree Preview" engine, through the tree and exactly
(the bpy module; benchmark output, not a test).

    python sample_scenes/animation_bench.py [--scene glass_sphere] [--frames 24] [--arc 20]
        [--quality default] [--size 960x540] [--out animation_bench.json]

The sample scene is built in Blender (build_blend.py); its close camera circles the object
over FRAMES frames (an arc of ``--arc`` degrees at the close camera's distance and height,
aimed at the object's centre by a Track To constraint). The object is baked with the add-on's
settings at ``--quality`` for the frame range (every distinct camera position), then the animation is rendered
twice in one Blender session, through the tree and exactly (the cache moved aside: the engine
then traces with a warning). Per frame: wall seconds from render_pre to render_post, the
engine's stats (export, build of the parts not kept, the object's CPU, traced share, what was
reused). Prints a table and writes the rows as JSON.
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

import bpy  # noqa: E402
import build_blend  # noqa: E402
from mathutils import Vector  # noqa: E402

def animate_camera(scene, obj, frames: int, arc_deg: float) -> None:
    """The scene's close camera circles ``obj``'s centre by ``arc_deg`` over ``frames``
    frames."""
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
    for f in range(1, frames + 1):
        a = a0 + math.radians(arc_deg) * (f - 1) / max(frames - 1, 1)
        cam.location = (centre.x + radius * math.cos(a), centre.y + radius * math.sin(a),
                        centre.z + height)
        cam.keyframe_insert("location", frame=f)
    scene.frame_set(1)


def render_animation(engine_mod) -> list[dict]:
    """Render the frame range; per frame the engine's stats and the wall seconds."""
    rows, t = [], {}

    def pre(*_args):
        t["start"] = time.perf_counter()

    def post(*_args):
        stats = dict(engine_mod.LAST_RENDER["stats"])
        stats["wall_s"] = time.perf_counter() - t["start"]
        rows.append(stats)

    bpy.app.handlers.render_pre.append(pre)
    bpy.app.handlers.render_post.append(post)
    try:
        if bpy.ops.render.render(animation=True) != {"FINISHED"}:
            raise SystemExit("animation_bench: the render did not finish")
    finally:
        bpy.app.handlers.render_pre.remove(pre)
        bpy.app.handlers.render_post.remove(post)
    return rows


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
            "frames_reusing_all": sum(1 for r in later if len(r["reused"]) >= 3)}


def run(args, w: int, h: int) -> dict:
    addon = headless_render.ensure_addon("")
    cache = importlib.import_module(f"{addon.__name__}.cache")
    engine_mod = importlib.import_module(f"{addon.__name__}.engine")
    obj = build_blend.build_scene(args.scene)
    scene = bpy.context.scene
    animate_camera(scene, obj, args.frames, args.arc)
    obj.riray.quality = args.quality.upper()
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = w, h, 100
    r.engine = "RIRAY"
    folder = Path(args.work).resolve()
    folder.mkdir(parents=True, exist_ok=True)
    r.filepath = str(folder / "frame_")
    bpy.ops.wm.save_as_mainfile(filepath=str(folder / f"{args.scene}_anim.blend"))
    t0, c0 = time.perf_counter(), time.process_time()
    if bpy.ops.riray.bake(object=obj.name, wait=True) != {"FINISHED"}:
        raise SystemExit("animation_bench: the bake did not finish")
    bake = {"wall_s": time.perf_counter() - t0, "main_cpu_s": time.process_time() - c0,
            "cache_bytes": os.path.getsize(cache.cache_path(obj))}
    tree_rows = render_animation(engine_mod)
    path = cache.cache_path(obj)
    os.replace(path, path + ".aside")
    try:
        exact_rows = render_animation(engine_mod)
    finally:
        os.replace(path + ".aside", path)
    res = {"scene": args.scene, "frames": args.frames, "arc_deg": args.arc,
           "quality": args.quality, "size": [w, h],
           "blender": bpy.app.version_string, "machine": platform.processor() or platform.machine(),
           "cpu_count": os.cpu_count(), "bake": bake,
           "tree": summary(tree_rows), "exact": summary(exact_rows),
           "tree_frames": tree_rows, "exact_frames": exact_rows}
    res["tree_over_exact_wall"] = res["tree"]["wall_s"] / res["exact"]["wall_s"]
    return res


def table(res: dict) -> str:
    lines = ["| mode | first frame wall s | later frames: wall s | export wall s | build wall s | "
             "object CPU s | max traced | frames reusing tracer, tree, environment |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for mode in ("tree", "exact"):
        s = res[mode]
        lines.append(f"| {mode} | {s['first_frame_wall_s']:.2f} | {s['wall_s']:.2f} | "
                     f"{s['export_s']:.3f} | {s['build_s']:.3f} | {s['object_time_s']:.2f} | "
                     f"{100 * s['max_traced_fraction']:.1f} % | {s['frames_reusing_all']} of "
                     f"{res['frames'] - 1} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="glass_sphere")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--arc", type=float, default=20.0,
                    help="degrees the camera travels around the object (default 20)")
    ap.add_argument("--quality", default="default", choices=("draft", "fast", "default"),
                    help="the add-on's bake Quality (default: default)")
    ap.add_argument("--size", default="960x540", help="WIDTHxHEIGHT in pixels")
    ap.add_argument("--work", default="build/animation_bench",
                    help="folder for the .blend, its cache and the frames")
    ap.add_argument("--out", default="animation_bench.json")
    args = ap.parse_args(headless_render.script_args(sys.argv) if argv is None else argv)
    if args.frames < 2:
        print("animation_bench: --frames must be at least 2", file=sys.stderr)
        return 2
    size = args.size.lower().split("x")
    if len(size) != 2 or not all(s.isdigit() and int(s) > 0 for s in size):
        print(f"animation_bench: --size {args.size}: expected WIDTHxHEIGHT, e.g. 960x540",
              file=sys.stderr)
        return 2
    res = run(args, int(size[0]), int(size[1]))
    print(f"{res['scene']}, {res['frames']} frames over {res['arc_deg']:g} deg at "
          f"{res['size'][0]} x {res['size'][1]}, quality {res['quality']}, "
          f"Blender {res['blender']}; bake {res['bake']['wall_s']:.1f} s wall, cache "
          f"{res['bake']['cache_bytes'] / 1e6:.2f} MB")
    print(table(res))
    print(f"later frames, tree / exact wall: {res['tree_over_exact_wall']:.2f}")
    Path(args.out).write_text(json.dumps(res, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
