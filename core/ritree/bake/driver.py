"""The bake's passes over viewpoint levels: the uniform viewpoint trees, the refinement passes
that split the viewpoint cells where the cameras' rays are still traced or the measured
viewpoint-level error is too large, the viewpoint cells' measurement and the tree."""

from __future__ import annotations

import numpy as np

from ..tree import UNVERIFIED, RITree
from ..verify import viewpoint_errors
from .directions import DirectionPass
from .progress import Progress
from .shards import ShardedPass
from .slots import add_trees, add_viewpoints
from .state import BakeConfig, BakeState
from .tracing import Tracer

# Rays per query call when the bake answers the region's camera rays: bounds the query's
# per-ray arrays (hundreds of bytes a ray) for animations of many cameras.
QUERY_CHUNK = 1 << 20
# The angle threshold (degrees) of the refinement rule (refine_rule): the paper's value.
REFINE_ANGLE_DEG = 20.0
# The baked-error tolerance (degrees) under which finest_rule counts traced rays: the
# render-time default's value when the rule was made (54f061c, 2026-12-04).
FINEST_TOLERANCE_DEG = 2.0


def refine_rule():
    """The query rule whose traced rays split viewpoint cells in a refinement pass: the paper's,
    with its 20-degree angle threshold, null rays traced (since 527fbe9; answered null before),
    not the render-time default, which may change."""
    from ..query import QueryOptions
    return QueryOptions(angle_deg=REFINE_ANGLE_DEG, max_error_deg=None, null_interp=False,
                        many_classes="trace", solve_paths=False, fresnel_tree=False)


def finest_rule():
    """The query rule whose traced rays choose the cells of the finest viewpoint level
    (``finest_min_traced``): the baked-error tolerance at FINEST_TOLERANCE_DEG with exact mirror
    hits, every other rule off, pinned here (not the render-time default, which may change)."""
    from ..query import QueryOptions
    return QueryOptions(policy="ri", extrapolation=None, angle_deg=None, distance=None,
                        null_interp=True, max_error_deg=FINEST_TOLERANCE_DEG,
                        fallback_angle_deg=REFINE_ANGLE_DEG, path_identity=False,
                        one_path=False, mirror_rays="newton", many_classes="trace",
                        solve_paths=False, fresnel_tree=False)


