"""Adaptive direction trees (paper 3.3): each level traces the midpoints of all open cells of
a pass's trees at once, interpolates them from the cell corners with the renderer's own rules
(``interp.cell_weights``, usable = same class as the traced midpoint and not null), and splits
the cells where the corners disagree in class or null state or where the interpolated output
ray, hit point or normal misses the traced one by more than the tolerance. New corner samples
are keyed on the finest grid, so cells share them. Then the extra samples of the new leaves
(``extras``)."""

from __future__ import annotations

import numpy as np

from ..dircube import CUBE, N_SLOTS
from ..interp import FAIL, UNIT_CORNERS, angle_between, cell_weights
from ..quadtree import CORNERS
from ..tree import BOUNDARY, PATH_CHANGE, UNVERIFIED, Samples
from .extras import ExtraSearch, extra_samples
from .slots import rects_see_object
from .state import classes, take


class DirectionPass:
    """Bakes direction trees into ``state`` (a BakeState) with ``tracer``, reporting to
    ``progress``: all trees of a pass level by level, then their extra samples."""

    def __init__(self, cfg, state, tracer, progress):
        self.cfg, self.state, self.tracer, self.progress = cfg, state, tracer, progress

    def bake(self, trees) -> None:
        """Bake the direction trees ``trees`` (ids of trees with no nodes yet)."""
        s, Gd = self.state, self.cfg.Gd
        self.progress.start_pass(len(trees))
        s.stages.count[:] = 0
        nodes = s.dirf.add_roots(trees)
        s.dirf.corner[nodes] = self._ensure(np.repeat(trees, 4),
                                            np.tile(CORNERS * (Gd - 1), (len(trees), 1)),
                                            s.stages.corners(-1)).reshape(-1, 4)
        # levels 0..M-1 split where the test fails; leaves at the maximum depth M are tested too
        # (their error recorded, UNVERIFIED where they would split), not split
        for level in range(self.cfg.M + 1):
            if len(nodes) == 0:
                break
            nodes = self._level(level, nodes)
        self._extras(trees)
        self.progress.end_pass()

    def _level(self, level, nodes) -> np.ndarray:
        """Test direction level ``level``'s open cells ``nodes`` (their midpoints traced, kept
        where they split) and split them; returns the children to test next."""
        p, M, Gd = self.cfg.params, self.cfg.M, self.cfg.Gd
        s, dirf = self.state, self.state.dirf
        tr = dirf.tree_of_nodes()[nodes]
        inside = self._overlaps_rect(nodes, tr)           # only the baked rectangle refines
        nodes, tr = nodes[inside], tr[inside]
        self.progress.level(level, len(nodes))
        cc = dirf.corner_coords(nodes, M)
        mid = (cc[:, 0] + cc[:, 3]) // 2 if level < M else (cc[:, 0] + cc[:, 3]) / 2
        if level < p.min_direction_depth:
            split = np.ones(len(nodes), bool)
        else:
            u, v = self.uv_of(tr, mid)
            ms = self._trace(tr, u, v)
            scale = dirf.cube_scale(nodes, tr, np.broadcast_to(UNIT_CORNERS[:, 0], (len(tr), 4)),
                                    np.broadcast_to(UNIT_CORNERS[:, 1], (len(tr), 4)))
            split, err, flags = _midpoint_test(s.samples, dirf.corner[nodes], scale, ms,
                                               self.cfg.class_of, np.radians(p.tolerance_deg),
                                               p.tolerance_dist * self.cfg.diag)
            flags |= self._hidden_hits(nodes, tr, ms)
            s.record(nodes, err, flags | np.where(split & (level == M), UNVERIFIED, 0))
            if level == M:
                return nodes[:0]
            # the traced midpoint becomes a corner of the children: keep it
            keep = np.flatnonzero(split)
            if len(keep):
                new = s.add_samples(take(ms, keep), s.stages.mid(level))
                s.index.add((tr * Gd * Gd + mid[:, 1] * Gd + mid[:, 0])[keep], new)
        sn = nodes[split]
        if len(sn) == 0:
            return sn
        kids = dirf.split(sn)                                        # (n, 4)
        kc = dirf.corner_coords(kids.ravel(), M)                     # (4n, 4, 2)
        ktr = np.repeat(tr[split], 4)
        dirf.corner[kids.ravel()] = self._ensure(np.repeat(ktr, 4), kc.reshape(-1, 2),
                                                 s.stages.corners(level)).reshape(-1, 4)
        return kids.ravel()

    def _extras(self, trees) -> None:
        """Extra samples (paper 4.3) for the leaves of ``trees`` inside their rectangles."""
        s, dirf = self.state, self.state.dirf
        self.progress.label = "extra samples"
        tree_of = dirf.tree_of_nodes()
        leaves = np.flatnonzero((dirf.child < 0) & np.isin(tree_of, trees))
        leaves = leaves[self._overlaps_rect(leaves, tree_of[leaves])]
        search = ExtraSearch(forest=dirf, samples=s.samples, class_of=self.cfg.class_of,
                             M=self.cfg.M, steps=self.cfg.params.search_steps,
                             probe=self._probe, keep=self._keep)
        s.add_extras(extra_samples(search, leaves, tree_of))

    def _probe(self, tr, gxy) -> Samples:
        """Trace the extra-sample rays of trees ``tr`` at direction grid points ``gxy``."""
        u, v = self.uv_of(tr, gxy)
        return self._trace(tr, u, v, "extra")

    def _keep(self, samples: Samples, step, leaf_level) -> np.ndarray:
        """Append the extra samples found at search ``step`` for leaves at ``leaf_level``."""
        return self.state.add_samples(samples, self.state.stages.extra(step, leaf_level))

    def uv_of(self, tr, gxy):
        """(u, v) on the direction cube of grid points ``gxy`` (n, 2) of trees ``tr``."""
        d = self.state.dirf.domain[tr]
        Gd = self.cfg.Gd
        return (d[:, 0] + (d[:, 1] - d[:, 0]) * gxy[:, 0] / (Gd - 1),
                d[:, 2] + (d[:, 3] - d[:, 2]) * gxy[:, 1] / (Gd - 1))

    def _tree_vp_cube(self, tr):
        vp = tr // N_SLOTS
        return vp, CUBE[self.state.vp_face[vp], tr % N_SLOTS]

    def _trace(self, tr, u, v, kind="level") -> Samples:
        vp, cube = self._tree_vp_cube(tr)
        self.tracer.kind = kind
        return self.tracer(vp, cube, u, v)

    def _ensure(self, tr, gxy, stage):
        """Sample ids for grid points (tree, gx, gy), tracing the ones not sampled yet (they are
        created at ``stage``)."""
        Gd, s = self.cfg.Gd, self.state
        keys = tr * Gd * Gd + gxy[:, 1] * Gd + gxy[:, 0]
        ids = s.index.lookup(keys)
        miss = np.flatnonzero(ids < 0)
        if len(miss):
            nk, first, inv2 = np.unique(keys[miss], return_index=True, return_inverse=True)
            t_new, g_new = tr[miss][first], gxy[miss][first]
            u, v = self.uv_of(t_new, g_new)
            new = s.add_samples(self._trace(t_new, u, v), stage)
            s.index.add(nk, new)
            ids[miss] = new[inv2.ravel()]
        return ids

    def _overlaps_rect(self, nodes, tr):
        cc = self.state.dirf.corner_coords(nodes, self.cfg.M)
        u_lo, v_lo = self.uv_of(tr, cc[:, 0])
        u_hi, v_hi = self.uv_of(tr, cc[:, 3])
        r = self.state.rect[tr]
        return (u_hi >= r[:, 0]) & (u_lo <= r[:, 1]) & (v_hi >= r[:, 2]) & (v_lo <= r[:, 3])

    def _hidden_hits(self, nodes, tr, ms):
        """BOUNDARY for the direction cells ``nodes`` whose corners and traced midpoints ``ms``
        all miss while their frustum (the rays from their viewpoint through the cell) meets the
        box of some sub-patch or triangle of the object: a hit may lie between the samples
        (paper Fig. 9(b)), so the render checks the cell's misses."""
        s = self.state
        out = np.zeros(len(nodes), np.uint8)
        i = np.flatnonzero(np.all(s.samples.patch[s.dirf.corner[nodes]] < 0, axis=1)
                           & (ms.patch < 0))
        if len(i) == 0:
            return out
        cc = s.dirf.corner_coords(nodes[i], self.cfg.M)
        u0, v0 = self.uv_of(tr[i], cc[:, 0])
        u1, v1 = self.uv_of(tr[i], cc[:, 3])
        vp, cube = self._tree_vp_cube(tr[i])
        seen = rects_see_object(self.cfg.st.tracer, s.vp_pos[vp], cube,
                                np.stack([u0, u1, v0, v1], axis=1))
        out[i[seen]] = BOUNDARY
        return out


