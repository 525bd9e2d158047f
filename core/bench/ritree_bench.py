"""RI-Tree benchmark (``riray bench``): the paper's Tables 1-3 for the sample scenes and views,
parameter sweeps, and the plots that read them.

**Tables** (paper, section 6): for each sample scene and view (far, close, zoom), one RI-Tree
is baked for that camera and five rows are measured: *exact* (every object ray traced),
*interpolated* without an angle threshold, *interpolated* with the angle threshold,
*interpolated* with the default baked-error tolerance, and the *raytree* policy (Bala et al.'s
identical-ray-tree rule); a sixth, *deeper*, is the default tolerance on a second tree for the
camera baked at ``deeper_tree``'s depths, against its own exact passes. On a mirror, whose
default answers come from exact mirror hits (``--mirror-rays newton``), each tree also gets the
default tolerance with mirror rays from the interpolated hit and normal (``--mirror-rays
reflect``: rows *interp_reflect* and *deeper_reflect*). A last row, *deeper_rules* (one pass),
runs the deeper tree's default rules without the tolerance: the object pixels they trace or
answer beyond the default tolerance (or with a wrong kind of answer: hit / miss, null) are the
*floor* no render-time rule on that tree can go below. Columns: rays traced, the traced share
of the object and that share plus the share answered beyond the tolerance,
object-only and total CPU seconds (the paper's split, summed over a pass's shares) and a
machine-independent work count - flat-sub-patch pairs solved by Newton and Newton iterations
(tracing), samples gathered (interpolation: 16 per ray looked up in the tree, 2 more per ray
answered from a leaf's extra samples) - because wall time on a shared machine is noisy.

**Measurement.** One *pass* renders the whole view in one worker process, share by share; every
share is rendered through the tree and exactly, one right after the other (the order flips from
pass to pass), so both see the same load and caches. All passes of a view (every row's and
sweep point's, on every tree baked for it) run as one batch, ``workers`` passes at a time, each
in its own process, so the other core is busy for both halves of nearly every pass alike. (A
view split over two processes is not: the share that finishes last runs its second half alone
on an idle machine, and that half, exact or interpolated by the pass's order, ran measurably
faster.) Each interpolated configuration gets ``repeats`` passes (sweep points
``sweep_repeats``, the policy points of the Pareto curves at least ``pareto_repeats``); the
exact row is the median over all passes of the view, each interpolated
row the median over its own, and of its own passes' exact halves (``exact_object_cpu_s``).
Work counts and errors are deterministic (first pass). The tree is saved to a .rit file and
loaded back (memory-mapped, packed samples) before rendering, as ``riray render --tree`` would
use it.

**Sweeps** (on ``sweep_scenes``, ``sweep_view``): viewpoint x direction depth, bake tolerance
(re-bake each), and the render-time options angle threshold, distance threshold and
extrapolation (one tree, at the table depths): bake wall and CPU time, cache size, render time,
traced fraction, angular error of the interpolated output rays (mean, 99th percentile, max),
image error against the exact render (PSNR, max per-pixel difference).

**Output** (folder ``out``): ``tables.csv``, ``sweeps.csv``, ``results.json`` (everything, with
the machine and the command), ``tables.md`` and ``sweeps.md`` (Markdown), the plots
``pareto.png`` (error versus render time, Pareto front marked), ``bake_depth.png`` (bake time
and cache size versus depth), ``amortized.png`` (time per frame versus frame count: bake + N
interpolated frames against N exact frames, break-even marked) - plots need matplotlib
(``pip install 'riray[bench]'``; imported only here, lazily) - and per-view images
(``images/``: exact, interpolated, traced masks).
"""

from __future__ import annotations

import csv
import json
import math
import resource
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..parallel import map_chunks, workers_default
from ..render.camera import camera_rays
from ..render.exact import SceneTracer, render_pixels, share_size
from ..render.interpolated import disagreements, psnr, query_own_cpu
from ..ritree import tree as ritree
from ..ritree.bake import bake
from ..ritree.interp import angle_between
from ..ritree.query import (DEFAULT_MAX_ERROR_DEG, EXTRA_S, EXTRAPOLATED_S, FULL, OUTSIDE,
                            TRACED, QueryOptions,
                            TreeQuery)
from ..ritree.region import region_for_cameras
from ..scene.samples import SAMPLES, build
from .exact_bench import machine
from .pareto import dominance, dominance_markdown

VIEWS = ("far", "close", "zoom")
ROWS = ("exact", "interp", "interp_angle", "interp_tol", "interp_reflect", "raytree", "deeper",
        "deeper_reflect", "deeper_rules")
ROW_LABELS = {"exact": "ray traced", "interp": "interpolated (no angle threshold)",
              "interp_angle": "interpolated (angle threshold {angle:g} deg)",
              "interp_tol": f"interpolated (default: max error {DEFAULT_MAX_ERROR_DEG:g} deg)",
              "interp_reflect": "default tolerance, mirror rays from the interpolated normal "
                                "(--mirror-rays reflect)",
              "raytree": "raytree policy (Bala et al.)",
              "deeper": "default tolerance, deeper tree (viewpoint depth {vp} + refine {vr}{fm}, "
                         "direction depth {dd})",
              "deeper_reflect": "deeper tree, mirror rays from the interpolated normal",
              "deeper_rules": "deeper tree, default rules without the tolerance (one pass)"}


def paper(**kw) -> QueryOptions:
    """The paper's rules with options ``kw``: no baked-error tolerance, mirror rays
    interpolated."""
    return QueryOptions(**{"max_error_deg": None, "mirror_rays": "interpolate", **kw})
