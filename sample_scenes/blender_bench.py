"""riray next to Blender's own renderers on the sample scenes (docs/benchmarks.md, "Blender").

    .venv/bin/python sample_scenes/blender_bench.py [NAME ...] [--out bench_out/blender]
        [--view close] [--size 300 | --size 1920x1080] [--quality default]
        [--spp 1 4 16 64 256] [--reference-spp 1024] [--workers 2] [--no-eevee]

Needs the bpy wheel (``make venv-bpy``) and the installed ``riray``. For each sample scene the
*fair* variant (riray.bench.compare.whitted_scene: emission-only environment, no lights, a pure
sharp mirror / refractor) is built as a Blender scene by sample_scenes/build_blend.py - the
same builder that makes the sample .blend files the add-on renders - and rendered at the same
resolution (``--size``: N for N x N pixels, or WIDTHxHEIGHT) with
- Cycles (CPU, ``--workers`` threads, fixed seed, no adaptive sampling, no light-path limits
  below riray's max_events) at each ``--spp``, without and with OpenImageDenoise;
- Cycles at ``--reference-spp`` with the default 1.5 px filter: the converged reference;
- Cycles at 16 spp with a 0.01 px filter: point sampling, the check that Cycles and riray
  compute the same Whitted answer (riray shoots one ray through each pixel centre);
- EEVEE unless ``--no-eevee`` (what this machine offers: without a GPU Blender falls back to
  software OpenGL, so its time here says nothing about EEVEE on a graphics card);
and the same core Scene is rendered by riray in this process: exact, and through an RI-Tree
baked for the view at the ``--quality`` preset (core's QUALITY_PRESETS, the presets of
``riray bake --quality`` and the add-on's Quality; default: default, viewpoint depth 5 and
direction depth 6; fast: depths 4 and 5) with the default query options (the 2 degree
baked-error tolerance). Every image is compared with the reference (PSNR of display-range
linear RGB, max per-pixel difference); times are wall seconds per frame (Cycles: the whole
render call, scene sync included; riray: the render, with the once-per-scene
acceleration-structure build and the bake listed apart). The tree frame's stage CPU seconds
(summed over the workers) show where it goes. The tree frame is rendered once more as a user
runs it, ``riray render --tree`` in a fresh process without Blender and Cycles: its wall
seconds and peak resident memory (RSS, MiB, the largest of the process and its workers).

Writes OUT/blender.json, OUT/blender.csv, OUT/blender.md (the side-by-side table, the tree
frame's stages and the query's steps within its object stage) and the images
(OUT/<scene>_*.png).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import build_blend  # noqa: E402  (imports bpy and riray)
import bpy  # noqa: E402
import numpy as np  # noqa: E402

from riray.bench.compare import whitted_scene  # noqa: E402
from riray.bench.exact_bench import machine  # noqa: E402
from riray.bench.ritree_measure import bake_view  # noqa: E402
from riray.bench.ritree_output import json_safe  # noqa: E402
from riray.render.exact import render_exact  # noqa: E402
from riray.imageio import write_png  # noqa: E402
from riray.render.interpolated import psnr, render_tree  # noqa: E402
from riray.ritree.params import QUALITY_PRESETS, BakeParams  # noqa: E402
from riray.scene.camera import Shot, check_image_size  # noqa: E402
from riray.scene.io import save_scene  # noqa: E402
from riray.trace.scene_tracer import SceneTracer  # noqa: E402
from riray.ritree.query import QueryOptions  # noqa: E402
from riray.scene.samples import SAMPLES, build  # noqa: E402

SEED = 1
POINT_FILTER_PX = 0.01        # Cycles' smallest pixel filter: all samples at the pixel centre
POINT_SPP = 16
TESSELLATION = 16             # Blender's surface resolution per knot span for Cycles


def cycles_setup(scene, max_events: int, threads: int):
    s = scene
    s.render.engine = "CYCLES"
    c = s.cycles
    c.device = "CPU"
    c.use_adaptive_sampling = False
    c.seed = SEED
    c.sample_clamp_direct = c.sample_clamp_indirect = 0.0
    # light paths: enough specular bounces for riray's chains; nothing diffuse to follow
    c.max_bounces = c.glossy_bounces = c.transmission_bounces = max(2 * max_events, 16)
    c.diffuse_bounces = c.volume_bounces = 0
    c.transparent_max_bounces = 8
    c.caustics_reflective = c.caustics_refractive = True
    c.blur_glossy = 0.0
    s.render.threads_mode = "FIXED"
    s.render.threads = threads
    s.render.use_persistent_data = False


def prepare_object(obj, refractive: bool, resolution: int) -> dict:
    """Cycles renders the NURBS object from its tessellation: make that fine and smooth-shaded.
    (build_blend already turned a refractive object's normals outwards, as Cycles needs.)"""
    for sp in obj.data.splines:
        sp.use_smooth = True
    obj.data.resolution_u = obj.data.resolution_v = resolution
    obj.data.render_resolution_u = obj.data.render_resolution_v = resolution
    info = {"tessellation_per_segment": resolution}
    if refractive:
        info["volume_m3"] = build_blend.signed_volume(obj)
        if info["volume_m3"] <= 0:
            raise RuntimeError(f"{obj.name}: normals still point inwards")
    return info


def render_to_array(scene, path: Path) -> tuple[np.ndarray, float]:
    """Render the scene's camera; (linear RGB float64 image, top row first; wall seconds)."""
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = str(path)
    t0 = time.perf_counter()
    if bpy.ops.render.render(write_still=True) != {"FINISHED"}:
        raise SystemExit(f"{path.name}: the render did not finish")
    wall = time.perf_counter() - t0
    img = bpy.data.images.load(str(path))
    w, h = img.size
    px = np.empty(w * h * img.channels, np.float32)
    img.pixels.foreach_get(px)
    bpy.data.images.remove(img)
    rgb = px.reshape(h, w, -1)[::-1, :, :3].astype(np.float64)
    return rgb, wall


def compare(img, ref) -> dict:
    d = np.abs(np.clip(img, 0, 1) - np.clip(ref, 0, 1))
    return {"psnr_db": psnr(img, ref), "max_pixel_diff": float(d.max()),
            "mean_abs_diff": float(d.mean())}


def bench_scene(name, args, out: Path, tmp: Path, log) -> list:
    """Every renderer's frame of sample ``name``'s fair variant at ``args.size``: the rows."""
    view, (w, h) = args.view, args.size
    core = whitted_scene(build(name))
    core.render.width, core.render.height = w, h
    obj = build_blend.build_scene(name, core_scene=core)
    fix = prepare_object(obj, core.object.material.kind != "mirror", TESSELLATION)
    log(f"{name}: Blender object {fix}")
    scene = bpy.context.scene
    scene.camera = bpy.data.objects[view]
    scene.render.resolution_x, scene.render.resolution_y = w, h
    cycles_setup(scene, core.render.max_events, args.workers)
    rows, images = [], {}

    def cyc(label, spp, denoise=False, filt=1.5):
        scene.render.engine = "CYCLES"
        scene.cycles.samples = spp
        scene.cycles.use_denoising = denoise
        if denoise:
            scene.cycles.denoiser = "OPENIMAGEDENOISE"
        scene.cycles.filter_width = filt
        img, wall = render_to_array(scene, tmp / f"{name}_{label}.exr")
        images[label] = img
        rows.append({"renderer": "cycles", "label": label, "spp": spp, "denoise": denoise,
                     "filter_px": filt, "frame_s": wall})
        log(f"{name}/{view} {label}: {wall:.2f} s")

    ref_label = f"cycles_ref_{args.reference_spp}"
    cyc(ref_label, args.reference_spp)
    cyc(f"cycles_point_{POINT_SPP}", POINT_SPP, filt=POINT_FILTER_PX)
    for spp in args.spp:
        cyc(f"cycles_{spp}", spp)
        cyc(f"cycles_{spp}_denoised", spp, denoise=True)
    if args.eevee:
        rows += eevee_frame(scene, name, view, tmp, images, log)
    rows += riray_frames(core, view, (w, h), args, tmp, images, log)
    ref, point = images[ref_label], images[f"cycles_point_{POINT_SPP}"]
    for r in rows:
        r.update(scene=name, view=view, size=f"{w}x{h}")
        if r["label"] in images:
            r.update(compare(images[r["label"]], ref))
            r["psnr_vs_point_db"] = compare(images[r["label"]], point)["psnr_db"]
    for label, img in images.items():
        write_png(out / f"{name}_{view}_{label}.png", img)
    return rows


def eevee_frame(scene, name, view, tmp: Path, images, log) -> list:
    """EEVEE's frame (screen-space / ray-traced refraction approximations, whatever this build
    offers): one row, or one naming its error."""
    for eng in ("BLENDER_EEVEE", "BLENDER_EEVEE_NEXT"):
        try:
            scene.render.engine = eng
        except TypeError:
            continue
        ee = scene.eevee
        for attr in ("use_raytracing", "use_ssr", "use_ssr_refraction"):
            if hasattr(ee, attr):
                setattr(ee, attr, True)
        for mat in bpy.data.materials:     # let EEVEE trace/refract through the object
            for attr in ("use_raytrace_refraction", "use_screen_refraction"):
                if hasattr(mat, attr):
                    setattr(mat, attr, True)
        try:
            img, wall = render_to_array(scene, tmp / f"{name}_eevee.exr")
        except RuntimeError as e:
            log(f"{name}/{view} eevee failed: {e}")
            return [{"renderer": "eevee", "label": "eevee", "error": str(e)}]
        images["eevee"] = img
        log(f"{name}/{view} eevee: {wall:.2f} s")
        return [{"renderer": "eevee", "label": "eevee", "engine": eng, "frame_s": wall}]
    return []


def riray_frames(core, view, size, args, tmp: Path, images, log) -> list:
    """riray on the very same core scene: the exact frame, then the frame through a tree baked
    for the view at the ``args.quality`` preset, with the CPU seconds of its stages and of the
    query's steps within the object stage, and its frame again by ``riray render`` in a fresh
    process (wall s, peak RSS MiB)."""
    w, h = size
    shot = Shot(camera=view, width=w, height=h)
    t0 = time.perf_counter()
    st = SceneTracer(core)
    build_s = time.perf_counter() - t0
    ex = render_exact(st, shot, workers=args.workers)
    images["riray_exact"] = ex.image
    exact = {"renderer": "riray", "label": "riray_exact",
             "frame_s": ex.stats["summary"]["wall_s"], "build_s": build_s}
    tree, brec = bake_view(st, core, core.camera(view), w, args.params, args.workers, tmp,
                           height=h)
    it = render_tree(st, tree, shot, options=QueryOptions(), reference=False,
                     workers=args.workers)
    images["riray_interpolated"] = it.image
    s = it.stats["summary"]
    stages = {k: v for k, v in it.stats["interp_counts"].items()
              if k.startswith(("stage_", "query_")) and k.endswith("_cpu_s")}
    cli = cli_tree_frame(core, view, size, brec["tree_path"], args.workers, tmp)
    interp = {"renderer": "riray", "label": "riray_interpolated", "quality": args.quality,
              "frame_s": s["wall_s"], "frame_cpu_s": s["interp_total_cpu_s"],
              "query_own_cpu_s": s["query_own_cpu_s"], "build_s": build_s,
              "bake_s": brec["bake_s"], "cache_bytes": brec["cache_bytes"],
              "traced_fraction": s["traced_fraction_of_object"], **stages,
              "cli_frame_s": cli["wall_s"], "peak_rss_mib": cli["peak_rss_mib"]}
    log(f"{core.name}/{view} riray: exact {exact['frame_s']:.2f} s, interpolated "
        f"{interp['frame_s']:.2f} s (bake {brec['bake_s']:.1f} s; riray render "
        f"{cli['wall_s']:.2f} s, peak RSS {cli['peak_rss_mib']:.0f} MiB)")
    return [exact, interp]


def cli_tree_frame(core, view, size, tree_path, workers, tmp: Path) -> dict:
    """The tree frame as a user renders it, ``riray render --tree`` (no reference) in a fresh
    process: its summary (wall_s; peak_rss_mib: the largest of the process and its workers)."""
    scene_path = tmp / f"{core.name}.json"
    save_scene(core, scene_path)
    w, h = size
    cmd = [sys.executable, "-m", "riray.cli", "render", str(scene_path), "--tree",
           str(tree_path), "--camera", view, "--width", str(w), "--height", str(h),
           "--workers", str(workers), "--no-reference", "--quiet",
           "--out", str(tmp / f"{core.name}_{view}_cli")]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"riray render failed ({res.returncode}): {res.stderr.strip()}")
    return json.loads(res.stdout)


