"""Answering rays through the RI-Tree (paper 4.1, 4.2, 4.3, 5.1-5.4).

For each query ray that enters the padded box: its entry point Q and face give the viewpoint
cell (four viewpoints, bilinear weights); its direction gives the hemicube slot and (u, v);
the four direction trees give four leaf cells (DQs), 16 samples in all. Then
- policy "ri" (the paper): the two-patch condition over the 16 class ids; with two classes
  the exact first hit against only the <= 16 candidate patches picks the class; usable samples
  are those of that class that are not null; each DQ interpolates bilinearly (4 usable),
  barycentrically (3) or from its extra samples (one/two-interpolant cells); the QNode level
  combines the DQs the same way; extrapolation and the pairwise angle/distance thresholds
  apply; anything short of three interpolants at either level is traced exactly - except
  where counting the null samples of the class as usable gives an interpolation whose
  interpolants are all null: that ray is answered null (``null_interp``, on by default; the
  paper traces it), so the trapped regions of a refractor are not traced ray by ray.
- policy "raytree" (Bala et al., for comparison): interpolate only when all 16 samples have
  identical ray trees; trace otherwise.
Interpolated first-hit points and normals feed local illumination; a dielectric's reflected
ray and Fresnel weight come from the interpolated normal.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from ..trace.objectfn import ObjectRays, fresnel_dielectric, reflect
from .extras import extra_weights
from .interp import (BILINEAR, EXTRA, EXTRAPOLATED, FAIL, TRIANGLE, UNIT_CORNERS,
                     bilinear_weights, cell_weights, drop_outlier, far_pairs, may_have_far_pairs)
from .locate import Located, locate

# Rays per block of the blend stage: bounds its (rays, 24, 12) float32 sample gather to 38 MB.
BLEND_BLOCK = 1 << 15
# Interpolated unit vectors shorter than this before normalization (opposed samples) are not
# trusted: the ray is traced.
MIN_BLEND_NORM = 1e-3

# Answer codes: how each ray was answered.
# FULL..EXTRAPOLATED_S interpolate an output ray; NULL_S answers the null ray (trapped: every
# interpolant of the query's class is null).
MISS, FULL, REDUCED, EXTRA_S, EXTRAPOLATED_S, TRACED, OUTSIDE, NULL_S = 0, 1, 2, 3, 4, 5, 6, 7
ANSWER_NAMES = ("miss", "interpolated_16", "interpolated_reduced", "interpolated_extra",
                "interpolated_extrapolated", "traced", "traced_outside_tree", "interpolated_null")
# Why a ray was traced.
WHY_CLASSES, WHY_USABLE, WHY_THRESHOLD, WHY_RAYTREE, WHY_BLEND = 1, 2, 3, 4, 5
WHY_NAMES = ("", "more_than_two_classes", "too_few_usable", "threshold", "raytree_mismatch",
             "degenerate_blend")


@dataclass
class QueryOptions:
    """Render-time choices (no re-bake needed). Angles in degrees, distances relative to the
    object's box diagonal; None switches a rule off."""

    policy: str = "ri"                 # "ri" (the paper) or "raytree" (Bala et al.)
    extrapolation: float | None = None  # allowed barycentric distance below 0 (None: off)
    angle_deg: float | None = 20.0     # pairwise angle threshold between interpolants
    distance: float | None = None      # pairwise distance threshold between output origins
    threshold_on: str = "samples"      # compare all interpolated samples (the paper), or the
                                       # four viewpoints' "intermediate" rays f*(R_VP)
    threshold_leaves: str = "all"      # samples mode: compare the samples of "all" direction
                                       # leaves, or of the "unverified" ones only (at the maximum
                                       # depth: a shallower leaf passed the bake's midpoint test)
    null_interp: bool = True           # a ray whose interpolants (class rules, null rays
                                       # counted) are all null is null; False: traced (the paper)

    def validate(self) -> "QueryOptions":
        if self.policy not in ("ri", "raytree"):
            raise ValueError(f"policy must be 'ri' or 'raytree', got {self.policy!r}")
        if self.threshold_on not in ("intermediate", "samples"):
            raise ValueError("threshold_on must be 'intermediate' or 'samples', "
                             f"got {self.threshold_on!r}")
        if self.threshold_leaves not in ("unverified", "all"):
            raise ValueError("threshold_leaves must be 'unverified' or 'all', "
                             f"got {self.threshold_leaves!r}")
        for name in ("extrapolation", "angle_deg", "distance"):
            val = getattr(self, name)
            if val is not None and not (np.isfinite(val) and val >= 0):
                raise ValueError(f"{name} must be None or a finite number >= 0, got {val!r}")
        return self