class Baker:
    """One bake: its configuration ``cfg``, its state (``state``: forests and samples, grown
    pass by pass) and ``progress``; direction trees are baked locally or, with a cluster, as
    shards (``directions``)."""

    def __init__(self, cfg: BakeConfig, progress: Progress):
        self.cfg, self.progress = cfg, progress
        self.state = BakeState.empty(cfg)
        self.directions = ShardedPass(cfg, self.state, progress) if cfg.cluster is not None \
            else DirectionPass(cfg, self.state, Tracer(cfg, self.state, progress), progress)

    @property
    def vpf(self):
        """The viewpoint forest (corners = viewpoint ids)."""
        return self.state.vpf

    def start(self, region):
        """Uniform viewpoint trees to depth D; corner viewpoints of the region's cells."""
        vpf = self.state.vpf
        nodes = vpf.add_roots(np.arange(6))
        for _ in range(self.cfg.D):
            nodes = vpf.split(nodes).ravel()
        if region is not None and region.cells is not None:
            face = vpf.tree_of_nodes()[nodes]
            nodes = nodes[region.cells[face, vpf.ix[nodes], vpf.iy[nodes]]]
        vps = add_viewpoints(self.cfg, self.state, nodes)
        self.directions.bake(add_trees(self.cfg, self.state, region, self.cfg.D, vps))

    def refine(self, region) -> bool:
        """One refinement pass: split the viewpoint cells where the region's rays are traced
        for lack of interpolants or by the thresholds, or where the measured viewpoint-level
        error exceeds ``viewpoint_tolerance_deg``; False when nothing is left to split. With
        ``finest_min_traced`` > 0, the pass that makes the finest level (and any later one)
        splits only the cells through which at least that many of the region's rays are traced
        under ``finest_rule``: the last level goes where tracing costs most."""
        from ..locate import entry_points
        from ..query import WHY_THRESHOLD, WHY_USABLE, TreeQuery
        vpf, p, Dmax = self.state.vpf, self.cfg.params, self.cfg.Dmax
        tree = self.tree()
        o, d, tmax = region.rays
        finest = int(vpf.level[vpf.child < 0].max()) + 1 >= Dmax
        if finest and p.finest_min_traced > 0:
            self.measure(region, tree)
            leaf = self._traced_cells(tree, o, d, tmax)
        else:
            ans, why = _answers(TreeQuery(tree, self.cfg.st, refine_rule()), o, d, tmax)
            bad = (why == WHY_USABLE) | (why == WHY_THRESHOLD)
            t_in, face, x, y, _ = entry_points(tree, o[bad], d[bad])
            leaf, _, _ = vpf.locate(face, x, y)
            err = self.measure(region, tree)
            leaf = np.union1d(leaf[leaf >= 0], np.flatnonzero(err > p.viewpoint_tolerance_deg))
        leaf = leaf[vpf.level[leaf] < Dmax]
        if len(leaf) == 0:
            return False
        # level by level: a new viewpoint's direction rectangles are those the rays through
        # the new cells it is a corner of need, the rectangles of their level (the finest pass
        # may split cells of several levels, and a finer level's rectangles are narrower; a
        # later, finer cell that reuses the viewpoint needs no more: for one viewpoint a
        # coarser level's rectangle holds a finer one's)
        levels = vpf.level[leaf]
        trees = []
        for lv in np.unique(levels):
            kids = vpf.split(leaf[levels == lv]).ravel()
            vps = add_viewpoints(self.cfg, self.state, kids)
            if len(vps):
                trees.append(add_trees(self.cfg, self.state, region, int(lv) + 1, vps))
        if trees:
            self.directions.bake(np.concatenate(trees))
        return True

    def _traced_cells(self, tree, o, d, tmax) -> np.ndarray:
        """Viewpoint leaves through which at least ``finest_min_traced`` of the rays (o, d,
        tmax) are traced under ``finest_rule``, on ``tree``, the tree as it is now (its
        viewpoint errors just measured)."""
        from ..locate import locate
        from ..query import TRACED, TreeQuery
        ans, _ = _answers(TreeQuery(tree, self.cfg.st, finest_rule()), o, d, tmax)
        tr = ans == TRACED
        loc, _ = locate(tree, o[tr], d[tr], tmax[tr])
        count = np.bincount(loc.vnode, minlength=len(self.state.vpf.child))
        return np.flatnonzero(count >= self.cfg.params.finest_min_traced)

    def measure(self, region, tree=None) -> np.ndarray:
        """Viewpoint-level errors of the current tree on the region's cameras (verify.py),
        kept for the tree; cells above the tolerance are flagged UNVERIFIED (a later pass that
        splits them measures their children). Returns the errors (degrees; NaN: not
        measured)."""
        cams = region.cameras if region is not None else None
        tree = tree or self.tree()
        err, flags = viewpoint_errors(tree, self.cfg.st, cams or [])
        flags[err > self.cfg.params.viewpoint_tolerance_deg] |= UNVERIFIED
        # kept for the bake and given to ``tree``, which a pass may query with them (its
        # decoded samples and locators are not built twice)
        self.state.vp_err, self.state.vp_flags = tree.vp_err, tree.vp_flags = err, flags
        return err

    def tree(self) -> RITree:
        """The tree as baked so far (its samples shared with the bake's)."""
        cfg, s = self.cfg, self.state
        s.grow_records()                                        # grow to the forest
        kv = len(s.vpf.child)
        vp_err = np.full(kv, np.nan, np.float32)
        vp_flags = np.zeros(kv, np.uint8)
        if s.vp_err is not None:
            vp_err[:len(s.vp_err)] = s.vp_err
            vp_flags[:len(s.vp_flags)] = s.vp_flags
        return RITree(params=cfg.params, box_lo=cfg.box_lo, box_hi=cfg.box_hi,
                      diag=cfg.diag, class_of=cfg.class_of.astype(np.int64),
                      vp_forest=s.vpf, vp_pos=s.vp_pos, vp_face=s.vp_face,
                      dir_forest=s.dirf, dir_rect=s.rect, samples=s.samples,
                      **s.ex, dir_err=s.dir_err.copy(), dir_flags=s.dir_flags.copy(),
                      vp_err=vp_err, vp_flags=vp_flags,
                      meta={"rays_traced": int(s.stats.rays),
                            "viewpoints": int(len(s.vp_pos)),
                            "direction_trees": int(np.sum(s.dirf.root >= 0)),
                            "samples": int(len(s.samples)),
                            "extra_cells": int(len(s.ex["ex_node"]))})


def _answers(query, o, d, tmax):
    """(answer, why) codes of rays (o, d, tmax) from ``query`` (a TreeQuery), QUERY_CHUNK rays
    a call."""
    parts = [query(o[a:a + QUERY_CHUNK], d[a:a + QUERY_CHUNK], tmax[a:a + QUERY_CHUNK])[1:3]
             for a in range(0, max(len(o), 1), QUERY_CHUNK)]
    return tuple(np.concatenate([p[k] for p in parts]) for k in (0, 1))
