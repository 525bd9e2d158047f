"""riray next to Blender's own renderers on the sample scenes (docs/benchmarks.md, "Blender").

    .venv/bin/python sample_scenes/blender_bench.py [NAME ...] [--out bench_out/blender]
        [--view close] [--size 300] [--spp 1 4 16 64 256] [--reference-spp 1024] [--workers 2]

Needs the bpy wheel (``make venv-bpy``) and the installed ``riray``. For each sample scene the
*fair* variant (riray.bench.compare.whitted_scene: emission-only environment, no lights, a pure
sharp mirror / refractor) is built as a Blender scene by sample_scenes/build_blend.py - the
same builder that makes the sample .blend files the add-on renders - and rendered at the same
resolution with
- Cycles (CPU, ``--workers`` threads, fixed seed, no adaptive sampling, no light-path limits
  below riray's max_events) at each ``--spp``, without and with OpenImageDenoise;
- Cycles at ``--reference-spp`` with the default 1.5 px filter: the converged reference;
- Cycles at 16 spp with a 0.01 px filter: point sampling, the check that Cycles and riray
  compute the same Whitted answer (riray shoots one ray through each pixel centre);
- EEVEE (what this machine offers: without a GPU Blender falls back to software OpenGL, so its
  time here says nothing about EEVEE on a graphics card);
and the same core Scene is rendered by riray in this process: exact, and through an RI-Tree
baked for the view (viewpoint depth 4, direction depth 5) with the default query options
(the 2 degree baked-error tolerance). Every image is compared with the
reference (PSNR of display-range linear RGB, max per-pixel difference); times are wall seconds
per frame (Cycles: the whole render call, scene sync included; riray: the render, with the
once-per-scene acceleration-structure build and the bake listed apart).

Writes OUT/blender.json, OUT/blender.csv, OUT/blender.md and the images (OUT/<scene>_*.png).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
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
from riray.bench.ritree_config import BenchConfig  # noqa: E402
from riray.bench.ritree_measure import bake_view  # noqa: E402
from riray.bench.ritree_output import json_safe  # noqa: E402
from riray.render.exact import render_exact  # noqa: E402
from riray.imageio import write_png  # noqa: E402
from riray.render.interpolated import psnr, render_tree  # noqa: E402
from riray.scene.camera import Shot  # noqa: E402
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
    bpy.ops.render.render(write_still=True)
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


def bench_scene(name, view, size, spps, ref_spp, workers, out: Path, tmp: Path, log) -> list:
    core = whitted_scene(build(name))
    core.render.width = core.render.height = size
    obj = build_blend.build_scene(name, core_scene=core)
    fix = prepare_object(obj, core.object.material.kind != "mirror", TESSELLATION)
    log(f"{name}: Blender object {fix}")
    scene = bpy.context.scene
    scene.camera = bpy.data.objects[view]
    scene.render.resolution_x = scene.render.resolution_y = size
    cycles_setup(scene, core.render.max_events, workers)
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

    cyc(f"cycles_ref_{ref_spp}", ref_spp)
    ref = images[f"cycles_ref_{ref_spp}"]
    cyc(f"cycles_point_{POINT_SPP}", POINT_SPP, filt=POINT_FILTER_PX)
    for spp in spps:
        cyc(f"cycles_{spp}", spp)
        cyc(f"cycles_{spp}_denoised", spp, denoise=True)
    # EEVEE: screen-space / ray-traced refraction approximations, whatever this build offers
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
            rows.append({"renderer": "eevee", "label": "eevee", "error": str(e)})
            log(f"{name}/{view} eevee failed: {e}")
            break
        images["eevee"] = img
        rows.append({"renderer": "eevee", "label": "eevee", "engine": eng, "frame_s": wall})
        log(f"{name}/{view} eevee: {wall:.2f} s")
        break
    # riray on the very same core scene
    t0 = time.perf_counter()
    st = SceneTracer(core)
    build_s = time.perf_counter() - t0
    cam = core.camera(view)
    ex = render_exact(st, Shot(camera=view, width=size, height=size), workers=workers)
    images["riray_exact"] = ex.image
    rows.append({"renderer": "riray", "label": "riray_exact", "frame_s": ex.stats["summary"]["wall_s"],
                 "build_s": build_s})
    cfg = BenchConfig()
    params = cfg.bake_params(cfg.viewpoint_depth, cfg.direction_depth, cfg.tolerance)
    tree, brec = bake_view(st, core, cam, size, params, workers, tmp)
    it = render_tree(st, tree, Shot(camera=view, width=size, height=size),
                     options=QueryOptions(), reference=False, workers=workers)
    images["riray_interpolated"] = it.image
    rows.append({"renderer": "riray", "label": "riray_interpolated",
                 "frame_s": it.stats["summary"]["wall_s"], "build_s": build_s,
                 "bake_s": brec["bake_s"], "cache_bytes": brec["cache_bytes"],
                 "traced_fraction": it.stats["summary"]["traced_fraction_of_object"]})
    log(f"{name}/{view} riray: exact {rows[-2]['frame_s']:.2f} s, interpolated "
        f"{rows[-1]['frame_s']:.2f} s (bake {brec['bake_s']:.1f} s)")
    point = images[f"cycles_point_{POINT_SPP}"]
    for r in rows:
        r.update(scene=name, view=view, size=size)
        if r["label"] in images:
            r.update(compare(images[r["label"]], ref))
            r["psnr_vs_point_db"] = compare(images[r["label"]], point)["psnr_db"]
    for label, img in images.items():
        write_png(out / f"{name}_{view}_{label}.png", img)
    return rows


COLS = ("scene", "view", "size", "renderer", "label", "spp", "denoise", "filter_px", "frame_s",
        "psnr_db", "psnr_vs_point_db", "max_pixel_diff", "mean_abs_diff", "build_s", "bake_s",
        "cache_bytes", "traced_fraction", "engine", "error")


def markdown(rows) -> str:
    lines = ["| scene | renderer | setting | s / frame | PSNR vs reference dB | max diff | "
             "PSNR vs point-sampled Cycles dB |", "|---|---|---|---:|---:|---:|---:|"]

    def f(v, fmt):
        if v is None:
            return "-"
        return "inf" if isinstance(v, float) and not np.isfinite(v) else fmt.format(v)

    for r in rows:
        setting = r["label"]
        if r["renderer"] == "cycles":
            setting = (f"{r['spp']} spp" + (", denoised" if r["denoise"] else "")
                       + (" (point filter)" if r["filter_px"] < 1 else "")
                       + (" (reference)" if "ref" in r["label"] else ""))
        elif r["label"] == "riray_interpolated":
            setting = (f"interpolated (bake {r['bake_s']:.1f} s, "
                       f"{100 * r['traced_fraction']:.0f}% traced)")
        elif r["label"] == "riray_exact":
            setting = "exact"
        lines.append(f"| {r['scene']} | {r['renderer']} | {setting} | "
                     f"{f(r.get('frame_s'), '{:.2f}')} | {f(r.get('psnr_db'), '{:.1f}')} | "
                     f"{f(r.get('max_pixel_diff'), '{:.2f}')} | "
                     f"{f(r.get('psnr_vs_point_db'), '{:.1f}')} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", help=f"samples (default: {', '.join(SAMPLES)})")
    ap.add_argument("--out", default="bench_out/blender")
    ap.add_argument("--view", default="close", choices=("far", "close", "zoom"))
    ap.add_argument("--size", type=int, default=300)
    ap.add_argument("--spp", type=int, nargs="+", default=[1, 4, 16, 64, 256])
    ap.add_argument("--reference-spp", type=int, default=1024)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = ap.parse_args(build_blend.script_args(sys.argv) if argv is None else argv)
    names = args.names or list(SAMPLES)
    bad = [n for n in names if n not in SAMPLES]
    if bad:
        ap.error(f"unknown sample(s) {bad}; choose from {', '.join(SAMPLES)}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    def log(msg):
        print(f"{(time.perf_counter() - t0) / 60:5.1f} min  {msg}", file=sys.stderr, flush=True)

    rows = []
    with tempfile.TemporaryDirectory(prefix="riray_blender_bench_") as tmp:
        for n in names:
            rows += bench_scene(n, args.view, args.size, args.spp, args.reference_spp,
                                args.workers, out, Path(tmp), log)
    res = {"machine": machine(), "blender": bpy.app.version_string,
           "command": "python sample_scenes/blender_bench.py " + " ".join(
               [*names, "--out", args.out, "--view", args.view, "--size", str(args.size),
                "--spp", *map(str, args.spp), "--reference-spp", str(args.reference_spp),
                "--workers", str(args.workers)]),
           "elapsed_s": time.perf_counter() - t0, "rows": rows}
    (out / "blender.json").write_text(json.dumps(json_safe(res), indent=1) + "\n")
    with open(out / "blender.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(COLS)
        for r in rows:
            w.writerow(["" if r.get(c) is None else r.get(c) for c in COLS])
    (out / "blender.md").write_text(markdown(rows) + "\n")
    print(markdown(rows))
    print(f"wrote {out / 'blender.json'}, blender.csv, blender.md and images")
    return 0


if __name__ == "__main__":
    sys.exit(main())