class StageClock:
    """CPU seconds (this process's CPU clock) spent per named stage of a query."""

    def __init__(self):
        self.cpu: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str):
        t0 = time.process_time()
        try:
            yield
        finally:
            self.cpu[name] = self.cpu.get(name, 0.0) + time.process_time() - t0


# Stages whose time is exact tracing the query calls (the rest is the query's own work).
TRACING_STAGES = ("first_hits", "trace")


def group_rows(keys: np.ndarray):
    """Group the rows of an (m, k) integer array: (group id of each row (m,), index of the
    first row of each group (G,)); groups are numbered in sorted key order."""
    m = len(keys)
    if m == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order = np.lexsort(keys.T[::-1])
    sk = keys[order]
    new = np.ones(m, bool)
    new[1:] = np.any(sk[1:] != sk[:-1], axis=1)
    group = np.empty(m, np.int64)
    group[order] = np.cumsum(new) - 1
    return group, order[new]


def blend(table_vals, sid, w, wd) -> np.ndarray:
    """Weighted sums of samples: (n, K) sample ids with weights ``w`` for origins, points and
    normals and ``wd`` for directions (perspective-scaled) -> (n, 12) float64, in blocks of
    BLEND_BLOCK rays (float32 gather and sums)."""
    n = len(sid)
    out = np.empty((n, 12))
    for a in range(0, n, BLEND_BLOCK):
        b = min(a + BLEND_BLOCK, n)
        v = table_vals[sid[a:b]]
        out[a:b] = np.matmul(w[a:b, None, :].astype(np.float32), v)[:, 0]
        out[a:b, 3:6] = np.matmul(wd[a:b, None, :].astype(np.float32), v[:, :, 3:6])[:, 0]
    return out


