"""Measuring ``riray bench``'s rows: bake a view's tree (:func:`bake_view`), render the view
through it and exactly, share by share, interleaved (:func:`measure_pass`), and run every pass
of a view's configurations as one batch (:func:`measure_configs`)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..parallel import map_chunks
from ..render.compare import compare_share
from ..render.frame import (NOT_HANDED, ExactAnswerer, TreeAnswerer, join_shares,
                            share_size)
from ..render.interpolated import psnr, query_own_cpu
from ..ritree import tree as ritree
from ..ritree.answers import EXTRA_S, OUTSIDE, SOLVED, is_interpolated, is_traced
from ..ritree.bake import bake
from ..ritree.query import DEFAULT_MAX_ERROR_DEG, TreeQuery
from ..ritree.region import region_for_cameras
from ..scene.camera import camera_rays
from .common import cpu_seconds, median

SAMPLES_PER_LOOKUP = 16      # a query ray reads 4 viewpoints x 4 direction-cell corners
SAMPLES_PER_EXTRA = 2        # ... and at least 2 extra samples when a leaf's extras answer it
TRACER_KEYS = ("pairs", "newton_iters", "fallback_pairs")


def bake_view(st, scene, cam, size, params, workers, tree_dir, height=None) -> tuple:
    """Bake the tree for camera ``cam`` at size x size pixels (size x ``height`` where given),
    save it, load it back. Returns (tree, bake record)."""
    region = region_for_cameras(st, params, [cam], size, size if height is None else height)
    c0, t0 = cpu_seconds(), time.perf_counter()
    tree = bake(st, params, region, workers=workers)
    wall, cpu = time.perf_counter() - t0, cpu_seconds() - c0
    path = Path(tree_dir) / (f"{scene.name}_{cam.name}_vp{params.viewpoint_depth}"
                             f"_vr{params.viewpoint_refine}_dir{params.direction_depth}"
                             f"_tol{params.tolerance_deg:g}.rit")
    ritree.save(tree, path)
    rec = {"viewpoint_depth": params.viewpoint_depth, "direction_depth": params.direction_depth,
           "viewpoint_refine": params.viewpoint_refine,
           "tolerance": params.tolerance_deg, "bake_s": wall, "bake_cpu_s": cpu,
           "cache_bytes": path.stat().st_size, "tree_samples": len(tree.samples),
           "bake_rays": int(tree.meta.get("rays_traced", 0)),
           "refine_passes": int(tree.meta.get("refine_passes", 0)), "tree_path": str(path)}
    return ritree.load(path, scene), rec


def measure_pass(st, tree, cam, size, options, order=0) -> dict:
    """One interleaved pass in this process (see the module doc): every share through the tree
    and exactly (render/compare.py).
    ``order`` 0: tree first, 1: exact first. Returns per-mode stats, answers, errors, images."""
    o, d = camera_rays(cam, size, size)
    tree_a, exact_a = TreeAnswerer(TreeQuery(tree, st, options)), ExactAnswerer(st)

    def work(a, b):
        return compare_share(st, o[a:b], d[a:b], tree_a, exact_a, exact_first=bool(order))

    t0 = time.perf_counter()
    parts = map_chunks(work, len(o), share_size(len(o), 1), 1)
    wall = time.perf_counter() - t0
    fi = join_shares([p.tree for p in parts], wall)
    fx = join_shares([p.exact for p in parts], wall)
    s_i, s_x = fi.stats, fx.stats
    answers = fi.answer
    err = np.concatenate([p.err_deg for p in parts])
    err = err[np.isfinite(err)]
    cand = answers != NOT_HANDED
    objmask = fx.object_mask
    traced = is_traced(answers)
    solved = answers == SOLVED
    beyond = np.concatenate([_beyond(p) for p in parts])
    lookups = int(np.sum(cand & (answers != OUTSIDE)))
    extra = int(np.sum(answers == EXTRA_S))
    return {"wall_s": wall, "s_i": s_i, "s_x": s_x, "answers": answers, "err": err,
            "img_i": fi.color.reshape(size, size, 3), "img_x": fx.color.reshape(size, size, 3),
            "traced_mask": traced.reshape(size, size),
            "rays_traced": int(traced.sum()), "object_rays": int(cand.sum()),
            "traced_fraction": float(traced[objmask].mean()) if objmask.any() else 0.0,
            "solved_fraction": float(solved[objmask].mean()) if objmask.any() else 0.0,
            "beyond_fraction": float(beyond[objmask].mean()) if objmask.any() else 0.0,
            "object_hits": int(s_x["object_hits"]),
            "interpolated": int(is_interpolated(answers).sum()),
            "samples_gathered": SAMPLES_PER_LOOKUP * lookups + SAMPLES_PER_EXTRA * extra,
            "hit_disagree": sum(p.hit_disagree for p in parts),
            "null_disagree": sum(p.null_disagree for p in parts)}


def _beyond(p) -> np.ndarray:
    """(n,) bool over a compared share's rays: answered (not traced) beyond the default
    tolerance, or with a wrong kind of answer (hit / miss, null / not null)."""
    ans, handed = p.tree.answer.answer, p.tree.handed
    ri, rx = p.tree.answer.rays, p.exact.answer.rays
    off = ~is_traced(ans) & ((ri.hit != rx.hit) | (ri.null != rx.null))
    off |= p.interpolated & (p.err_deg[handed] > DEFAULT_MAX_ERROR_DEG)
    beyond = np.zeros(len(p.tree.color), bool)
    beyond[handed[off]] = True
    return beyond


def _errors(p) -> dict:
    e = p["err"]        # empty where no ray was interpolated: no error to report (None)
    diff = np.abs(np.clip(p["img_i"], 0, 1) - np.clip(p["img_x"], 0, 1))
    return {"angle_mean_deg": float(e.mean()) if len(e) else None,
            "angle_p99_deg": float(np.percentile(e, 99)) if len(e) else None,
            "angle_max_deg": float(e.max()) if len(e) else None,
            "psnr_db": psnr(p["img_i"], p["img_x"]), "max_pixel_diff": float(diff.max()),
            "hit_disagreements": p["hit_disagree"], "null_disagreements": p["null_disagree"]}


def measure_configs(st, cam, size, configs: dict, workers) -> dict:
    """Measure the interpolated ``configs`` ({name: (tree, QueryOptions, passes)}) against
    exact, interleaved: every pass of every config in one batch, ``workers`` passes at a time
    (one process each; the order flips between a config's passes and between neighbouring
    configs). Returns {name: row} plus "exact" (the median over every pass) and "_images"."""
    names = list(configs)
    tasks = [(k, r) for r in range(max(c[2] for c in configs.values())) for k in names
             if r < configs[k][2]]
    for tree, opt, _ in configs.values():
        TreeQuery(tree, st, opt)          # the tree's load-time work, once, before the fork

    def one(a, b):
        k, r = tasks[a]
        tree, opt, _ = configs[k]
        return measure_pass(st, tree, cam, size, opt, order=(r + names.index(k)) % 2)

    passes = {k: [] for k in names}
    for (k, _), p in zip(tasks, map_chunks(one, len(tasks), 1, workers)):
        passes[k].append(p)
    all_p = [p for ps in passes.values() for p in ps]
    rows = {"exact": _exact_row(all_p)}
    images = {"exact": all_p[0]["img_x"]}
    for k, ps in passes.items():
        rows[k] = _interp_row(ps)
        images[k] = ps[0]["img_i"]
        images[k + "_traced"] = ps[0]["traced_mask"]
    rows["_images"] = images
    return rows


def _exact_row(all_p) -> dict:
    """The exact row of a view from all its passes: work counts of the first, CPU seconds the
    median over every pass's exact half."""
    first = all_p[0]
    ex_obj = [p["s_x"]["object_cpu_s"] for p in all_p]
    ex_tot = [p["s_x"]["total_cpu_s"] for p in all_p]
    return {"rays_traced": first["object_rays"], "object_rays": first["object_rays"],
            "object_hits": first["object_hits"], "interpolated": 0,
            "traced_fraction": 1.0 if first["object_rays"] else 0.0, "solved_fraction": 0.0,
            "beyond_fraction": 0.0,
            "object_cpu_s": median(ex_obj), "total_cpu_s": median(ex_tot),
            "object_cpu_s_all": ex_obj, "total_cpu_s_all": ex_tot,
            **{k: int(first["s_x"].get(k, 0)) for k in TRACER_KEYS},
            "exact_first_hits": 0, "exact_mirror_hits": 0, "mirror_newton_cpu_s": 0.0,
            "samples_gathered": 0,
            "angle_mean_deg": 0.0, "angle_p99_deg": 0.0, "angle_max_deg": 0.0,
            "psnr_db": float("inf"), "max_pixel_diff": 0.0, "hit_disagreements": 0,
            "null_disagreements": 0, "object_speedup": 1.0, "total_speedup": 1.0,
            "query_own_cpu_s": None, "query_own_fraction": None}      # no query


