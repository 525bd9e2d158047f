"""Rendering through the RI-Tree, measured against the exact renderer in the same run.

The frame is cut into shares (one per worker process; exact.share_size). Each share is rendered
twice in the same process, interleaved: once with the exact object function, once with the tree
(``ritree.query.TreeQuery``, one staged call over the whole share), the order alternating from
share to share, so the *object-only* times compare the same rays under the same machine load
(paper, section 6). Times are CPU seconds of the worker's CPU clock (``*_cpu_s``) and wall
seconds (``*_wall_s``). Outputs:
- the interpolated image (and the exact one, as reference),
- the traced mask (white = traced, as in the paper's Figures 15-17),
- the angular-error image (Figure 14's colouring: grey 0-2 deg, lighter = smaller; green
  above 2 deg; red traced; black off the object),
- stats: how every ray was answered, rays traced, times, and the angular error of the
  interpolated output rays against the exact ones (mean, 99th percentile, max).
"""

from __future__ import annotations

import time

import numpy as np

from ..parallel import map_chunks, workers_default
from ..ritree.query import ANSWER_NAMES, OUTSIDE, TRACED, TRACING_STAGES, WHY_NAMES, TreeQuery
from ..scene.camera import camera_rays
from ..trace.scene_tracer import SceneTracer
from .compare import compare_share, disagreements  # noqa: F401  (disagreements: re-exported)
from .exact import RenderResult
from .frame import (ExactAnswerer, FrameResult, TreeAnswerer, join_shares, peak_rss_mib,
                    share_size)

ERROR_GREY_MAX_DEG = 2.0     # Figure 14: greyscale up to 2 degrees, green beyond