class TreeQuery:
    """Answers batches of rays with a baked tree, tracing exactly (``st``, a SceneTracer) where
    the tree cannot answer.

    One call runs a staged pipeline over all its rays (call it with a whole frame, or a
    worker's share of one): locate -> group rays by sample set -> exact first hits of all
    two-class rays (one tracer call) -> per (set, class) decisions -> per-ray weights ->
    blend -> exact tracing of every ray the tree cannot answer (one tracer call). Work that
    depends only on the 16 samples and the class (class counts, candidate patches, usable
    corners, whether any pairwise threshold can bite) is done once per set, not per ray."""

    def __init__(self, tree, st, options: QueryOptions | None = None):
        self.tree, self.st = tree, st
        self.opt = (options or QueryOptions()).validate()
        self.material = st.scene.object.material
        self.table = tree.table

    def __call__(self, o, d, tmax=None):
        """(ObjectRays, answers (N,), why (N,), stats) for rays o, d (unit). ``stats`` holds
        ``exact_first_hits`` and the CPU seconds of each stage (``query_<stage>_cpu_s``)."""
        o = np.asarray(o, np.float64)
        d = np.asarray(d, np.float64)
        n = len(o)
        tmax = np.full(n, np.inf) if tmax is None else np.asarray(tmax, np.float64)
        clock = StageClock()
        ans = np.full(n, MISS, np.int8)
        why = np.zeros(n, np.int8)
        res = _empty_result(n, o, d)
        with clock("locate"):
            loc, outside = locate(self.tree, o, d, tmax)
        ans[outside] = OUTSIDE
        n_exact = 0
        if len(loc):
            if self.opt.policy == "raytree":
                self._raytree(o, d, tmax, loc, res, ans, why, clock)
            else:
                n_exact = self._ri(o, d, tmax, loc, res, ans, why, clock)
        with clock("trace"):
            tr = np.flatnonzero((ans == TRACED) | (ans == OUTSIDE))
            if len(tr):
                ex = self.st.object_function(o[tr], d[tr], tmax[tr])
                for k, val in ex.__dict__.items():
                    getattr(res, k)[tr] = val
        stats = {"exact_first_hits": n_exact,
                 **{f"query_{k}_cpu_s": v for k, v in clock.cpu.items()}}
        return res, ans, why, stats

    # ------------------------------------------------------------------ sample sets
    def _sets(self, loc: Located):
        """Group located rays by their four leaves (= their 16 samples): (set of each ray,
        leaves (S, 4), sample ids (S, 16), sample classes (S, 16), trees (S, 4))."""
        set_of, first = group_rows(loc.leaf)
        s_leaf = loc.leaf[first]
        s_ids = self.tree.dir_forest.corner[s_leaf].reshape(-1, 16)
        return set_of, s_leaf, s_ids, self.table.cls[s_ids], loc.trees[first]

    def _corner_scale(self, s_leaf, s_trees) -> np.ndarray:
        """(S, 16) perspective weights of the sets' corner samples (see Forest.cube_scale)."""
        s = len(s_leaf)
        return self.tree.dir_forest.cube_scale(
            s_leaf, s_trees, np.broadcast_to(UNIT_CORNERS[:, 0], (s, 4, 4)),
            np.broadcast_to(UNIT_CORNERS[:, 1], (s, 4, 4))).reshape(s, 16)

    # ------------------------------------------------------------------ the paper's policy
    def _ri(self, o, d, tmax, loc, res, ans, why, clock) -> int:
        tree, tab, opt = self.tree, self.table, self.opt
        with clock("group"):
            set_of, s_leaf, s_ids, s_cls, s_trees = self._sets(loc)
            srt = np.sort(s_cls, axis=1)
            n_cls = 1 + np.sum(srt[:, 1:] != srt[:, :-1], axis=1)
            r_n = n_cls[set_of]
            rows = loc.ray
            many = r_n > 2
            ans[rows[many]] = TRACED
            why[rows[many]] = WHY_CLASSES
            pc = np.where(r_n == 1, srt[set_of, 0], -2)
            two = np.flatnonzero(r_n == 2)
        if len(two):
            with clock("first_hits"):
                pc[two] = self._first_hit_class(o, d, tmax, rows[two], set_of[two],
                                                np.flatnonzero(n_cls == 2), s_ids)
        ans[rows[pc == -1]] = MISS
        go = np.flatnonzero(pc >= 0)
        if len(go) == 0:
            return len(two)
        thresholds = opt.angle_deg is not None or opt.distance is not None
        ang = None if opt.angle_deg is None else np.radians(opt.angle_deg)
        dist = None if opt.distance is None else opt.distance * tree.diag
        per_sample = thresholds and opt.threshold_on == "samples"
        with clock("decide"):
            loc, set_of, pc = loc.take(go), set_of[go], pc[go]
            m = len(loc)
            unit_of, ufirst = group_rows(np.stack([set_of, pc], axis=1))
            u_set, u_pc = set_of[ufirst], pc[ufirst]
            u_ids = s_ids[u_set]
            u_usable = (s_cls[u_set] == u_pc[:, None]) & ~tab.null[u_ids]          # (U, 16)
            # the DQs whose samples the thresholds compare: all, or those the bake could not
            # verify (split to the maximum depth: a shallower leaf's midpoint matched)
            u_checked = np.ones((len(u_set), 4), bool)
            if per_sample and opt.threshold_leaves == "unverified":
                u_checked = tree.dir_forest.level[s_leaf[u_set]] >= tree.params.direction_depth
            u_far = np.zeros(len(u_set), bool)      # units where some threshold may bite
            if per_sample:
                u_far = self._may_be_far(s_leaf[u_set], u_ids, u_usable, u_pc, u_checked, ang,
                                         dist)
        with clock("weights"):
            usable = u_usable[unit_of].reshape(m, 4, 4)
            checked = u_checked[unit_of]
            thr_hit = np.zeros((m, 4), bool)            # DQs whose corners the thresholds cut
            fr = np.flatnonzero(u_far[unit_of])         # rays that need the pairwise tests
            if len(fr):
                self._direction_thresholds(fr, unit_of, u_far, u_ids, u_usable, u_checked, loc,
                                           usable, thr_hit, ang, dist)
            w = np.zeros((m, 4, 6))                          # 4 corners + up to 2 extras
            sid = np.zeros((m, 4, 6), np.int64)
            sid[:, :, :4] = u_ids[unit_of].reshape(m, 4, 4)
            dq_st = np.zeros((m, 4), np.int8)
            is_extra = np.zeros((m, 4), bool)
            ex_pos = np.zeros((m, 4, 2, 2))
            for k in range(4):
                wk, sk = cell_weights(usable[:, k], loc.lx[:, k], loc.ly[:, k], opt.extrapolation)
                w[:, k, :4] = wk
                dq_st[:, k] = sk
                fail = np.flatnonzero(sk == FAIL)
                if len(fail):
                    ea = extra_weights(tree, tab, loc.leaf[fail, k], loc.lx[fail, k],
                                       loc.ly[fail, k], usable[fail, k], pc[fail],
                                       opt.extrapolation)
                    g = fail[ea.rows]
                    w[g, k] = ea.w
                    sid[g, k, 4:] = ea.ids
                    ex_pos[g, k] = ea.pos
                    dq_st[g, k] = np.where(ea.extrapolated, EXTRAPOLATED, EXTRA)
                    is_extra[g, k] = True
            # viewpoint level
            dq_ok = dq_st != FAIL
            thr_q = np.zeros(m, bool)
            scale = None
            if per_sample and len(fr):
                self._viewpoint_thresholds(fr, usable, w, sid, is_extra, dq_ok, checked, loc,
                                           thr_hit, thr_q, ang, dist)
            elif thresholds and not per_sample:
                # the intermediate rays f*(R_VP): parallel query rays from the four viewpoints
                scale = self._scales(loc, set_of, s_leaf, s_trees, is_extra, ex_pos)
                inter = blend(tab.vals, sid.reshape(4 * m, 6), w.reshape(4 * m, 6),
                              (w * scale).reshape(4 * m, 6)).reshape(m, 4, 12)
                idir = inter[:, :, 3:6] / np.maximum(
                    np.linalg.norm(inter[:, :, 3:6], axis=2), 1e-300)[:, :, None]
                r2, blocks = far_pairs(idir, inter[:, :, 0:3], dq_ok, ang, dist)
                dq_ok[r2], thr_q[r2] = drop_outlier(blocks, dq_ok[r2], UNIT_CORNERS,
                                                    np.stack([loc.alpha[r2], loc.beta[r2]], 1))
            W, qst = cell_weights(dq_ok, loc.alpha, loc.beta, opt.extrapolation)
            few = qst == FAIL
            # too few interpolants because the thresholds cut them: traced "by the threshold"
            thr = ~(few & (thr_q | np.any(thr_hit & ~dq_ok, axis=1)))
            few &= thr
        with clock("blend"):
            cand = np.flatnonzero(~few & thr)
            weights = (W[cand, :, None] * w[cand]).reshape(len(cand), 24)
            if scale is None:
                scale = self._scales(loc.take(cand), set_of[cand], s_leaf, s_trees,
                                     is_extra[cand], ex_pos[cand])
            else:
                scale = scale[cand]
            out = self._blend_rows(sid[cand].reshape(len(cand), 24), weights,
                                   scale.reshape(len(cand), 24), is_extra[cand].any(axis=1))
            od, nm = out[:, 3:6], out[:, 9:12]
            lod, lnm = np.linalg.norm(od, axis=1), np.linalg.norm(nm, axis=1)
            blend_ok = np.ones(m, bool)
            blend_ok[cand] = (lod > MIN_BLEND_NORM) & (lnm > MIN_BLEND_NORM)
            good = ~few & thr & blend_ok
            kind = np.maximum(dq_st.max(axis=1, where=dq_ok, initial=BILINEAR), qst)
            code = np.select([kind == BILINEAR, kind == TRIANGLE, kind == EXTRA,
                              kind == EXTRAPOLATED], [FULL, REDUCED, EXTRA_S, EXTRAPOLATED_S],
                             TRACED)
            rows = loc.ray
            ans[rows] = np.where(good, code, TRACED)
            why[rows] = np.select([few, ~thr, ~blend_ok], [WHY_USABLE, WHY_THRESHOLD, WHY_BLEND], 0)
            gc = good[cand]
            g = cand[gc]
            self._fill(res, ans, rows[g], o, d, tmax, out[gc, 0:3], od[gc] / lod[gc, None],
                       out[gc, 6:9], nm[gc] / lnm[gc, None], pc[g],
                       self._patch_of(sid[g].reshape(len(g), 24), weights[gc]))
            if opt.null_interp:
                flat = sid[:, :, :4].reshape(m, 16)
                nul = tab.null[flat]
                r = np.flatnonzero(few & np.any(nul & (tab.cls[flat] == pc[:, None]), axis=1))
                if len(r):
                    self._null(loc.take(r), flat[r], pc[r], o, d, tmax, res, ans, why)
        return len(two)

    def _first_hit_class(self, o, d, tmax, rows, set_of, two_sets, s_ids) -> np.ndarray:
        """Class of the exact first hit (-1: miss) of rays ``rows`` against only the distinct
        patches of their two-class sets (one tracer call for all of them)."""
        pat = np.sort(self.table.patch[s_ids[two_sets]].astype(np.int64), axis=1)
        dup = np.zeros_like(pat, bool)
        dup[:, 1:] = pat[:, 1:] == pat[:, :-1]
        cand = np.where(dup | (pat < 0), -1, pat)
        cand = cand[np.searchsorted(two_sets, set_of)]
        hit = self.st.tracer.intersect(o[rows], d[rows], tmax=tmax[rows], patches=cand)
        return np.where(hit.hit, hit.cls, -1)

    def _unit_extras(self, u_leaf, u_pc):
        """The extra samples of the units' leaves: ids (U, 4, 4) and which are usable for the
        unit's class (U, 4, 4)."""
        tree, tab = self.tree, self.table
        ids = np.zeros(u_leaf.shape + (4,), np.int64)
        ok = np.zeros(u_leaf.shape + (4,), bool)
        if len(tree.ex_node):
            pos = np.minimum(np.searchsorted(tree.ex_node, u_leaf), len(tree.ex_node) - 1)
            has = tree.ex_node[pos] == u_leaf
            ids = np.where(has[..., None], tree.ex_ids[pos], 0)
            ok = has[..., None] & (tab.cls[ids] == u_pc[:, None, None]) & ~tab.null[ids]
        return ids, ok

    def _may_be_far(self, u_leaf, u_ids, u_usable, u_pc, u_checked, ang, dist) -> np.ndarray:
        """(U,) units where a pairwise threshold may cut something: the test of far_pairs on
        everything a ray of the unit can use (checked usable corners and extras); a unit that
        passes has no far pair among any ray's interpolants."""
        ex_ids, ex_ok = self._unit_extras(u_leaf, u_pc)
        u = len(u_ids)
        ids = np.concatenate([u_ids, ex_ids.reshape(u, 16)], axis=1)
        used = np.concatenate([u_usable & np.repeat(u_checked, 4, axis=1),
                               (ex_ok & u_checked[:, :, None]).reshape(u, 16)], axis=1)
        v = self.table.vals[ids].astype(np.float64)
        return may_have_far_pairs(v[..., 3:6], v[..., 0:3], used, ang, dist)

    def _direction_thresholds(self, fr, unit_of, u_far, u_ids, u_usable, u_checked, loc,
                              usable, thr_hit, ang, dist):
        """Paper 5.3 at the direction level for rays ``fr``: far corners of a DQ are not usable
        (an outlier is dropped). Far pairs are found once per unit; the outlier dropped depends
        on where the ray falls in the cell."""
        fu = np.flatnonzero(u_far)
        v = self.table.vals[u_ids[fu]].astype(np.float64)
        used = u_usable[fu] & np.repeat(u_checked[fu], 4, axis=1)
        rws, far = far_pairs(v[..., 3:6], v[..., 0:3], used, ang, dist)
        slot = np.full(len(u_far), -1)
        slot[fu[rws]] = np.arange(len(rws))
        rr = fr[slot[unit_of[fr]] >= 0]
        if len(rr) == 0:
            return
        f = far[slot[unit_of[rr]]].reshape(-1, 4, 4, 4, 4)
        for k in range(4):
            usable[rr, k], thr_hit[rr, k] = drop_outlier(
                f[:, k, :, k], usable[rr, k], UNIT_CORNERS,
                np.stack([loc.lx[rr, k], loc.ly[rr, k]], 1))

    def _viewpoint_thresholds(self, fr, usable, w, sid, is_extra, dq_ok, checked, loc, thr_hit,
                              thr_q, ang, dist):
        """Paper 5.3 at the viewpoint level for rays ``fr``: DQs are far apart when any of their
        interpolants are (an extra-sample triangle's samples for extras); a DQ with a far pair
        inside is unusable, then an outlying DQ is dropped."""
        n = len(fr)
        member = np.concatenate([usable[fr], np.zeros((n, 4, 2), bool)], axis=2)
        member = np.where(is_extra[fr, :, None], w[fr] != 0, member)
        member &= dq_ok[fr, :, None] & checked[fr, :, None]
        v = self.table.vals[sid[fr].reshape(n, 24)].astype(np.float64)
        rws, far = far_pairs(v[..., 3:6], v[..., 0:3], member.reshape(n, 24), ang, dist)
        blocks = far.reshape(-1, 4, 6, 4, 6).any(axis=4).any(axis=2)          # (R, 4, 4)
        inner = np.diagonal(blocks, axis1=1, axis2=2)                           # (R, 4)
        r = fr[rws]
        thr_hit[r] |= inner
        dq_ok[r] &= ~inner
        dq_ok[r], thr_q[r] = drop_outlier(blocks, dq_ok[r], UNIT_CORNERS,
                                          np.stack([loc.alpha[r], loc.beta[r]], 1))

    def _scales(self, loc, set_of, s_leaf, s_trees, is_extra, ex_pos) -> np.ndarray:
        """(m, 4, 6) perspective weights of each ray's interpolants: corners once per set,
        extras per ray."""
        m = len(loc)
        scale = np.ones((m, 4, 6))
        if m == 0:
            return scale
        scale[:, :, :4] = self._corner_scale(s_leaf, s_trees)[set_of].reshape(m, 4, 4)
        r, k = np.nonzero(is_extra)
        if len(r):
            scale[r, k, 4:] = self.tree.dir_forest.cube_scale(
                loc.leaf[r, k], loc.trees[r, k], ex_pos[r, k, :, 0], ex_pos[r, k, :, 1])
        return scale

    def _blend_rows(self, sid, weights, scale, has_extra) -> np.ndarray:
        """Blend (n, 24) interpolants; rays without extras blend their 16 corners only."""
        out = np.empty((len(sid), 12))
        corners = (np.arange(24) % 6) < 4
        for sel, cols in ((~has_extra, corners), (has_extra, slice(None))):
            r = np.flatnonzero(sel)
            if len(r):
                wr = weights[r][:, cols]
                out[r] = blend(self.table.vals, sid[r][:, cols], wr, wr * scale[r][:, cols])
        return out

    def _null(self, loc, flat, pc, o, d, tmax, res, ans, why):
        """Rays (``loc``, their 16 sample ids ``flat``) that had too few usable interpolants:
        the same interpolation with the null samples of the query's class as the usable ones
        (null as a state of its own, like a class: four null corners, or three with the query
        inside their triangle, at both levels). Where it succeeds the query ray is answered
        null (trapped), with the interpolated first-hit point and normal for its local
        illumination."""
        tab = self.table
        m = len(loc)
        use = ((tab.cls[flat] == pc[:, None]) & tab.null[flat]).reshape(m, 4, 4)
        w = np.zeros((m, 4, 4))
        st = np.zeros((m, 4), np.int8)
        for k in range(4):
            w[:, k], st[:, k] = cell_weights(use[:, k], loc.lx[:, k], loc.ly[:, k])
        W, qst = cell_weights(st != FAIL, loc.alpha, loc.beta)
        weights = (W[:, :, None] * w).reshape(m, 16)
        ok = np.flatnonzero(qst != FAIL)
        if len(ok) == 0:
            return
        out = blend(tab.vals, flat[ok], weights[ok], weights[ok])
        pt, nm = out[:, 6:9], out[:, 9:12]
        ln = np.linalg.norm(nm, axis=1)
        keep = ln > MIN_BLEND_NORM
        ok, pt, nm, ln = ok[keep], pt[keep], nm[keep], ln[keep]
        rows = loc.ray[ok]
        ans[rows] = NULL_S
        why[rows] = 0
        self._fill(res, ans, rows, o, d, tmax, pt, np.zeros_like(pt), pt, nm / ln[:, None],
                   pc[ok], self._patch_of(flat[ok], weights[ok]), null=True)

    # ------------------------------------------------------------------ Bala et al.'s policy
    def _raytree(self, o, d, tmax, loc, res, ans, why, clock):
        """Interpolate (16 samples, bilinear at both levels) only where all 16 samples share
        one ray tree and class and none is null; trace otherwise. Decided once per set."""
        tab = self.table
        with clock("group"):
            set_of, s_leaf, s_ids, s_cls, s_trees = self._sets(loc)
            th = tab.tree[s_ids]
            same = np.all(th == th[:, :1], axis=1) & np.all(s_cls == s_cls[:, :1], axis=1) \
                & ~np.any(tab.null[s_ids], axis=1)
            r_same = same[set_of]
            rows = loc.ray
            ans[rows[r_same & (s_cls[set_of, 0] == -1)]] = MISS
            ans[rows[~r_same]] = TRACED
            why[rows[~r_same]] = WHY_RAYTREE
        with clock("blend"):
            g = np.flatnonzero(r_same & (s_cls[set_of, 0] != -1))
            if len(g) == 0:
                return
            wq = bilinear_weights(loc.alpha[g], loc.beta[g])
            wdq = np.stack([bilinear_weights(loc.lx[g, k], loc.ly[g, k]) for k in range(4)], 1)
            weights = (wq[:, :, None] * wdq).reshape(len(g), 16)
            sg = set_of[g]
            out = blend(tab.vals, s_ids[sg], weights,
                        weights * self._corner_scale(s_leaf, s_trees)[sg])
            od, nm = out[:, 3:6], out[:, 9:12]
            ans[rows[g]] = FULL
            self._fill(res, ans, rows[g], o, d, tmax, out[:, 0:3],
                       od / np.linalg.norm(od, axis=1)[:, None], out[:, 6:9],
                       nm / np.linalg.norm(nm, axis=1)[:, None], s_cls[sg, 0].astype(np.int64),
                       tab.patch[s_ids[sg, 0]].astype(np.int64))

    # ------------------------------------------------------------------ results
    def _patch_of(self, sid, weights):
        """The patch of the heaviest interpolant (a representative patch id)."""
        best = np.argmax(np.abs(weights), axis=1)
        return self.table.patch[sid[np.arange(len(sid)), best]].astype(np.int64)

    def _fill(self, res, ans, rows, o, d, tmax, oo, od, pt, nm, cls, patch, null=False):
        dd = d[rows]
        t_first = np.einsum("ij,ij->i", pt - o[rows], dd)
        # the environment is in front of the interpolated hit: the object is not seen
        hidden = t_first >= tmax[rows]
        ans[rows[hidden]] = MISS
        k = ~hidden
        rows, oo, od, pt, nm, cls, patch, dd, t_first = (
            a[k] for a in (rows, oo, od, pt, nm, cls, patch, dd, t_first))
        flip = np.einsum("ij,ij->i", nm, dd) > 0
        nm = np.where(flip[:, None], -nm, nm)
        res.hit[rows] = True
        res.null[rows] = null
        res.out_origin[rows] = oo
        res.out_dir[rows] = od
        res.point[rows] = pt
        res.normal[rows] = nm
        res.t_first[rows] = t_first
        res.cls[rows] = cls
        res.patch[rows] = patch
        if self.material.kind == "dielectric":
            cos_i = -np.einsum("ij,ij->i", dd, nm)
            res.fresnel[rows] = fresnel_dielectric(cos_i, np.full(len(rows), 1.0 / self.material.ior))
            res.refl_dir[rows] = reflect(dd, nm)


def _empty_result(n, o, d) -> ObjectRays:
    """Misses for every ray (output = input ray), to be filled in by the stages."""
    return ObjectRays(hit=np.zeros(n, bool), null=np.zeros(n, bool), out_origin=o.copy(),
                      out_dir=d.copy(), t_first=np.full(n, np.inf), point=np.zeros((n, 3)),
                      normal=np.zeros((n, 3)), patch=np.full(n, -1, np.int64),
                      cls=np.full(n, -1, np.int64), events=np.zeros(n, np.int64),
                      refl_dir=np.zeros((n, 3)), fresnel=np.zeros(n),
                      tree=np.zeros(n, np.uint32))
