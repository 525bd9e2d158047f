"""``riray bench``'s sweeps: the points (tree, bake record, sweep, key, QueryOptions) of the
depth, tolerance and render-time option sweeps and of the policy curves, their entries for
:func:`measure_configs` and their rows; a swept scene baked and measured in one batch."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..trace.scene_tracer import SceneTracer
from ..ritree.query import QueryOptions
from ..scene.samples import build
from .ritree_config import BenchConfig, paper
from .ritree_measure import bake_view, measure_configs
from .ritree_output import err3


@dataclass
class BenchRun:
    """What every step of one run shares: its configuration, worker processes, the folder the
    trees are saved into and the step log (``log(msg, step=True)``)."""

    cfg: BenchConfig
    workers: int
    tree_dir: Path
    log: Callable


def bake_cols(brec) -> dict:
    """The bake record's columns of a table or sweep row."""
    return {k: brec[k] for k in ("viewpoint_depth", "direction_depth", "viewpoint_refine",
                                 "tolerance", "bake_s",
                                 "bake_cpu_s", "cache_bytes", "tree_samples", "bake_rays")}


def strip_all(row) -> dict:
    """``row`` without its per-pass lists (the ``*_all`` keys)."""
    return {k: v for k, v in row.items() if not k.endswith("_all")}


def drop_tree(tree, brec, cfg) -> None:
    """Forget a baked tree; its .rit file too unless the run keeps trees."""
    del tree
    if not cfg.keep_trees:
        Path(brec["tree_path"]).unlink(missing_ok=True)


# The sweeps of the policy points (``policy_points``), which the Pareto judgement compares.
POLICY_SWEEPS = ("angle", "max_error", "reflect", "path", "raytree")


def point_configs(cfg, points) -> dict:
    """measure_configs' entries of sweep ``points`` [(tree, bake record, sweep, key, options)]:
    cfg.sweep_repeats passes each, policy points at least cfg.pareto_repeats."""
    return {f"point{i}": (pt[0], pt[4], max(cfg.sweep_repeats, cfg.pareto_repeats)
                          if pt[2] in POLICY_SWEEPS else cfg.sweep_repeats)
            for i, pt in enumerate(points)}


def point_rows(cfg, name, points, rows, log) -> list:
    """Sweep rows of ``points`` from measure_configs' ``rows`` (each point against its own
    interleaved exact halves)."""
    out = []
    for i, (_, brec, sweep, key, opt) in enumerate(points):
        x = strip_all(rows[f"point{i}"])
        log(f"{name}/{cfg.sweep_view} {sweep} {key}: traced {x['traced_fraction']:.1%}, "
            f"err {err3(x)} deg, PSNR {x['psnr_db']:.1f} dB")
        out.append({"scene": name, "view": cfg.sweep_view, "sweep": sweep, **bake_cols(brec),
                    "policy": opt.policy, "angle": opt.angle_deg, "distance": opt.distance,
                    "extrapolation": opt.extrapolation, "max_error": opt.max_error_deg,
                    "path_identity": opt.path_identity, "mirror_rays": opt.mirror_rays, **x})
    return out


def is_mirror(name) -> bool:
    """Whether sample scene ``name``'s object is a mirror."""
    return build(name).object.material.kind == "mirror"


# The render-time policies compared on every scene's Pareto plot (one tree, no re-bake).
def policy_points(cfg, mirror=False) -> list:
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


def sweep_scene(run: BenchRun, name) -> list:
    """Every sweep of scene ``name``: the depth and tolerance trees are baked first, then all
    points are measured in one batch."""
    cfg, log = run.cfg, run.log
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
                                           cfg.bake_params(vp, dd, tol), run.workers,
                                           run.tree_dir)
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
    points += [(tree, brec, *pt) for pt in policy_points(cfg)]
    rows = measure_configs(st, cam, cfg.size, point_configs(cfg, points), run.workers)
    out = point_rows(cfg, name, points, rows, log)
    for t in trees.values():
        drop_tree(*t, cfg)
    return out