def render_tree(scene, tree, camera=None, width=None, height=None, options=None,
                reference=True, workers=None, progress=None, st: SceneTracer | None = None):
    """Render ``camera`` through ``tree``; with ``reference`` also exactly (same rays, same
    process, interleaved) for the error statistics and images. Returns a RenderResult whose
    ``masks`` hold "traced", "object", "angle_error_deg" and, with reference, "exact"."""
    w = int(scene.render.width if width is None else width)
    h = int(scene.render.height if height is None else height)
    cam = scene.camera(camera)
    o, d = camera_rays(cam, w, h)
    st = st or SceneTracer(scene)
    query = TreeQuery(tree, st, options)
    tree_answerer = TreeAnswerer(query)
    exact_answerer = ExactAnswerer(st) if reference else None
    workers = workers_default() if workers is None else workers
    size = share_size(len(o), workers)

    def work(a, b):
        return compare_share(st, o[a:b], d[a:b], tree_answerer, exact_answerer,
                             exact_first=bool((a // size) % 2))

    t0 = time.perf_counter()
    parts = map_chunks(work, len(o), size, workers, progress)
    frame = join_shares([p.tree for p in parts], time.perf_counter() - t0)
    err = np.concatenate([p.err_deg for p in parts])
    stats = _answer_stats(frame)
    summary = {"scene": scene.name, "camera": cam.name, "width": w, "height": h,
               "mode": "interpolated", "policy": query.opt.policy, **_tree_summary(frame)}
    masks = {"traced": traced_mask(frame.answer).reshape(h, w),
             "object": frame.object_mask.reshape(h, w), "angle_error_deg": err.reshape(h, w)}
    if reference:
        exact = join_shares([p.exact for p in parts], frame.wall_s)
        summary.update(_reference_summary(frame, exact, parts, err))
        stats["exact_counts"] = exact.stats
        masks["exact"] = exact.color.reshape(h, w, 3)
    stats["summary"] = summary
    return RenderResult(image=frame.color.reshape(h, w, 3), stats=stats, masks=masks)


def traced_mask(answer: np.ndarray) -> np.ndarray:
    """Rays traced exactly by the tree query (inside the tree or outside it)."""
    return (answer == TRACED) | (answer == OUTSIDE)


def _answer_stats(frame: FrameResult) -> dict:
    """How every ray was answered and why rays were traced; the query's summed counts."""
    a, why = frame.answer, frame.why
    return {"answers": {ANSWER_NAMES[k]: int(np.sum(a == k)) for k in range(len(ANSWER_NAMES))},
            "traced_because": {WHY_NAMES[k]: int(np.sum(why == k))
                               for k in range(1, len(WHY_NAMES))},
            "interp_counts": frame.stats}


def _tree_summary(frame: FrameResult) -> dict:
    """The tree render's share of the summary: pixels, traced rays, times, memory."""
    si, obj = frame.stats, frame.object_mask
    traced = traced_mask(frame.answer)
    n_obj = int(obj.sum())
    return {"object_pixels": n_obj, "rays_traced": int(traced.sum()),
            "traced_fraction_of_object": round(float(traced[obj].mean()) if n_obj else 0.0, 5),
            "interp_object_only_cpu_s": round(si["object_cpu_s"], 4),
            "interp_total_cpu_s": round(si["total_cpu_s"], 4),
            "interp_object_only_wall_s": round(si["object_wall_s"], 4),
            "interp_total_wall_s": round(si["total_wall_s"], 4),
            "query_own_cpu_s": round(query_own_cpu(si), 4),
            "shares": frame.shares, "wall_s": round(frame.wall_s, 4),
            "peak_rss_mib": round(peak_rss_mib(), 1)}


def _reference_summary(frame: FrameResult, exact: FrameResult, parts, err) -> dict:
    """Against the exact frame: times and speed-ups, angular error, disagreements, PSNR."""
    si, sx = frame.stats, exact.stats
    e = err[np.isfinite(err)]
    img, ref = frame.color, exact.color
    return {
        "exact_object_only_cpu_s": round(sx["object_cpu_s"], 4),
        "exact_total_cpu_s": round(sx["total_cpu_s"], 4),
        "exact_object_only_wall_s": round(sx["object_wall_s"], 4),
        "exact_total_wall_s": round(sx["total_wall_s"], 4),
        "object_only_speedup": round(sx["object_cpu_s"] / max(si["object_cpu_s"], 1e-9), 3),
        "total_speedup": round(sx["total_cpu_s"] / max(si["total_cpu_s"], 1e-9), 3),
        "query_own_fraction_of_exact_object_only": round(
            query_own_cpu(si) / max(sx["object_cpu_s"], 1e-9), 4),
        "angle_error_deg_mean": round(float(e.mean()), 5) if len(e) else None,
        "angle_error_deg_p99": round(float(np.percentile(e, 99)), 5) if len(e) else None,
        "angle_error_deg_max": round(float(e.max()), 5) if len(e) else None,
        "hit_disagreements": sum(p.hit_disagree for p in parts),
        "null_disagreements": sum(p.null_disagree for p in parts),
        "psnr_db": round(psnr(img, ref), 3),
        "max_pixel_diff": round(float(np.abs(_clip(img) - _clip(ref)).max()), 5)}


def query_own_cpu(stats: dict) -> float:
    """CPU seconds of the RI-Tree query's own work in summed render stats: every query stage
    but the exact tracing it calls (query.TRACING_STAGES)."""
    return sum(v for k, v in stats.items() if k.startswith("query_") and k.endswith("_cpu_s")
               and k[len("query_"):-len("_cpu_s")] not in TRACING_STAGES)


def _clip(img):
    return np.clip(img, 0.0, 1.0)


def psnr(a, b) -> float:
    """PSNR in dB of display-range (clipped to [0, 1]) linear images; inf when identical."""
    mse = float(np.mean((_clip(a) - _clip(b)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


def error_image(err_deg: np.ndarray, traced: np.ndarray, objmask: np.ndarray) -> np.ndarray:
    """Figure 14's colouring as uint8 RGB: grey (white = 0 deg, dark = 2 deg) where interpolated,
    green above 2 deg, red where traced, black off the object."""
    h, w = err_deg.shape
    img = np.zeros((h, w, 3), np.uint8)
    ok = np.isfinite(err_deg) & objmask
    g = np.clip(1.0 - err_deg / ERROR_GREY_MAX_DEG, 0.0, 1.0) * 200 + 55
    grey = ok & (err_deg <= ERROR_GREY_MAX_DEG)
    img[grey] = np.repeat(g[grey].astype(np.uint8)[:, None], 3, axis=1)
    img[ok & (err_deg > ERROR_GREY_MAX_DEG)] = (0, 200, 0)
    img[traced & objmask] = (220, 0, 0)
    return img


def save_tree_render(res: RenderResult, folder) -> list:
    """Write interpolated.png/.npy, traced.png (white = traced), angle_error.png (with a
    reference), exact.png/.npy (with a reference) and stats.json into ``folder``."""
    import json
    from pathlib import Path

    from ..atomic import atomic_write_text
    from .image import write_float_image, write_png, write_png_u8
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []

    def put(name, fn, img):
        p = folder / name
        fn(p, img)
        out.append(p)

    put("interpolated.png", write_png, res.image)
    put("interpolated.npy", write_float_image, res.image)
    put("traced.png", write_png_u8, np.where(res.masks["traced"], 255, 0).astype(np.uint8))
    if "exact" in res.masks:
        put("exact.png", write_png, res.masks["exact"])
        put("exact.npy", write_float_image, res.masks["exact"])
        put("angle_error.png", write_png_u8, error_image(res.masks["angle_error_deg"],
                                                           res.masks["traced"], res.masks["object"]))
    p = folder / "stats.json"
    atomic_write_text(p, json.dumps(res.stats, indent=2, default=float) + "\n")
    out.append(p)
    return out