SAMPLES_PER_LOOKUP = 16      # a query ray reads 4 viewpoints x 4 direction-cell corners
SAMPLES_PER_EXTRA = 2        # ... and at least 2 extra samples when a leaf's extras answer it
TRACER_KEYS = ("pairs", "newton_iters", "fallback_pairs")


@dataclass
class BenchConfig:
    """What one ``riray bench`` run measures. Depths and tolerances as in BakeParams; angles in
    degrees; distances relative to the object's box diagonal; None switches an option off."""

    out: str = "bench_out"
    scenes: tuple = SAMPLES
    views: tuple = VIEWS
    size: int = 300                       # image side (the paper: 300 x 300, one ray a pixel)
    repeats: int = 3                      # passes per interpolated configuration (median)
    workers: int | None = None
    viewpoint_depth: int = 4              # table trees
    direction_depth: int = 5
    tolerance: float = 0.5                # bake tolerance of the table trees (degrees)
    # (viewpoint depth, direction depth, viewpoint refine[, finest_min_traced]) of the "deeper"
    # row's own tree: the default tolerance on a tree the bake may refine further, where its
    # tests fail, the finest level only where that many camera rays are traced (None: no row)
    deeper_tree: tuple | None = (4, 7, 4, 20)
    angle: float = 20.0                   # the "with threshold" row (the CLI default)
    sweeps: bool = True
    sweep_scenes: tuple = ("glass_sphere", "vase_glass")
    sweep_view: str = "close"
    sweep_repeats: int = 1
    pareto_repeats: int = 3               # passes per policy point (the Pareto curves), median
    vp_depths: tuple = (3, 4, 5)
    dir_depths: tuple = (4, 5, 6)
    tolerances: tuple = (0.25, 0.5, 1.0, 2.0)
    angles: tuple = (None, 45.0, 20.0, 10.0, 5.0)
    distances: tuple = (None, 0.1, 0.05, 0.02)
    extrapolations: tuple = (None, 0.1, 0.25, 0.5)
    max_errors: tuple = (16.0, 8.0, 4.0, 2.0, 1.0, 0.5, 0.25)   # --max-error (no angle threshold)
    path_max_errors: tuple = (4.0, 2.0)          # --max-error with --path-identity
    plots: bool = True
    images: bool = True
    keep_trees: bool = False
    quick: bool = False

    def validate(self) -> "BenchConfig":
        for name in (*self.scenes, *self.sweep_scenes):
            if name not in SAMPLES:
                raise ValueError(f"scenes: unknown sample {name!r}; samples: {', '.join(SAMPLES)}")
        for v in (*self.views, self.sweep_view):
            if v not in VIEWS:
                raise ValueError(f"views: unknown view {v!r}; views: {', '.join(VIEWS)}")
        if self.size < 2:
            raise ValueError(f"size: must be >= 2 (got {self.size})")
        for name in ("repeats", "sweep_repeats", "pareto_repeats"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: must be >= 1 (got {getattr(self, name)})")
        self.bake_params(self.viewpoint_depth, self.direction_depth, self.tolerance)
        if self.deeper_tree is not None:
            if len(self.deeper_tree) not in (3, 4):
                raise ValueError("deeper_tree: (viewpoint depth, direction depth, viewpoint "
                                 f"refine[, finest_min_traced]) (got {self.deeper_tree!r})")
            self.bake_params(*self.deeper_tree[:2], self.tolerance, *self.deeper_tree[2:])
        for vp in self.vp_depths:
            for dd in self.dir_depths:
                self.bake_params(vp, dd, self.tolerance)
        for t in self.tolerances:
            self.bake_params(self.viewpoint_depth, self.direction_depth, t)
        for a in (self.angle, *self.angles, *self.distances, *self.extrapolations,
                  *self.max_errors, *self.path_max_errors):
            if a is not None and not (math.isfinite(a) and a >= 0):
                raise ValueError(f"thresholds: must be finite and >= 0 (got {a!r})")
        return self

    def bake_params(self, vp, dd, tol, refine=None, finest=0) -> ritree.BakeParams:
        """BakeParams with the angular tolerance ``tol`` and the distance tolerance scaled with
        it from the defaults (0.5 deg <-> 0.002 of the box diagonal): one accuracy knob.
        ``refine``: viewpoint refinement levels (None: the default); ``finest``:
        finest_min_traced."""
        d = ritree.BakeParams()
        return ritree.BakeParams(viewpoint_depth=int(vp), direction_depth=int(dd),
                                 viewpoint_refine=d.viewpoint_refine if refine is None
                                 else int(refine),
                                 min_direction_depth=min(d.min_direction_depth, int(dd)),
                                 tolerance_deg=float(tol),
                                 tolerance_dist=d.tolerance_dist * float(tol) / d.tolerance_deg,
                                 finest_min_traced=int(finest)).validate()


# The --quick preset: a smoke check (< 2 minutes on two cores at its default size).
QUICK = dict(scenes=("glass_sphere", "vase_mirror"), views=("close", "zoom"), size=64,
             repeats=1, viewpoint_depth=3, direction_depth=4, sweep_scenes=("glass_sphere",),
             vp_depths=(2, 3), dir_depths=(3, 4), tolerances=(0.5, 2.0),
             angles=(None, 20.0, 5.0), distances=(None, 0.05), extrapolations=(None, 0.25),
             max_errors=(4.0, 1.0), path_max_errors=(2.0,), deeper_tree=(3, 5, 2), pareto_repeats=1,
             quick=True)


# --------------------------------------------------------------------------- measuring
def _cpu_seconds() -> float:
    """CPU seconds of this process and its reaped children (the bake's worker pools)."""
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def bake_view(st, scene, cam, size, params, workers, tree_dir) -> tuple:
    """Bake the tree for camera ``cam`` at size x size, save it, load it back (memory-mapped).
    Returns (tree, bake record)."""
    region = region_for_cameras(st, params, [cam], size, size)
    c0, t0 = _cpu_seconds(), time.perf_counter()
    tree = bake(st, params, region, workers=workers)
    wall, cpu = time.perf_counter() - t0, _cpu_seconds() - c0
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


def _tracer_delta(st, before):
    return {k: st.tracer.stats[k] - before[k] for k in TRACER_KEYS}


def measure_pass(st, tree, cam, size, options, order=0) -> dict:
    """One interleaved pass in this process (see the module doc): every share through the tree
    and exactly.
    ``order`` 0: tree first, 1: exact first. Returns per-mode stats, answers, errors, images."""
    query = TreeQuery(tree, st, options)
    o, d = camera_rays(cam, size, size)

    def work(a, b):
        oo, dd = o[a:b], d[a:b]
        box = {}

        def tree_fn(oc, dc, tmax):
            before = dict(st.tracer.stats)
            res, ans, _, qs = query(oc, dc, tmax)
            box.update(res=res, ans=ans)
            return res, {**qs, **_tracer_delta(st, before)}

        def exact_fn(oc, dc, tmax):
            before = dict(st.tracer.stats)
            res = st.object_function(oc, dc, tmax)
            box["xres"] = res
            return res, _tracer_delta(st, before)

        runs = [("interp", tree_fn), ("exact", exact_fn)]
        out = {}
        for name, fn in (runs if order == 0 else runs[::-1]):
            col, s, hit, cand = render_pixels(st, oo, dd, fn)
            out[name] = (col, s, hit, cand)
        cand = out["interp"][3]
        objmask = np.zeros(b - a, bool)
        objmask[out["exact"][2]] = True
        ans = box["ans"]
        ri, rx = box["res"], box["xres"]
        interp = (ans >= FULL) & (ans <= EXTRAPOLATED_S) & ri.hit & rx.hit & ~rx.null
        err = np.degrees(angle_between(ri.out_dir[interp], rx.out_dir[interp]))
        answers = np.full(b - a, -1, np.int8)
        answers[cand] = ans
        # answered (not traced) beyond the default tolerance, or with a wrong kind of answer
        # (hit / miss, null / not null)
        off = (ans != TRACED) & (ans != OUTSIDE) & ((ri.hit != rx.hit) | (ri.null != rx.null))
        off[np.flatnonzero(interp)[err > DEFAULT_MAX_ERROR_DEG]] = True
        beyond = np.zeros(b - a, bool)
        beyond[cand[off]] = True
        return {"col_i": out["interp"][0], "col_x": out["exact"][0], "s_i": out["interp"][1],
                "objmask": objmask, "beyond": beyond,
                "s_x": out["exact"][1], "answers": answers, "err": err,
                "disagree": disagreements(ri, rx)}

    t0 = time.perf_counter()
    parts = map_chunks(work, len(o), share_size(len(o), 1), 1)
    wall = time.perf_counter() - t0
    s_i, s_x = _sum(p["s_i"] for p in parts), _sum(p["s_x"] for p in parts)
    answers = np.concatenate([p["answers"] for p in parts])
    err = np.concatenate([p["err"] for p in parts])
    img_i = np.concatenate([p["col_i"] for p in parts]).reshape(size, size, 3)
    img_x = np.concatenate([p["col_x"] for p in parts]).reshape(size, size, 3)
    cand = answers >= 0
    objmask = np.concatenate([p["objmask"] for p in parts])
    traced = (answers == TRACED) | (answers == OUTSIDE)
    beyond = np.concatenate([p["beyond"] for p in parts])
    lookups = int(np.sum(cand & (answers != OUTSIDE)))
    extra = int(np.sum(answers == EXTRA_S))
    n_interp = int(np.sum((answers >= FULL) & (answers <= EXTRAPOLATED_S)))
    return {"wall_s": wall, "s_i": s_i, "s_x": s_x, "answers": answers, "err": err,
            "img_i": img_i, "img_x": img_x, "traced_mask": traced.reshape(size, size),
            "rays_traced": int(traced.sum()), "object_rays": int(cand.sum()),
            "traced_fraction": float(traced[objmask].mean()) if objmask.any() else 0.0,
            "beyond_fraction": float(beyond[objmask].mean()) if objmask.any() else 0.0,
            "object_hits": int(s_x["object_hits"]), "interpolated": n_interp,
            "samples_gathered": SAMPLES_PER_LOOKUP * lookups + SAMPLES_PER_EXTRA * extra,
            "hit_disagree": sum(p["disagree"][0] for p in parts),
            "null_disagree": sum(p["disagree"][1] for p in parts)}


def _sum(dicts):
    out = {}
    for d in dicts:
        for k, v in d.items():
            out[k] = out.get(k, 0) + v
    return out


def _median(xs):
    return float(np.median(np.asarray(xs, np.float64))) if len(xs) else float("nan")


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
    first = all_p[0]
    ex_obj = [p["s_x"]["object_cpu_s"] for p in all_p]
    ex_tot = [p["s_x"]["total_cpu_s"] for p in all_p]
    rows = {"exact": {"rays_traced": first["object_rays"], "object_rays": first["object_rays"],
                      "object_hits": first["object_hits"], "interpolated": 0,
                      "traced_fraction": 1.0 if first["object_rays"] else 0.0,
                      "beyond_fraction": 0.0,
                      "object_cpu_s": _median(ex_obj), "total_cpu_s": _median(ex_tot),
                      "object_cpu_s_all": ex_obj, "total_cpu_s_all": ex_tot,
                      **{k: int(first["s_x"].get(k, 0)) for k in TRACER_KEYS},
                      "exact_first_hits": 0, "exact_mirror_hits": 0, "mirror_newton_cpu_s": 0.0,
                      "samples_gathered": 0,
                      "angle_mean_deg": 0.0, "angle_p99_deg": 0.0, "angle_max_deg": 0.0,
                      "psnr_db": float("inf"), "max_pixel_diff": 0.0, "hit_disagreements": 0,
                      "null_disagreements": 0}}
    images = {"exact": first["img_x"]}
    for k, ps in passes.items():
        p = ps[0]
        io = [q["s_i"]["object_cpu_s"] for q in ps]
        it = [q["s_i"]["total_cpu_s"] for q in ps]
        # the same-pass exact times give a per-pass speed-up (noise cancels within a pass)
        sp_o = [q["s_x"]["object_cpu_s"] / max(q["s_i"]["object_cpu_s"], 1e-9) for q in ps]
        sp_t = [q["s_x"]["total_cpu_s"] / max(q["s_i"]["total_cpu_s"], 1e-9) for q in ps]
        own = [query_own_cpu(q["s_i"]) for q in ps]
        own_frac = [query_own_cpu(q["s_i"]) / max(q["s_x"]["object_cpu_s"], 1e-9) for q in ps]
        rows[k] = {"rays_traced": p["rays_traced"], "object_rays": p["object_rays"],
                   "exact_object_cpu_s": _median([q["s_x"]["object_cpu_s"] for q in ps]),
                   "exact_total_cpu_s": _median([q["s_x"]["total_cpu_s"] for q in ps]),
                   "object_hits": int(p["s_i"]["object_hits"]),
                   "interpolated": p["interpolated"],
                   "traced_fraction": p["traced_fraction"],
                   "beyond_fraction": p["beyond_fraction"],
                   "object_cpu_s": _median(io), "total_cpu_s": _median(it),
                   "object_cpu_s_all": io, "total_cpu_s_all": it,
                   "object_speedup": _median(sp_o), "total_speedup": _median(sp_t),
                   "query_own_cpu_s": _median(own), "query_own_fraction": _median(own_frac),
                   **{t: int(p["s_i"].get(t, 0)) for t in TRACER_KEYS},
                   "exact_first_hits": int(p["s_i"].get("exact_first_hits", 0)),
                   "exact_mirror_hits": int(p["s_i"].get("exact_mirror_hits", 0)),
                   "mirror_newton_cpu_s": _median([q["s_i"].get("query_newton_cpu_s", 0.0)
                                            for q in ps]),
                   "samples_gathered": p["samples_gathered"], **_errors(p)}
        images[k] = p["img_i"]
        images[k + "_traced"] = p["traced_mask"]
    rows["exact"]["object_speedup"] = rows["exact"]["total_speedup"] = 1.0
    rows["exact"]["query_own_cpu_s"] = rows["exact"]["query_own_fraction"] = None  # no query
    rows["_images"] = images
    return rows


# --------------------------------------------------------------------------- the run
class _Log:
    """Step lines on stderr with elapsed time."""

    def __init__(self, total, quiet=False):
        self.t0, self.i, self.total, self.quiet = time.perf_counter(), 0, total, quiet

    def __call__(self, msg, step=True):
        self.i += step
        if not self.quiet:
            el = time.perf_counter() - self.t0
            print(f"[{self.i:3d}/{self.total}] {el / 60:5.1f} min  {msg}", file=sys.stderr,
                  flush=True)


def _table_configs(cfg, mirror=False):
    return {"interp": paper(angle_deg=None),
            "interp_angle": paper(angle_deg=cfg.angle),
            "interp_tol": QueryOptions(),
            **({"interp_reflect": QueryOptions(mirror_rays="reflect")} if mirror else {}),
            "raytree": paper(policy="raytree", angle_deg=None)}


def _n_steps(cfg):
    n = len(cfg.scenes) * len(cfg.views) * (2 if cfg.deeper_tree is None else 3)
    if cfg.sweeps:
        per = len(cfg.vp_depths) * len(cfg.dir_depths) * 2 + len(cfg.tolerances) * 2 \
            + len(cfg.angles) + len(cfg.distances) + len(cfg.extrapolations) \
            + len(cfg.max_errors) + len(cfg.path_max_errors) + 1
        n += per * len(cfg.sweep_scenes)
        if cfg.sweep_view in cfg.views:
            n += sum(len(_policy_points(cfg, _is_mirror(name)))
                     for name in set(cfg.scenes) - set(cfg.sweep_scenes))
    return n


def run(cfg: BenchConfig, quiet=False) -> dict:
    """Run the benchmark; writes everything into ``cfg.out`` and returns the results dict."""
    cfg.validate()
    workers = workers_default() if cfg.workers is None else max(1, int(cfg.workers))
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    tree_dir = out / "trees" if cfg.keep_trees else Path(tempfile.mkdtemp(prefix="riray_bench_"))
    tree_dir.mkdir(parents=True, exist_ok=True)
    log = _Log(_n_steps(cfg), quiet)
    t_start = time.perf_counter()
    tables, sweeps = [], []
    try:
        for name in cfg.scenes:
            scene = build(name)
            st = SceneTracer(scene)
            for view in cfg.views:
                cam = scene.camera(view)
                params = cfg.bake_params(cfg.viewpoint_depth, cfg.direction_depth, cfg.tolerance)
                tree, brec = bake_view(st, scene, cam, cfg.size, params, workers, tree_dir)
                log(f"{name}/{view}: baked in {brec['bake_s']:.1f} s, "
                    f"{brec['cache_bytes'] / 1e6:.2f} MB")
                mirror = scene.object.material.kind == "mirror"
                configs = {k: (tree, opt, cfg.repeats)
                           for k, opt in _table_configs(cfg, mirror).items()}
                deeper = None
                if cfg.deeper_tree is not None:
                    deeper = _bake_deeper(cfg, name, st, scene, cam, workers, tree_dir, log)
                    configs["deeper"] = (deeper[0], QueryOptions(), cfg.repeats)
                    # the default rules without the tolerance: what they trace or answer beyond
                    # it is what no render-time rule on this tree can avoid tracing (the floor)
                    configs["deeper_rules"] = (deeper[0], QueryOptions(max_error_deg=None), 1)
                    if mirror:
                        configs["deeper_reflect"] = (deeper[0], QueryOptions(mirror_rays="reflect"),
                                                     cfg.repeats)
                points = []
                if cfg.sweeps and view == cfg.sweep_view and name not in cfg.sweep_scenes:
                    # the policy curves of every scene's Pareto plot, on the table tree (the
                    # swept scenes get theirs with their sweeps)
                    points = [(tree, brec, *pt) for pt in _policy_points(cfg, mirror)]
                    configs.update(_point_configs(cfg, points))
                rows = measure_configs(st, cam, cfg.size, configs, workers)
                images = rows.pop("_images")
                if cfg.images:
                    _save_images(out / "images", f"{name}_{view}", images)
                for kind in (k for k in ROWS if k in rows and not k.startswith("deeper")):
                    tables.append({"scene": name, "view": view, "row": kind,
                                   "label": ROW_LABELS[kind].format(angle=cfg.angle),
                                   **_strip(rows[kind]), **_bake_cols(brec)})
                r = rows["interp_angle"]
                log(f"{name}/{view}: traced {r['rays_traced']}/{r['object_rays']}, object-only "
                    f"{rows['exact']['object_cpu_s']:.2f} -> {r['object_cpu_s']:.2f} s")
                if deeper is not None:
                    tables += [_deeper_row(cfg, name, cam, rows[k], deeper[1], log, k)
                               for k in ("deeper", "deeper_reflect", "deeper_rules") if k in rows]
                    _drop_tree(*deeper, cfg)
                sweeps += _point_rows(cfg, name, points, rows, log)
                _drop_tree(tree, brec, cfg)
        if cfg.sweeps:
            for name in cfg.sweep_scenes:
                sweeps += _sweep_scene(cfg, name, workers, tree_dir, log)
    finally:
        if not cfg.keep_trees:
            for p in tree_dir.glob("*.rit"):
                p.unlink()
            tree_dir.rmdir()
    amort = amortization(tables)
    result = {"machine": machine(), "command": command_line(cfg), "workers": workers,
              "config": {k: (list(v) if isinstance(v, tuple) else v)
                         for k, v in asdict(cfg).items()},
              "elapsed_s": time.perf_counter() - t_start,
              "tables": tables, "sweeps": sweeps, "amortization": amort}
    written = write_outputs(result, out, cfg.plots)
    result["written"] = [str(p) for p in written]
    return result


def _bake_deeper(cfg, name, st, scene, cam, workers, tree_dir, log) -> tuple:
    """The view's tree baked at ``cfg.deeper_tree``'s depths: (tree, bake record)."""
    vp, dd, *rest = cfg.deeper_tree
    tree, brec = bake_view(st, scene, cam, cfg.size,
                           cfg.bake_params(vp, dd, cfg.tolerance, *rest), workers, tree_dir)
    log(f"{name}/{cam.name}: deeper tree baked in {brec['bake_s']:.1f} s, "
        f"{brec['cache_bytes'] / 1e6:.2f} MB")
    return tree, brec


def _deeper_row(cfg, name, cam, r, brec, log, kind="deeper") -> dict:
    """A row on the deeper tree ("deeper": the default options; "deeper_reflect": mirror rays
    from the interpolated normal), measured in the view's batch against its own interleaved exact halves (its
    speed-up is of the same passes)."""
    vp, dd, vr, *fm = cfg.deeper_tree
    log(f"{name}/{cam.name}: {kind} traced {r['rays_traced']}/{r['object_rays']}, "
        f"object-only {r['exact_object_cpu_s']:.2f} -> {r['object_cpu_s']:.2f} s", step=False)
    return {"scene": name, "view": cam.name, "row": kind,
            "label": ROW_LABELS[kind].format(vp=vp, dd=dd, vr=vr, fm=f" where >= {fm[0]} rays "
                                             "are traced" if fm and fm[0] else ""),
            **_strip(r), **_bake_cols(brec)}


def _bake_cols(brec):
    return {k: brec[k] for k in ("viewpoint_depth", "direction_depth", "viewpoint_refine",
                                 "tolerance", "bake_s",
                                 "bake_cpu_s", "cache_bytes", "tree_samples", "bake_rays")}


def _strip(row):
    return {k: v for k, v in row.items() if not k.endswith("_all")}


def _drop_tree(tree, brec, cfg):
    del tree
    if not cfg.keep_trees:
        Path(brec["tree_path"]).unlink(missing_ok=True)


# The sweeps of the policy points (``_policy_points``), which the Pareto judgement compares.
POLICY_SWEEPS = ("angle", "max_error", "reflect", "path", "raytree")


def _point_configs(cfg, points) -> dict:
    """measure_configs' entries of sweep ``points`` [(tree, bake record, sweep, key, options)]:
    cfg.sweep_repeats passes each, policy points at least cfg.pareto_repeats."""
    return {f"point{i}": (pt[0], pt[4], max(cfg.sweep_repeats, cfg.pareto_repeats)
                          if pt[2] in POLICY_SWEEPS else cfg.sweep_repeats)
            for i, pt in enumerate(points)}


def _point_rows(cfg, name, points, rows, log) -> list:
    """Sweep rows of ``points`` from measure_configs' ``rows`` (each point against its own
    interleaved exact halves)."""
    out = []
    for i, (_, brec, sweep, key, opt) in enumerate(points):
        x = _strip(rows[f"point{i}"])
        log(f"{name}/{cfg.sweep_view} {sweep} {key}: traced {x['traced_fraction']:.1%}, "
            f"err {_err3(x)} deg, PSNR {x['psnr_db']:.1f} dB")
        out.append({"scene": name, "view": cfg.sweep_view, "sweep": sweep, **_bake_cols(brec),
                    "policy": opt.policy, "angle": opt.angle_deg, "distance": opt.distance,
                    "extrapolation": opt.extrapolation, "max_error": opt.max_error_deg,
                    "path_identity": opt.path_identity, "mirror_rays": opt.mirror_rays, **x})
    return out


def _is_mirror(name) -> bool:
    return build(name).object.material.kind == "mirror"


# The render-time policies compared on every scene's Pareto plot (one tree, no re-bake).
def _policy_points(cfg, mirror=False) -> list:
    """(sweep, key, options): the angle threshold, the baked-error tolerance (alone, with
    path identity and, on a mirror, with mirror rays from the interpolated normal instead of
    exact mirror hits: ``--mirror-rays reflect``) and the raytree policy."""
    reflect = [("reflect", f"{t}", QueryOptions(angle_deg=None, max_error_deg=t,
                                                mirror_rays="reflect"))
               for t in cfg.max_errors] if mirror else []
    return ([("angle", f"{a}", paper(angle_deg=a)) for a in cfg.angles]
            + [("max_error", f"{t}", QueryOptions(angle_deg=None, max_error_deg=t))
               for t in cfg.max_errors] + reflect
            + [("path", f"{t}", QueryOptions(angle_deg=None, max_error_deg=t,
                                             path_identity=True)) for t in cfg.path_max_errors]
            + [("raytree", "Bala et al.", paper(policy="raytree", angle_deg=None))])


def _sweep_scene(cfg, name, workers, tree_dir, log) -> list:
    """Every sweep of scene ``name``: the depth and tolerance trees are baked first, then all
    points are measured in one batch."""
    scene = build(name)
    st = SceneTracer(scene)
    cam = scene.camera(cfg.sweep_view)
    default = paper(angle_deg=cfg.angle)
    trees = {}

    def baked(vp, dd, tol):
        if (vp, dd, tol) in trees:
            log(f"{name}/{cfg.sweep_view} vp {vp} dir {dd} tol {tol:g}: baked already")
        else:
            trees[vp, dd, tol] = bake_view(st, scene, cam, cfg.size,
                                           cfg.bake_params(vp, dd, tol), workers, tree_dir)
            brec = trees[vp, dd, tol][1]
            log(f"{name}/{cfg.sweep_view} bake vp {vp} dir {dd} tol {tol:g}: "
                f"{brec['bake_s']:.1f} s, {brec['cache_bytes'] / 1e6:.2f} MB")
        return trees[vp, dd, tol]

    points = [(*baked(vp, dd, cfg.tolerance), "depth", f"vp {vp} dir {dd}", default)
              for vp in cfg.vp_depths for dd in cfg.dir_depths]
    points += [(*baked(cfg.viewpoint_depth, cfg.direction_depth, tol), "tolerance",
                f"tol {tol:g}", default) for tol in cfg.tolerances]
    base = (cfg.viewpoint_depth, cfg.direction_depth, cfg.tolerance)
    if base not in trees:
        baked(*base)
    tree, brec = trees[base]
    points += [(tree, brec, "distance", f"{dist}", paper(angle_deg=None, distance=dist))
               for dist in cfg.distances]
    points += [(tree, brec, "extrapolation", f"{ex}", paper(angle_deg=cfg.angle, extrapolation=ex))
               for ex in cfg.extrapolations]
    points += [(tree, brec, *pt) for pt in _policy_points(cfg)]
    rows = measure_configs(st, cam, cfg.size, _point_configs(cfg, points), workers)
    out = _point_rows(cfg, name, points, rows, log)
    for t in trees.values():
        _drop_tree(*t, cfg)
    return out


def amortization(tables) -> list:
    """Per table view and interpolated row ("interp": no angle threshold, "interp_angle": with
    it, "interp_tol": the default tolerance, "deeper": it on the deeper tree): bake CPU
    seconds, per-frame total CPU seconds exact and interpolated, and the break-even frame count
    N* = bake / (exact - interpolated), the smallest N for which bake + N interpolated frames
    cost no more than N exact frames (None where interpolation saves nothing per frame: it
    never pays)."""
    out = []
    by = {}
    for r in tables:
        by.setdefault((r["scene"], r["view"]), {})[r["row"]] = r
    for (scene, view), rows in by.items():
        ex = rows["exact"]
        for kind in ("interp", "interp_angle", "interp_tol", "deeper"):
            if kind not in rows:
                continue
            it = rows[kind]
            saved = ex["total_cpu_s"] - it["total_cpu_s"]
            saved_o = ex["object_cpu_s"] - it["object_cpu_s"]
            out.append({"scene": scene, "view": view, "row": kind, "bake_cpu_s": it["bake_cpu_s"],
                        "bake_s": it["bake_s"], "exact_frame_cpu_s": ex["total_cpu_s"],
                        "interp_frame_cpu_s": it["total_cpu_s"],
                        "break_even_frames": (math.ceil(it["bake_cpu_s"] / saved)
                                              if saved > 0 else None),
                        "break_even_frames_object_only": (math.ceil(it["bake_cpu_s"] / saved_o)
                                                          if saved_o > 0 else None)})
    return out


def replot(out) -> list:
    """Re-make the derived outputs (amortization, Markdown, CSV, plots) of ``out`` from its
    results.json, measuring nothing."""
    out = Path(out)
    try:
        result = json.loads((out / "results.json").read_text(), parse_constant=float)
    except (OSError, ValueError) as e:
        raise ValueError(f"{out / 'results.json'}: cannot read a riray bench result ({e})") from None
    for r in (*result["tables"], *result["sweeps"]):
        for k, v in r.items():
            if v in ("inf", "-inf"):
                r[k] = float(v)
    result["amortization"] = amortization(result["tables"])
    written = write_outputs(result, out, True)
    result["written"] = [str(p) for p in written]
    return result


def command_line(cfg: BenchConfig) -> str:
    """The ``riray bench`` command that reproduces ``cfg``."""
    ref = BenchConfig(**QUICK) if cfg.quick else BenchConfig()
    parts = ["riray bench"] + (["--quick"] if cfg.quick else [])
    flags = {"scenes": "--scenes", "views": "--views", "size": "--size", "repeats": "--repeats",
             "viewpoint_depth": "--viewpoint-depth", "direction_depth": "--direction-depth",
             "tolerance": "--tolerance", "angle": "--angle", "sweep_scenes": "--sweep-scenes",
             "sweep_repeats": "--sweep-repeats", "pareto_repeats": "--pareto-repeats",
             "workers": "--workers"}
    for k, flag in flags.items():
        v = getattr(cfg, k)
        if v != getattr(ref, k):
            parts.append(f"{flag} {' '.join(map(str, v)) if isinstance(v, tuple) else v}")
    if not cfg.sweeps:
        parts.append("--no-sweeps")
    parts.append(f"--out {cfg.out}")
    return " ".join(parts)


# --------------------------------------------------------------------------- output
TABLE_CSV = ("scene", "view", "row", "label", "rays_traced", "object_rays", "traced_fraction",
             "beyond_fraction",
             "object_cpu_s", "total_cpu_s", "object_speedup", "total_speedup",
             "query_own_cpu_s", "query_own_fraction", "pairs",
             "newton_iters", "fallback_pairs", "exact_first_hits", "exact_mirror_hits",
             "mirror_newton_cpu_s", "samples_gathered",
             "angle_mean_deg", "angle_p99_deg", "angle_max_deg", "psnr_db", "max_pixel_diff",
             "hit_disagreements", "null_disagreements", "viewpoint_depth", "direction_depth",
             "viewpoint_refine",
             "tolerance", "bake_s",
             "bake_cpu_s", "cache_bytes", "tree_samples")
SWEEP_CSV = ("scene", "view", "sweep", "viewpoint_depth", "direction_depth", "tolerance",
             "policy", "angle", "distance", "extrapolation", "max_error", "path_identity",
             "mirror_rays",
             "bake_s", "bake_cpu_s",
             "cache_bytes", "tree_samples", "bake_rays", "rays_traced", "object_rays",
             "traced_fraction", "object_cpu_s", "total_cpu_s", "exact_object_cpu_s",
             "exact_total_cpu_s", "object_speedup", "total_speedup", "pairs", "newton_iters",
             "samples_gathered", "angle_mean_deg", "angle_p99_deg", "angle_max_deg", "psnr_db",
             "max_pixel_diff")


def _write_csv(path, rows, cols):
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for r in rows:
            w.writerow(["" if r.get(c) is None else r.get(c) for c in cols])


def _json_safe(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None if math.isnan(x) else ("inf" if x > 0 else "-inf")
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, np.generic):
        return _json_safe(x.item())
    return x


def write_outputs(result, out: Path, plots=True) -> list:
    written = []
    p = out / "tables.csv"
    _write_csv(p, result["tables"], TABLE_CSV)
    written.append(p)
    if result["sweeps"]:
        p = out / "sweeps.csv"
        _write_csv(p, result["sweeps"], SWEEP_CSV)
        written.append(p)
    result["pareto"] = dominance(result["sweeps"])
    p = out / "results.json"
    p.write_text(json.dumps(_json_safe(result), indent=1) + "\n")
    written.append(p)
    p = out / "tables.md"
    p.write_text(tables_markdown(result) + "\n")
    written.append(p)
    if result["sweeps"]:
        p = out / "sweeps.md"
        p.write_text(sweeps_markdown(result["sweeps"]) + "\n\n"
                     + dominance_markdown(result["sweeps"]) + "\n")
        written.append(p)
    if plots:
        try:
            from . import plots as plotting
            written += plotting.plot_all(result, out)
        except ImportError as e:     # matplotlib missing: the numbers are written regardless
            print(f"riray bench: plots skipped: {e}", file=sys.stderr)
    return written


def _fmt(v, f="{:.2f}"):
    if v is None:
        return "-"
    if isinstance(v, float) and not math.isfinite(v):
        return "inf"
    return f.format(v)


def _err3(r) -> str:
    if r["angle_mean_deg"] is None:
        return "- (none interpolated)"
    return f"{r['angle_mean_deg']:.3f} / {r['angle_p99_deg']:.2f} / {r['angle_max_deg']:.1f}"


def tables_markdown(result) -> str:
    """The paper-style tables, one per scene (rows: view x method), and the break-even table."""
    lines = []
    tables = result["tables"]
    for scene in dict.fromkeys(r["scene"] for r in tables):
        rows = [r for r in tables if r["scene"] == scene]
        r0 = rows[0]
        lines += [f"**{scene}** (tree: viewpoint depth {r0['viewpoint_depth']}, direction depth "
                  f"{r0['direction_depth']}, tolerance {r0['tolerance']:g} deg)", "",
                  "| view | method | rays traced | traced % of object | traced or beyond "
                  f"{DEFAULT_MAX_ERROR_DEG:g} deg, % of object | object-only CPU s "
                  "| total CPU s | object-only speed-up | query's own work, % of exact "
                  "object-only | pairs | Newton it | samples gathered | mean / p99 / max err deg "
                  "| wrong hit / null | PSNR dB |",
                  "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in rows:
            err = "-" if r["row"] == "exact" else _err3(r)
            own = "-" if r["row"] == "exact" else f"{100 * r['query_own_fraction']:.1f}"
            lines.append(
                f"| {r['view']} | {r['label']} | {r['rays_traced']:,} of {r['object_rays']:,} | "
                f"{100 * r['traced_fraction']:.1f} | "
                f"{100 * (r['traced_fraction'] + r['beyond_fraction']):.1f} | "
                f"{r['object_cpu_s']:.2f} | "
                f"{r['total_cpu_s']:.2f} | {r['object_speedup']:.2f}x | {own} | {r['pairs']:,} | "
                f"{r['newton_iters']:,} | {r['samples_gathered']:,} | {err} | "
                f"{r['hit_disagreements']} / {r['null_disagreements']} | "
                f"{_fmt(r['psnr_db'], '{:.1f}')} |")
        lines.append("")
    lines += ["**Bake and break-even** (CPU seconds per frame; N* = frames after which bake + N "
              "interpolated frames cost less than N exact ones)", "",
              "| scene | view | bake s (wall) | bake CPU s | cache MB | exact frame | interpolated "
              "frame, no threshold | N* | interpolated frame, angle threshold | N* | "
              "interpolated frame, default tolerance | N* | deeper tree: bake CPU s | cache MB "
              "| frame | N* |",
              "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    cache = {(r["scene"], r["view"], r["row"]): r["cache_bytes"] for r in tables}
    am = {(a["scene"], a["view"], a["row"]): a for a in result["amortization"]}
    for scene, view in dict.fromkeys((a["scene"], a["view"]) for a in result["amortization"]):
        a, b, c = (am[(scene, view, k)] for k in ("interp", "interp_angle", "interp_tol"))

        def be(x):
            return "never" if x["break_even_frames"] is None else f"{x['break_even_frames']:,}"
        t = am.get((scene, view, "deeper"))
        deep = ("- | - | - | -" if t is None else
                f"{t['bake_cpu_s']:.1f} | {cache[(scene, view, 'deeper')] / 1e6:.2f} | "
                f"{t['interp_frame_cpu_s']:.2f} | {be(t)}")
        lines.append(f"| {scene} | {view} | {a['bake_s']:.1f} | {a['bake_cpu_s']:.1f} | "
                     f"{cache[(scene, view, 'exact')] / 1e6:.2f} | {a['exact_frame_cpu_s']:.2f} | "
                     f"{a['interp_frame_cpu_s']:.2f} | {be(a)} | {b['interp_frame_cpu_s']:.2f} | "
                     f"{be(b)} | {c['interp_frame_cpu_s']:.2f} | {be(c)} | {deep} |")
    return "\n".join(lines)


def sweeps_markdown(rows) -> str:
    lines = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        lines += [f"**{scene}** ({rows[0]['view']} view)", "",
                  "| sweep | vp | dir | tol | angle | dist | extrap | max err | bake s | "
                  "cache MB | traced % | object-only s (exact) | total s (exact) | mean / p99 / "
                  "max err deg | PSNR dB | max diff |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in (r for r in rows if r["scene"] == scene):
            lines.append(
                f"| {r['sweep']} | {r['viewpoint_depth']} | {r['direction_depth']} | "
                f"{r['tolerance']:g} | {_fmt(r['angle'], '{:g}')} | {_fmt(r['distance'], '{:g}')} | "
                f"{_fmt(r['extrapolation'], '{:g}')} | {_fmt(r.get('max_error'), '{:g}')}"
                f"{' path' if r.get('path_identity') else ''}"
                f"{' reflect' if r.get('mirror_rays') == 'reflect' else ''} | "
                f"{r['bake_s']:.1f} | "
                f"{r['cache_bytes'] / 1e6:.2f} | {100 * r['traced_fraction']:.1f} | "
                f"{r['object_cpu_s']:.2f} ({r['exact_object_cpu_s']:.2f}) | "
                f"{r['total_cpu_s']:.2f} ({r['exact_total_cpu_s']:.2f}) | "
                f"{_err3(r)} | {_fmt(r['psnr_db'], '{:.1f}')} | {r['max_pixel_diff']:.2f} |")
        lines.append("")
    return "\n".join(lines)


def _save_images(folder, stem, images):
    from ..render.image import write_png, write_png_u8
    folder.mkdir(parents=True, exist_ok=True)
    for k, img in images.items():
        if k.endswith("_traced"):
            write_png_u8(folder / f"{stem}_{k}.png", np.where(img, 255, 0).astype(np.uint8))
        else:
            write_png(folder / f"{stem}_{k}.png", img)


def config_from_args(quick=False, **overrides) -> BenchConfig:
    """A BenchConfig: the full preset (or the --quick one), then every override that is not
    None."""
    base = BenchConfig(**QUICK) if quick else BenchConfig()
    return replace(base, **{k: (tuple(v) if isinstance(v, list) else v)
                            for k, v in overrides.items() if v is not None})

