"""Rendering through the RI-Tree, measured against the exact renderer in the same run.

The frame's camera rays (``Shot.samples`` per pixel, developed on the film: render/film.py) are
cut into shares (one per worker process; frame.share_size). Each share is rendered
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
from dataclasses import dataclass

import numpy as np

from ..parallel import map_chunks, workers_default
from ..ritree.answers import ANSWER_NAMES, SOLVED, WHY_NAMES, is_traced
from ..ritree.query import TRACING_STAGES, QueryOptions, TreeQuery
from ..scene.camera import Shot, check_image_size
from ..trace.scene_tracer import SceneTracer
from .compare import compare_share
from .exact import RenderResult
from .film import Film, FilmPart
from .frame import (ExactAnswerer, Specular, TreeAnswerer, peak_rss_mib, share_size,
                    sum_stats)

ERROR_GREY_MAX_DEG = 2.0     # Figure 14: greyscale up to 2 degrees, green beyond


def render_tree(st: SceneTracer, tree, shot: Shot = Shot(), options=None, reference=True,
                workers=None, progress=None, others: tuple = ()) -> RenderResult:
    """Render ``shot`` of the scene ``st`` traces through ``tree`` (with the render-time rules
    ``options``), ``shot.samples`` rays per pixel, the tree answering every one; with
    ``reference`` also exactly (same rays, same process, interleaved) for the error statistics
    and images. ``others``: the scene's other specular objects as (SceneTracer, tree, or None
    to trace it exactly) pairs (``tree`` may be None too). Returns a RenderResult whose
    ``masks`` hold "traced", "object" (with one sample bool images; with more the fraction of
    each pixel's samples traced / hitting an object), "angle_error_deg" (per pixel, the mean
    over its measured samples; NaN where none) and, with reference, "exact" (the exact image).
    Stats count camera rays (samples); with several objects the summary has each one's."""
    scene = st.scene
    cam, w, h = shot.resolve(scene)
    check_image_size(w, h)
    film = Film(cam, w, h, shot.samples)
    options = QueryOptions() if options is None else options
    pairs = [(st, tree), *others]
    names = [s.scene.object.name for s, _ in pairs]
    through = [Specular(s, ExactAnswerer(s) if t is None else TreeAnswerer(TreeQuery(t, s, options)))
               for s, t in pairs]
    exact = [Specular(s, ExactAnswerer(s)) for s, _ in pairs] if reference else None
    workers = workers_default() if workers is None else workers
    size = share_size(film.n_rays, workers)

    def work(a, b):
        cs = compare_share(st, *film.rays(a, b), through[0].answerer,
                           exact[0].answerer if reference else None,
                           exact_first=bool((a // size) % 2), others_tree=through[1:],
                           others_exact=exact[1:] if reference else ())
        return _develop(film, a, b, cs, names)

    t0 = time.perf_counter()
    parts = map_chunks(work, film.n_rays, size, workers, progress)
    wall = time.perf_counter() - t0
    dev = film.join(p.film for p in parts)
    counts = sum_stats(p.counts for p in parts)
    si = sum_stats(p.tree_stats for p in parts)
    stats = _answer_stats(counts, si)
    summary = {"scene": scene.name, "camera": cam.name, "width": w, "height": h,
               "samples": shot.samples, "mode": "interpolated", "policy": options.policy,
               **_tree_summary(counts, si, len(parts), wall)}
    if len(pairs) > 1:
        summary["objects"] = {name: _object_summary(counts, name, t is not None)
                              for name, (_, t) in zip(names, pairs)}
    masks = {"traced": dev.fraction("traced"), "object": dev.fraction("object"),
             "angle_error_deg": dev.mean("err", "measured")}
    image = dev.images["color"]
    if reference:
        masks["exact"] = dev.images["exact"]
        sx = sum_stats(p.exact_stats for p in parts)
        summary.update(_reference_summary(si, sx, image, masks["exact"], parts))
        stats["exact_counts"] = sx
    stats["summary"] = summary
    return RenderResult(image=image, stats=stats, masks=masks)


def _object_summary(counts: dict, name: str, has_tree: bool) -> dict:
    """One specular object's share of a frame: its pixels (camera rays it is the nearest hit
    of) and the fractions of them traced and solved along a sample's path."""
    n = counts.get(f"{name}/hit", 0)
    return {"through": "tree" if has_tree else "exact", "object_pixels": n,
            "traced_fraction_of_object": round(counts.get(f"{name}/traced_hit", 0) / n
                                               if n else 0.0, 5),
            "solved_fraction_of_object": round(counts.get(f"{name}/solved_hit", 0) / n
                                               if n else 0.0, 5)}


@dataclass
class _TreePart:
    """One share through the tree (and exactly), developed: the film's part, summed stats,
    answer counts, and the measured angle errors (degrees) in ray order."""
    film: FilmPart
    tree_stats: dict
    exact_stats: dict
    counts: dict
    err: np.ndarray
    hit_disagree: int
    null_disagree: int


def _develop(film: Film, a: int, b: int, cs, names: list[str]) -> _TreePart:
    """A compared share's colours and masks onto the film; its counts for the stats, in sum
    and per object (``names``: the objects' names; an object traced exactly counts every ray
    handed to it as traced)."""
    tree, n = cs.tree, b - a
    hit = np.zeros(n)
    hit[tree.hit] = 1.0
    traced = np.zeros(n)
    codes, counts = [], {}
    for name, o in zip(names, tree.objects):
        ans = o.answer.answer
        own = np.ones(len(o.handed)) if ans is None else is_traced(ans)
        traced[o.handed] = np.maximum(traced[o.handed], own)
        counts.update({f"{name}/hit": int(o.won.sum()),
                       f"{name}/traced_hit": int(own[o.won].sum()),
                       f"{name}/solved_hit": 0 if ans is None else int((ans[o.won] == SOLVED).sum())})
        if ans is not None:
            codes.append((ans, o.answer.why))
    ans = np.concatenate([c[0] for c in codes]) if codes else np.zeros(0, np.int8)
    why = np.concatenate([c[1] for c in codes]) if codes else np.zeros(0, np.int8)
    measured = np.isfinite(cs.err_deg)
    filtered = {"color": tree.color}
    if cs.exact is not None:
        filtered["exact"] = cs.exact.color
    box = {"object": hit, "traced": traced, "measured": measured,
           "err": np.where(measured, cs.err_deg, 0.0)}
    counts.update({"answer": np.bincount(ans, minlength=len(ANSWER_NAMES)),
                   "why": np.bincount(why[is_traced(ans)], minlength=len(WHY_NAMES)),
                   "traced": int(traced.sum()),
                   "traced_hit": sum(counts[f"{m}/traced_hit"] for m in names),
                   "solved_hit": sum(counts[f"{m}/solved_hit"] for m in names),
                   "hit": len(tree.hit)})
    return _TreePart(film.develop(a, b, filtered, box), tree.stats,
                     cs.exact.stats if cs.exact is not None else {}, counts,
                     cs.err_deg[measured], cs.hit_disagree, cs.null_disagree)


def _answer_stats(counts: dict, si: dict) -> dict:
    """How every ray was answered and why rays were traced; the query's summed counts."""
    a, why = counts["answer"], counts["why"]
    return {"answers": {ANSWER_NAMES[k]: int(a[k]) for k in range(len(ANSWER_NAMES))},
            "traced_because": {WHY_NAMES[k]: int(why[k]) for k in range(1, len(WHY_NAMES))},
            "interp_counts": si}


def _tree_summary(counts: dict, si: dict, shares: int, wall_s: float) -> dict:
    """The tree render's share of the summary: object rays, traced rays, times, memory."""
    n_obj = counts["hit"]
    return {"object_pixels": n_obj, "rays_traced": counts["traced"],
            "traced_fraction_of_object": round(counts["traced_hit"] / n_obj if n_obj else 0.0, 5),
            "solved_fraction_of_object": round(counts["solved_hit"] / n_obj if n_obj else 0.0, 5),
            "interp_object_only_cpu_s": round(si["object_cpu_s"], 4),
            "interp_total_cpu_s": round(si["total_cpu_s"], 4),
            "interp_object_only_wall_s": round(si["object_wall_s"], 4),
            "interp_total_wall_s": round(si["total_wall_s"], 4),
            "query_own_cpu_s": round(query_own_cpu(si), 4),
            "shares": shares, "wall_s": round(wall_s, 4),
            "peak_rss_mib": round(peak_rss_mib(), 1)}


def _reference_summary(si: dict, sx: dict, img, ref, parts) -> dict:
    """Against the exact frame (stats ``sx``, image ``ref``): times and speed-ups, angular
    error, disagreements, PSNR."""
    e = np.concatenate([p.err for p in parts])
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
    """Write interpolated.png/.npy, traced.png (white = traced; grey = that fraction of a
    pixel's samples), angle_error.png (with a reference; red where most samples were traced),
    exact.png/.npy (with a reference) and stats.json into ``folder``."""
    import json
    from pathlib import Path

    from ..files import atomic_write_text
    from ..imageio import write_float_image, write_png, write_png_u8
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []

    def put(name, fn, img):
        p = folder / name
        fn(p, img)
        out.append(p)

    put("interpolated.png", write_png, res.image)
    put("interpolated.npy", write_float_image, res.image)
    traced, objmask = res.masks["traced"], res.masks["object"]
    put("traced.png", write_png_u8, np.round(np.asarray(traced, float) * 255).astype(np.uint8))
    if "exact" in res.masks:
        put("exact.png", write_png, res.masks["exact"])
        put("exact.npy", write_float_image, res.masks["exact"])
        put("angle_error.png", write_png_u8, error_image(res.masks["angle_error_deg"],
                                                           traced >= 0.5, objmask > 0))
    p = folder / "stats.json"
    atomic_write_text(p, json.dumps(res.stats, indent=2, default=float) + "\n")
    out.append(p)
    return out