def _midpoint_test(samples, corner, scale, ms: Samples, class_of, tol_ang, tol_d):
    """Split test of cells with corner sample ids ``corner`` (N, 4) and traced midpoints ``ms``;
    ``scale`` (N, 4) weighs the corners' output directions as the renderer does
    (perspective-correct: the length of each corner's direction-cube point); tolerances
    ``tol_ang`` (radians) and ``tol_d`` (world units).

    Returns (split (N,), err (N,) float32, flags (N,) uint8): err is the output-direction error
    in degrees of the midpoint interpolated as the renderer would (the corners of its class,
    not null), 0 where the midpoint and all corners miss or are null of one class, NaN where
    there is no interpolation to measure; flags mark object/miss boundaries and ray-tree
    hash changes among the corners and the midpoint."""
    cc = classes(samples, corner, class_of)
    cm = np.where(ms.patch >= 0, class_of[np.maximum(ms.patch, 0)], -1)
    cn = samples.null[corner]
    disagree = np.any(cc != cm[:, None], axis=1) | np.any(cn != ms.null[:, None], axis=1)
    usable = (cc == cm[:, None]) & ~cn
    half = np.full(len(corner), 0.5)
    w, st = cell_weights(usable, half, half)
    smooth = ~disagree & ~ms.null & (cm >= 0)
    fail = np.zeros(len(corner), bool)
    err = np.full(len(corner), np.nan, np.float32)
    err[~disagree & (ms.null | (cm < 0))] = 0.0
    meas = ~ms.null & (cm >= 0) & (st != FAIL)
    if np.any(meas):
        i = np.flatnonzero(meas)
        wi = w[i][:, :, None]
        ci = corner[i]
        od = np.einsum("nkc,nk->nc", samples.out_d[ci].astype(np.float64), w[i] * scale[i])
        od /= np.maximum(np.linalg.norm(od, axis=1), 1e-300)[:, None]
        nm = (samples.normal[ci].astype(np.float64) * wi).sum(1)
        nm /= np.maximum(np.linalg.norm(nm, axis=1), 1e-300)[:, None]
        oo = (samples.out_o[ci].astype(np.float64) * wi).sum(1)
        pt = (samples.point[ci].astype(np.float64) * wi).sum(1)
        e_od = angle_between(od, ms.out_d[i].astype(np.float64))
        err[i] = np.degrees(e_od)
        fail[i] = ((e_od > tol_ang)
                   | (angle_between(nm, ms.normal[i].astype(np.float64)) > tol_ang)
                   | (np.linalg.norm(oo - ms.out_o[i], axis=1) > tol_d)
                   | (np.linalg.norm(pt - ms.point[i], axis=1) > tol_d))
    fail |= smooth & (st == FAIL)
    hit = np.concatenate([cc, cm[:, None]], axis=1) >= 0
    flags = np.where(hit.any(1) & ~hit.all(1), BOUNDARY, 0).astype(np.uint8)
    th = np.concatenate([samples.tree[corner], ms.tree[:, None]], axis=1).astype(np.int64)
    th_hit = np.where(hit, th, -1)
    lo = np.where(hit, th, np.iinfo(np.int64).max).min(axis=1)
    flags |= np.where(th_hit.max(axis=1) > lo, PATH_CHANGE, 0).astype(np.uint8)
    return disagree | (smooth & fail), err, flags