COLS = ("scene", "view", "size", "renderer", "label", "quality", "spp", "denoise", "filter_px",
        "frame_s", "psnr_db", "psnr_vs_point_db", "max_pixel_diff", "mean_abs_diff", "build_s",
        "bake_s", "cache_bytes", "traced_fraction", "frame_cpu_s", "query_own_cpu_s",
        "cli_frame_s", "peak_rss_mib", "engine", "error")


def _cell(v, fmt):
    if v is None:
        return "-"
    return "inf" if isinstance(v, float) and not np.isfinite(v) else fmt.format(v)


def setting(r) -> str:
    """A row's renderer and setting in words."""
    if r["renderer"] == "cycles":
        return ("Cycles " + f"{r['spp']} spp" + (", denoised" if r["denoise"] else "")
                + (", 0.01 px filter (point sampled)" if r["filter_px"] < 1 else "")
                + (" (the reference)" if "ref" in r["label"] else ""))
    if r["renderer"] == "eevee":
        return "EEVEE (software OpenGL here)"
    if r["label"] == "riray_exact":
        return "riray exact"
    return f"riray through the tree ({r['quality']} bake, 2 deg baked-error tolerance)"


def side_by_side(rows) -> str:
    """Settings down, scenes across; cells: wall s / frame · PSNR dB against the reference."""
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    cells = {}
    for r in rows:
        if r.get("frame_s") is None:
            continue
        db = "ref" if "ref" in r["label"] else _cell(r.get("psnr_db"), "{:.1f}")
        cells.setdefault(setting(r), {})[r["scene"]] = f"{r['frame_s']:.2f} s · {db}"
    lines = ["| renderer | " + " | ".join(scenes) + " |", "|---|" + "---:|" * len(scenes)]
    for name, by in cells.items():
        lines.append(f"| {name} | " + " | ".join(by.get(s, "-") for s in scenes) + " |")
    tree = [r for r in rows if r["label"] == "riray_interpolated"]
    exact = [r for r in rows if r["label"] == "riray_exact"]
    lines += ["", "riray exact against point-sampled Cycles (same answer check), PSNR dB: "
              + ", ".join(f"{r['scene']} {_cell(r.get('psnr_vs_point_db'), '{:.1f}')}"
                          for r in exact),
              "riray bake (s) / traced fraction of the tree frame: "
              + ", ".join(f"{r['scene']} {r['bake_s']:.1f} / {100 * r['traced_fraction']:.0f}%"
                          for r in tree)]
    return "\n".join(lines)


