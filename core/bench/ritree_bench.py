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
runs the deeper tree's default rules without the tolerance and without solving along paths:
the object pixels they trace or answer beyond the default tolerance (or with a wrong kind of answer: hit / miss, null) are the
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
loaded back (packed samples) before rendering, as ``riray render --tree`` would
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
(``pip install 'riray[bench]'``; imported only in ritree_output, lazily) - and per-view images
(``images/``: exact, interpolated, traced masks).

Modules: ``ritree_config`` (rows, BenchConfig, presets), ``ritree_measure`` (baking a view,
the interleaved passes, the rows they give), ``ritree_sweeps`` (sweep and policy points),
``ritree_output`` (CSV, JSON, Markdown, plots, images, replot); this module runs them.
"""

from __future__ import annotations

import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

from ..parallel import workers_default
from ..trace.scene_tracer import SceneTracer
from ..ritree.query import QueryOptions
from ..scene.samples import build
from .exact_bench import machine
from .ritree_config import (QUICK, ROW_LABELS, ROWS, VIEWS, BenchConfig, command_line,
                            config_from_args, paper)
from .ritree_measure import (SAMPLES_PER_EXTRA, SAMPLES_PER_LOOKUP, TRACER_KEYS, bake_view,
                             measure_configs, measure_pass)
from .ritree_output import (SWEEP_CSV, TABLE_CSV, amortization, replot, save_images,
                            sweeps_markdown, tables_markdown, write_outputs)
from .ritree_sweeps import (POLICY_SWEEPS, BenchRun, bake_cols, drop_tree, is_mirror,
                            point_configs, point_rows, policy_points, strip_all, sweep_scene)

__all__ = ["POLICY_SWEEPS", "QUICK", "ROWS", "ROW_LABELS", "SAMPLES_PER_EXTRA",
           "SAMPLES_PER_LOOKUP", "SWEEP_CSV", "TABLE_CSV", "TRACER_KEYS", "VIEWS", "BenchConfig",
           "amortization", "bake_view", "command_line", "config_from_args", "measure_configs",
           "measure_pass", "paper", "replot", "run", "sweeps_markdown", "tables_markdown",
           "write_outputs"]


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
            n += sum(len(policy_points(cfg, is_mirror(name)))
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
    bench = BenchRun(cfg, workers, tree_dir, _Log(_n_steps(cfg), quiet))
    t_start = time.perf_counter()
    tables, sweeps = [], []
    try:
        for name in cfg.scenes:
            scene = build(name)
            st = SceneTracer(scene)
            for view in cfg.views:
                view_tables, view_sweeps = _table_view(bench, name, scene, st, view)
                tables += view_tables
                sweeps += view_sweeps
        if cfg.sweeps:
            for name in cfg.sweep_scenes:
                sweeps += sweep_scene(bench, name)
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


def _table_view(bench: BenchRun, name, scene, st, view) -> tuple:
    """The table rows of sample ``name``'s ``view`` (its tree baked, every row measured in one
    batch, with the deeper tree's rows and, on a scene that is not swept, its policy points):
    (table rows, sweep rows)."""
    cfg, log = bench.cfg, bench.log
    cam = scene.camera(view)
    params = cfg.bake_params(cfg.viewpoint_depth, cfg.direction_depth, cfg.tolerance)
    tree, brec = bake_view(st, scene, cam, cfg.size, params, bench.workers, bench.tree_dir)
    log(f"{name}/{view}: baked in {brec['bake_s']:.1f} s, {brec['cache_bytes'] / 1e6:.2f} MB")
    mirror = scene.object.material.kind == "mirror"
    configs = {k: (tree, opt, cfg.repeats) for k, opt in _table_configs(cfg, mirror).items()}
    deeper = None
    if cfg.deeper_tree is not None:
        deeper = _bake_deeper(bench, name, scene, st, cam)
        configs.update(_deeper_configs(cfg, deeper[0], mirror))
    points = []
    if cfg.sweeps and view == cfg.sweep_view and name not in cfg.sweep_scenes:
        # the policy curves of every scene's Pareto plot, on the table tree (the swept scenes
        # get theirs with their sweeps)
        points = [(tree, brec, *pt) for pt in policy_points(cfg, mirror)]
        configs.update(point_configs(cfg, points))
    rows = measure_configs(st, cam, cfg.size, configs, bench.workers)
    images = rows.pop("_images")
    if cfg.images:
        save_images(Path(cfg.out) / "images", f"{name}_{view}", images)
    tables = [{"scene": name, "view": view, "row": kind,
               "label": ROW_LABELS[kind].format(angle=cfg.angle),
               **strip_all(rows[kind]), **bake_cols(brec)}
              for kind in ROWS if kind in rows and not kind.startswith("deeper")]
    r = rows["interp_angle"]
    log(f"{name}/{view}: traced {r['rays_traced']}/{r['object_rays']}, object-only "
        f"{rows['exact']['object_cpu_s']:.2f} -> {r['object_cpu_s']:.2f} s")
    if deeper is not None:
        tables += [_deeper_row(cfg, name, cam, rows[k], deeper[1], log, k)
                   for k in ("deeper", "deeper_reflect", "deeper_rules") if k in rows]
        drop_tree(*deeper, cfg)
    sweeps = point_rows(cfg, name, points, rows, log)
    drop_tree(tree, brec, cfg)
    return tables, sweeps


def _deeper_configs(cfg, tree, mirror) -> dict:
    """measure_configs' entries on the deeper tree: the default options, and the default rules
    without the tolerance and without solving along paths (one pass): what they trace or
    answer beyond the tolerance is what no interpolation rule on this tree can avoid (the
    floor); on a mirror the default options with mirror rays from the interpolated normal."""
    configs = {"deeper": (tree, QueryOptions(), cfg.repeats),
               "deeper_rules": (tree, QueryOptions(max_error_deg=None, solve_paths=False), 1)}
    if mirror:
        configs["deeper_reflect"] = (tree, QueryOptions(mirror_rays="reflect"), cfg.repeats)
    return configs


def _bake_deeper(bench: BenchRun, name, scene, st, cam) -> tuple:
    """The view's tree baked at ``cfg.deeper_tree``'s depths: (tree, bake record)."""
    cfg = bench.cfg
    vp, dd, *rest = cfg.deeper_tree
    tree, brec = bake_view(st, scene, cam, cfg.size,
                           cfg.bake_params(vp, dd, cfg.tolerance, *rest), bench.workers,
                           bench.tree_dir)
    bench.log(f"{name}/{cam.name}: deeper tree baked in {brec['bake_s']:.1f} s, "
              f"{brec['cache_bytes'] / 1e6:.2f} MB")
    return tree, brec


def _deeper_row(cfg, name, cam, r, brec, log, kind="deeper") -> dict:
    """A row on the deeper tree ("deeper": the default options; "deeper_reflect": mirror rays
    from the interpolated normal), measured in the view's batch against its own interleaved
    exact halves (its speed-up is of the same passes)."""
    vp, dd, vr, *fm = cfg.deeper_tree
    log(f"{name}/{cam.name}: {kind} traced {r['rays_traced']}/{r['object_rays']}, "
        f"object-only {r['exact_object_cpu_s']:.2f} -> {r['object_cpu_s']:.2f} s", step=False)
    return {"scene": name, "view": cam.name, "row": kind,
            "label": ROW_LABELS[kind].format(vp=vp, dd=dd, vr=vr, fm=f" where >= {fm[0]} rays "
                                             "are traced" if fm and fm[0] else ""),
            **strip_all(r), **bake_cols(brec)}