def _interp_row(ps) -> dict:
    """An interpolated configuration's row from its passes ``ps``: work counts and errors of
    the first, CPU seconds and speed-ups the median over the passes."""
    p = ps[0]
    io = [q["s_i"]["object_cpu_s"] for q in ps]
    it = [q["s_i"]["total_cpu_s"] for q in ps]
    # the same-pass exact times give a per-pass speed-up (noise cancels within a pass)
    sp_o = [q["s_x"]["object_cpu_s"] / max(q["s_i"]["object_cpu_s"], 1e-9) for q in ps]
    sp_t = [q["s_x"]["total_cpu_s"] / max(q["s_i"]["total_cpu_s"], 1e-9) for q in ps]
    own = [query_own_cpu(q["s_i"]) for q in ps]
    own_frac = [query_own_cpu(q["s_i"]) / max(q["s_x"]["object_cpu_s"], 1e-9) for q in ps]
    return {"rays_traced": p["rays_traced"], "object_rays": p["object_rays"],
            "exact_object_cpu_s": median([q["s_x"]["object_cpu_s"] for q in ps]),
            "exact_total_cpu_s": median([q["s_x"]["total_cpu_s"] for q in ps]),
            "object_hits": int(p["s_i"]["object_hits"]),
            "interpolated": p["interpolated"],
            "traced_fraction": p["traced_fraction"],
            "solved_fraction": p["solved_fraction"],
            "beyond_fraction": p["beyond_fraction"],
            "object_cpu_s": median(io), "total_cpu_s": median(it),
            "object_cpu_s_all": io, "total_cpu_s_all": it,
            "object_speedup": median(sp_o), "total_speedup": median(sp_t),
            "query_own_cpu_s": median(own), "query_own_fraction": median(own_frac),
            **{t: int(p["s_i"].get(t, 0)) for t in TRACER_KEYS},
            "exact_first_hits": int(p["s_i"].get("exact_first_hits", 0)),
            "exact_mirror_hits": int(p["s_i"].get("exact_mirror_hits", 0)),
            "mirror_newton_cpu_s": median([q["s_i"].get("query_newton_cpu_s", 0.0) for q in ps]),
            "samples_gathered": p["samples_gathered"], **_errors(p)}