def stage_table(rows) -> str:
    """The tree frame per scene: wall and CPU seconds, CPU seconds per stage of the frame
    (summed over the workers; the object stage includes the query's own work and the rays it
    traces), and the same frame by ``riray render`` in a fresh process with its peak RSS."""
    tree = [r for r in rows if r["label"] == "riray_interpolated"]
    stages = list(dict.fromkeys(k for r in tree for k in r if k.startswith("stage_")))
    names = [k[len("stage_"):-len("_cpu_s")].replace("_", " ") for k in stages]
    lines = ["| scene | size | s / frame | CPU s | " + " | ".join(names)
             + " | query's own CPU s | riray render s / frame | peak RSS MiB |",
             "|---|---|" + "---:|" * (len(stages) + 5)]
    for r in tree:
        lines.append(f"| {r['scene']} | {r['size']} | {r['frame_s']:.2f} | "
                     f"{r['frame_cpu_s']:.2f} | "
                     + " | ".join(_cell(r.get(k), "{:.2f}") for k in stages)
                     + f" | {r['query_own_cpu_s']:.2f} | {r['cli_frame_s']:.2f} | "
                     f"{r['peak_rss_mib']:.0f} |")
    return "\n".join(lines)


def query_table(rows) -> str:
    """The tree frame's object stage per scene: CPU seconds of each step of the query (summed
    over the workers; first hits, trace, newton and paths are its exact work)."""
    tree = [r for r in rows if r["label"] == "riray_interpolated"]
    steps = list(dict.fromkeys(k for r in tree for k in r if k.startswith("query_")
                               and k.endswith("_cpu_s") and k != "query_own_cpu_s"))
    names = [k[len("query_"):-len("_cpu_s")].replace("_", " ") for k in steps]
    lines = ["| scene | size | object CPU s | " + " | ".join(names) + " |",
             "|---|---|" + "---:|" * (len(steps) + 1)]
    for r in tree:
        cells = [_cell(r.get(k), "{:.2f}") for k in ("stage_object_cpu_s", *steps)]
        lines.append(f"| {r['scene']} | {r['size']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def markdown(rows) -> str:
    return side_by_side(rows) + "\n\n" + stage_table(rows) + "\n\n" + query_table(rows)


class OneLineParser(argparse.ArgumentParser):
    """Bad input: one line naming it, exit status 2 (no usage, no traceback)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def image_size(text: str) -> tuple[int, int]:
    """--size: N (N x N pixels) or WIDTHxHEIGHT, each side 1..MAX_IMAGE_SIDE pixels."""
    parts = text.lower().split("x")
    if len(parts) > 2 or not all(p.isdigit() for p in parts):
        raise argparse.ArgumentTypeError(f"{text!r}: expected N or WIDTHxHEIGHT pixels, e.g. "
                                         "300 or 1920x1080")
    w, h = int(parts[0]), int(parts[-1])
    try:
        check_image_size(w, h)
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"{text!r}: {e}") from None
    return w, h


def positive_int(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a whole number >= 1")
    return int(text)


def parse_args(argv: list[str]) -> argparse.Namespace:
    """The bench's arguments, all checked before any work (bad input: one line, exit 2);
    ``params``: the BakeParams of the ``--quality`` preset."""
    ap = OneLineParser(prog="blender_bench.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", help=f"samples (default: {', '.join(SAMPLES)})")
    ap.add_argument("--out", default="bench_out/blender")
    ap.add_argument("--view", default="close", choices=("far", "close", "zoom"))
    ap.add_argument("--size", type=image_size, default=(300, 300),
                    help="N (N x N pixels) or WIDTHxHEIGHT (default 300)")
    ap.add_argument("--quality", choices=tuple(QUALITY_PRESETS), default="default",
                    help="bake quality preset of the tree, as riray bake --quality and the "
                    "add-on's Quality (default: default)")
    ap.add_argument("--spp", type=positive_int, nargs="+", default=[1, 4, 16, 64, 256])
    ap.add_argument("--reference-spp", type=positive_int, default=1024)
    ap.add_argument("--workers", type=positive_int, default=os.cpu_count() or 1)
    ap.add_argument("--eevee", action=argparse.BooleanOptionalAction, default=True,
                    help="render EEVEE too (default: yes)")
    args = ap.parse_args(argv)
    args.names = args.names or list(SAMPLES)
    bad = [n for n in args.names if n not in SAMPLES]
    if bad:
        ap.error(f"unknown sample(s) {bad}; choose from {', '.join(SAMPLES)}")
    args.params = BakeParams.preset(args.quality).validate()
    return args


def command_line(args) -> str:
    """The command that reproduces ``args``."""
    w, h = args.size
    return " ".join(["python sample_scenes/blender_bench.py", *args.names, "--out", args.out,
                     "--view", args.view, "--size", f"{w}x{h}", "--quality", args.quality,
                     "--spp", *map(str, args.spp), "--reference-spp", str(args.reference_spp),
                     "--workers", str(args.workers), *([] if args.eevee else ["--no-eevee"])])


def main(argv=None) -> int:
    args = parse_args(build_blend.script_args(sys.argv) if argv is None else argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    def log(msg):
        print(f"{(time.perf_counter() - t0) / 60:5.1f} min  {msg}", file=sys.stderr, flush=True)

    rows = []
    with tempfile.TemporaryDirectory(prefix="riray_blender_bench_") as tmp:
        for n in args.names:
            rows += bench_scene(n, args, out, Path(tmp), log)
    res = {"machine": machine(), "blender": bpy.app.version_string,
           "command": command_line(args), "elapsed_s": time.perf_counter() - t0, "rows": rows}
    (out / "blender.json").write_text(json.dumps(json_safe(res), indent=1) + "\n")
    stages = list(dict.fromkeys(k for r in rows for k in r
                                if k.startswith(("stage_", "query_")) and k not in COLS))
    with open(out / "blender.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow((*COLS, *stages))
        for r in rows:
            w.writerow(["" if r.get(c) is None else r.get(c) for c in (*COLS, *stages)])
    (out / "blender.md").write_text(markdown(rows) + "\n")
    print(markdown(rows))
    print(f"wrote {out / 'blender.json'}, blender.csv, blender.md and images")
    return 0


if __name__ == "__main__":
    sys.exit(main())
