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

from dataclasses import dataclass

import numpy as np

from ..trace.boxes import slab_intervals
from ..trace.objectfn import ObjectRays, fresnel_dielectric, reflect
from .dircube import SLOT, UV_AXES, dir_to_cube
from .interp import (BILINEAR, EXTRA, EXTRAPOLATED, FAIL, TRIANGLE, UNIT_CORNERS,
                     cell_weights, drop_outlier, far_pairs, pick_triangle)

QUERY_CHUNK = 16384            # rays per query batch (bounds the (N, 16, 12) gathers)
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


def entry_points(tree, o, d):
    """Entry distance, face and face coordinates of rays into the tree's padded box.
    Returns (t_in, face, x, y, inside): inside marks rays starting inside the box."""
    lo, hi = tree.box_lo, tree.box_hi
    tnear, tfar = slab_intervals(o, d, lo, hi)
    ins = (o >= lo) & (o <= hi)
    axis = np.argmax(tnear, axis=1)
    rows = np.arange(len(o))
    tn = tnear[rows, axis]
    tf = tfar.min(axis=1)
    inside = np.all(ins, axis=1)
    t_in = np.where((tn <= tf) & (tf >= 0), np.maximum(tn, 0.0), np.inf)
    face = 2 * axis + (d[rows, axis] < 0)
    q = o + np.where(np.isfinite(t_in), t_in, 0.0)[:, None] * d
    ua = np.array([p[0] for p in UV_AXES])[axis]
    va = np.array([p[1] for p in UV_AXES])[axis]
    return t_in, face, q[rows, ua], q[rows, va], inside


class TreeQuery:
    """Answers batches of rays with a baked tree, tracing exactly (``st``, a SceneTracer) where
    the tree cannot answer."""

    def __init__(self, tree, st, options: QueryOptions | None = None):
        self.tree, self.st = tree, st
        self.opt = (options or QueryOptions()).validate()
        self.material = st.scene.object.material

    def __call__(self, o, d, tmax=None):
        """(ObjectRays, answers (N,), why (N,), stats) for rays o, d (unit)."""
        n = len(o)
        tmax = np.full(n, np.inf) if tmax is None else np.asarray(tmax, np.float64)
        parts = [self._chunk(o[a:a + QUERY_CHUNK], d[a:a + QUERY_CHUNK], tmax[a:a + QUERY_CHUNK])
                 for a in range(0, n, QUERY_CHUNK)]
        if not parts:
            return self._empty_result(0), np.zeros(0, np.int8), np.zeros(0, np.int8), {}
        res = ObjectRays(**{k: np.concatenate([getattr(p[0], k) for p in parts])
                            for k in parts[0][0].__dict__})
        ans = np.concatenate([p[1] for p in parts])
        why = np.concatenate([p[2] for p in parts])
        stats = {"exact_first_hits": sum(p[3] for p in parts)}
        return res, ans, why, stats

    # ------------------------------------------------------------------ one chunk
    def _chunk(self, o, d, tmax):
        tree, opt = self.tree, self.opt
        n = len(o)
        ans = np.full(n, MISS, np.int8)
        why = np.zeros(n, np.int8)
        res = self._empty_result(n, o, d)
        t_in, face, x, y, inside = entry_points(tree, o, d)
        enter = np.isfinite(t_in) & (t_in < tmax)
        ans[inside] = OUTSIDE
        q = np.flatnonzero(enter & ~inside)
        # viewpoint cell
        vnode, alpha, beta = tree.vp_forest.locate(face[q], x[q], y[q])
        vps = tree.vp_forest.corner[np.maximum(vnode, 0)]
        cf, u, v = dir_to_cube(d[q])
        slot = SLOT[face[q], cf]
        ok = (vnode >= 0) & np.all(vps >= 0, axis=1) & (slot >= 0)
        trees = vps * 5 + slot[:, None]                                    # (m, 4)
        trees = np.where(ok[:, None], trees, 0)
        leaf, lx, ly = tree.dir_forest.locate(trees.ravel(), np.repeat(u, 4), np.repeat(v, 4))
        leaf, lx, ly = leaf.reshape(-1, 4), lx.reshape(-1, 4), ly.reshape(-1, 4)
        rect = tree.dir_rect[trees]
        ok &= np.all(leaf >= 0, axis=1)
        ok &= np.all((u[:, None] >= rect[..., 0]) & (u[:, None] <= rect[..., 1])
                     & (v[:, None] >= rect[..., 2]) & (v[:, None] <= rect[..., 3]), axis=1)
        ids = tree.dir_forest.corner[np.maximum(leaf, 0)]                 # (m, 4, 4)
        ok &= np.all(ids >= 0, axis=(1, 2))
        ans[q[~ok]] = OUTSIDE
        keep = np.flatnonzero(ok)
        q, alpha, beta, leaf, lx, ly, ids, trees = (
            a[keep] for a in (q, alpha, beta, leaf, lx, ly, ids, trees))
        n_exact = 0
        if len(q):
            if opt.policy == "raytree":
                n_exact = self._raytree(o, d, tmax, q, alpha, beta, leaf, trees, lx, ly, ids,
                                        res, ans, why)
            else:
                n_exact = self._ri(o, d, tmax, q, alpha, beta, leaf, trees, lx, ly, ids, res,
                                   ans, why)
        # exact tracing where the tree could not answer
        tr = np.flatnonzero((ans == TRACED) | (ans == OUTSIDE))
        if len(tr):
            ex = self.st.object_function(o[tr], d[tr], tmax[tr])
            for k, val in ex.__dict__.items():
                getattr(res, k)[tr] = val
        return res, ans, why, n_exact

    def _empty_result(self, n, o=None, d=None) -> ObjectRays:
        o = np.zeros((n, 3)) if o is None else o
        d = np.zeros((n, 3)) if d is None else d
        return ObjectRays(hit=np.zeros(n, bool), null=np.zeros(n, bool), out_origin=o.copy(),
                          out_dir=d.copy(), t_first=np.full(n, np.inf), point=np.zeros((n, 3)),
                          normal=np.zeros((n, 3)), patch=np.full(n, -1, np.int64),
                          cls=np.full(n, -1, np.int64), events=np.zeros(n, np.int64),
                          refl_dir=np.zeros((n, 3)), fresnel=np.zeros(n),
                          tree=np.zeros(n, np.uint32))

    # ------------------------------------------------------------------ the paper's policy
    def _ri(self, o, d, tmax, q, alpha, beta, leaf, trees, lx, ly, ids, res, ans, why):
        tree, opt = self.tree, self.opt
        m = len(q)
        flat = ids.reshape(m, 16)
        cls = tree.sample_class(flat)
        srt = np.sort(cls, axis=1)
        n_cls = 1 + np.sum(srt[:, 1:] != srt[:, :-1], axis=1)
        many = n_cls > 2
        ans[q[many]] = TRACED
        why[q[many]] = WHY_CLASSES
        pcls = np.where(n_cls == 1, srt[:, 0], -2)
        two = np.flatnonzero(n_cls == 2)
        n_exact = len(two)
        if len(two):
            # the exact first hit of the query ray against only the candidate patches
            pat = tree.samples.patch[flat[two]].astype(np.int64)
            srt_p = np.sort(pat, axis=1)
            dup = np.zeros_like(srt_p, bool)
            dup[:, 1:] = srt_p[:, 1:] == srt_p[:, :-1]
            cand = np.where(dup | (srt_p < 0), -1, srt_p)
            hit = self.st.tracer.intersect(o[q[two]], d[q[two]], tmax=tmax[q[two]], patches=cand)
            pcls[two] = np.where(hit.hit, hit.cls, -1)
        miss = (pcls == -1) & ~many
        ans[q[miss]] = MISS
        go = np.flatnonzero(~many & ~miss)
        if len(go) == 0:
            return n_exact
        q, alpha, beta, leaf, trees, lx, ly, flat, cls, pc = (
            a[go] for a in (q, alpha, beta, leaf, trees, lx, ly, flat, cls, pcls))
        m = len(q)
        usable = ((cls == pc[:, None]) & ~tree.samples.null[flat]).reshape(m, 4, 4)
        thresholds = opt.angle_deg is not None or opt.distance is not None
        ang = None if opt.angle_deg is None else np.radians(opt.angle_deg)
        dist = None if opt.distance is None else opt.distance * tree.diag
        per_sample = thresholds and opt.threshold_on == "samples"
        vals = np.zeros((m, 4, 6, 12))
        vals[:, :, :4] = tree.samples.gather(flat).reshape(m, 4, 4, 12)
        thr_hit = np.zeros((m, 4), bool)              # DQs whose corners the thresholds cut
        # the DQs whose samples the thresholds compare: all, or those the bake could not verify
        # (split to the maximum depth: a shallower leaf's midpoint matched its interpolation)
        checked = np.ones((m, 4), bool)
        if per_sample and opt.threshold_leaves == "unverified":
            checked = tree.dir_forest.level[leaf] >= tree.params.direction_depth
        if per_sample:
            # direction level: far corners of a DQ are not usable (an outlier is dropped)
            v = vals[:, :, :4].reshape(m, 16, 12)
            rows, far = far_pairs(v[:, :, 3:6], v[:, :, 0:3],
                                  (usable & checked[:, :, None]).reshape(m, 16), ang, dist)
            far = far.reshape(-1, 4, 4, 4, 4)
            for k in range(4):
                usable[rows, k], thr_hit[rows, k] = drop_outlier(
                    far[:, k, :, k], usable[rows, k], UNIT_CORNERS,
                    np.stack([lx[rows, k], ly[rows, k]], 1))
        # direction level: per DQ weights over its corners (plus extra samples)
        w = np.zeros((m, 4, 6))                                  # 4 corners + up to 2 extras
        sid = np.zeros((m, 4, 6), np.int64)
        sid[:, :, :4] = flat.reshape(m, 4, 4)
        dq_st = np.zeros((m, 4), np.int8)
        is_extra = np.zeros((m, 4), bool)
        lpos = np.zeros((m, 4, 6, 2))                           # cell-local sample positions
        lpos[:, :, :4] = UNIT_CORNERS
        for k in range(4):
            wk, sk = cell_weights(usable[:, k], lx[:, k], ly[:, k], opt.extrapolation)
            w[:, k, :4] = wk
            dq_st[:, k] = sk
            fail = np.flatnonzero(sk == FAIL)
            if len(fail):
                self._extra(fail, k, leaf, lx, ly, usable, pc, w, sid, dq_st, is_extra, lpos)
        ex_r, ex_k = np.nonzero(is_extra)
        if len(ex_r):
            vals[ex_r, ex_k, 4:] = tree.samples.gather(sid[ex_r, ex_k, 4:])
        # viewpoint level
        dq_ok = dq_st != FAIL
        # perspective-correct directions: weight each output direction by the length of its
        # sample's direction-cube point (exact for affine ray maps such as a plane mirror)
        vals_s = vals.copy()
        vals_s[..., 3:6] *= tree.dir_forest.cube_scale(leaf, trees, lpos[..., 0],
                                                       lpos[..., 1])[..., None]
        inter = np.einsum("nkj,nkjc->nkc", w, vals_s)                   # f*(R_VP) per DQ
        thr_q = np.zeros(m, bool)
        if thresholds:
            if per_sample:
                # DQs are far apart when any of their interpolants are (the chosen triangle's
                # samples for extras); an extra-sample triangle with a far pair is unusable
                member = np.concatenate([usable, np.zeros((m, 4, 2), bool)], axis=2)
                member = np.where(is_extra[:, :, None], w != 0, member) & dq_ok[:, :, None]
                member &= checked[:, :, None]
                v = vals.reshape(m, 24, 12)
                rows, far = far_pairs(v[:, :, 3:6], v[:, :, 0:3], member.reshape(m, 24), ang,
                                      dist)
                blocks = far.reshape(-1, 4, 6, 4, 6).any(axis=4).any(axis=2)   # (R, 4, 4)
                inner = np.diagonal(blocks, axis1=1, axis2=2)                  # (R, 4)
                thr_hit[rows] |= inner
                dq_ok[rows] &= ~inner
            else:
                # the intermediate rays f*(R_VP): parallel query rays from the four viewpoints
                idir = inter[:, :, 3:6] / np.maximum(
                    np.linalg.norm(inter[:, :, 3:6], axis=2), 1e-300)[:, :, None]
                rows, blocks = far_pairs(idir, inter[:, :, 0:3], dq_ok, ang, dist)
            dq_ok[rows], thr_q[rows] = drop_outlier(blocks, dq_ok[rows], UNIT_CORNERS,
                                                    np.stack([alpha[rows], beta[rows]], 1))
        W, qst = cell_weights(dq_ok, alpha, beta, opt.extrapolation)
        few = qst == FAIL
        # too few interpolants because the thresholds cut them: traced "by the threshold"
        thr = ~(few & (thr_q | np.any(thr_hit & ~dq_ok, axis=1)))
        few &= thr
        sid = sid.reshape(m, 24)
        weights = (W[:, :, None] * w).reshape(m, 24)
        out = np.einsum("nk,nkc->nc", W, inter)
        od, nm = out[:, 3:6], out[:, 9:12]
        lod, lnm = np.linalg.norm(od, axis=1), np.linalg.norm(nm, axis=1)
        blend = (lod > MIN_BLEND_NORM) & (lnm > MIN_BLEND_NORM)
        good = ~few & thr & blend
        kind = np.maximum(dq_st.max(axis=1, where=dq_ok, initial=BILINEAR), qst)
        code = np.select([kind == BILINEAR, kind == TRIANGLE, kind == EXTRA, kind == EXTRAPOLATED],
                         [FULL, REDUCED, EXTRA_S, EXTRAPOLATED_S], TRACED)
        ans[q] = np.where(good, code, TRACED)
        why[q] = np.select([few, ~thr, ~blend], [WHY_USABLE, WHY_THRESHOLD, WHY_BLEND], 0)
        g = np.flatnonzero(good)
        self._fill(res, ans, q[g], o, d, tmax, out[g, 0:3], od[g] / lod[g, None], out[g, 6:9],
                   nm[g] / lnm[g, None], pc[g], self._patch_of(sid[g], weights[g]))
        if opt.null_interp:
            nul = tree.samples.null[flat]
            r = np.flatnonzero(few & np.any(nul & (cls == pc[:, None]), axis=1))
            if len(r):
                self._null(r, o, d, tmax, q, alpha, beta, lx, ly, flat, cls, pc, nul, res,
                           ans, why)
        return n_exact

    def _null(self, r, o, d, tmax, q, alpha, beta, lx, ly, flat, cls, pc, nul, res, ans, why):
        """Rows ``r`` that had too few usable interpolants: the same interpolation with the
        null samples of the query's class as the usable ones (null as a state of its own, like
        a class: four null corners, or three with the query inside their triangle, at both
        levels). Where it succeeds the query ray is answered null (trapped), with the
        interpolated first-hit point and normal for its local illumination."""
        m = len(r)
        use = ((cls[r] == pc[r, None]) & nul[r]).reshape(m, 4, 4)
        w = np.zeros((m, 4, 4))
        st = np.zeros((m, 4), np.int8)
        for k in range(4):
            w[:, k], st[:, k] = cell_weights(use[:, k], lx[r, k], ly[r, k])
        W, qst = cell_weights(st != FAIL, alpha[r], beta[r])
        weights = (W[:, :, None] * w).reshape(m, 16)
        ok = qst != FAIL
        r, weights = r[ok], weights[ok]
        if len(r) == 0:
            return
        vals = self.tree.samples.gather(flat[r])                           # (g, 16, 12)
        pt = np.einsum("nk,nkc->nc", weights, vals[:, :, 6:9])
        nm = np.einsum("nk,nkc->nc", weights, vals[:, :, 9:12])
        ln = np.linalg.norm(nm, axis=1)
        keep = ln > MIN_BLEND_NORM
        r, weights, pt, nm, ln = r[keep], weights[keep], pt[keep], nm[keep], ln[keep]
        rows = q[r]
        ans[rows] = NULL_S
        why[rows] = 0
        self._fill(res, ans, rows, o, d, tmax, pt, np.zeros_like(pt), pt, nm / ln[:, None],
                   pc[r], self._patch_of(flat[r], weights), null=True)

    def _extra(self, fail, k, leaf, lx, ly, usable, pc, w, sid, dq_st, is_extra, lpos):
        """Direction-level interpolation from the extra samples of one/two-interpolant leaves
        (paper 4.3, Figure 12) for DQ ``k`` of rows ``fail``."""
        tree = self.tree
        lf = leaf[fail, k]
        pos = np.searchsorted(tree.ex_node, lf)
        pos = np.minimum(pos, max(len(tree.ex_node) - 1, 0))
        has = (len(tree.ex_node) > 0) & (tree.ex_node[pos] == lf) if len(tree.ex_node) else \
            np.zeros(len(fail), bool)
        rows, pos = fail[has], pos[has]
        if len(rows) == 0:
            return
        kind = tree.ex_kind[pos]
        exc = tree.ex_corner[pos]
        exi = tree.ex_ids[pos]
        exp = tree.ex_pos[pos].astype(np.float64)
        us = usable[rows, k]
        ex_use = (tree.sample_class(exi) == pc[rows, None]) & ~tree.samples.null[exi]
        n = len(rows)
        # candidate triangles: vertex (slot, position); slots 0..3 corners, 4, 5 extras
        tri_slot = np.zeros((n, 2, 3), np.int64)
        tri_pos = np.zeros((n, 2, 3, 2))
        valid = np.zeros((n, 2), bool)
        extra_ids = np.zeros((n, 2), np.int64)
        r = np.arange(n)
        one = kind == 1
        L = np.where(one, exc[:, 0], 0)
        one_ok = one & us[r, L] & (us.sum(1) == 1) & ex_use[:, 0] & ex_use[:, 1]
        # two-interpolant: the usable pair must be (A1, A2) or (B1, B2)
        A = exc[:, 0:2].clip(0)
        B = exc[:, 2:4].clip(0)
        a_side = (kind == 2) & us[r, A[:, 0]] & us[r, A[:, 1]] & (us.sum(1) == 2) \
            & ex_use[:, 0] & ex_use[:, 1]
        b_side = (kind == 2) & us[r, B[:, 0]] & us[r, B[:, 1]] & (us.sum(1) == 2) \
            & ex_use[:, 2] & ex_use[:, 3]
        # one-interpolant: triangle (L, v1, v2)
        tri_slot[one_ok, 0] = np.stack([L[one_ok], np.full(one_ok.sum(), 4),
                                        np.full(one_ok.sum(), 5)], 1)
        extra_ids[one_ok] = exi[one_ok][:, 0:2]
        valid[one_ok, 0] = True
        for side, (c1, c2), (e1, e2) in ((a_side, (A[:, 0], A[:, 1]), (0, 1)),
                                         (b_side, (B[:, 0], B[:, 1]), (2, 3))):
            s_ = np.flatnonzero(side)
            # T1 = (c1, c2, ea), T2 = (c2, ea, eb), ea on the edge from c1, eb from c2
            tri_slot[s_, 0] = np.stack([c1[s_], c2[s_], np.full(len(s_), 4)], 1)
            tri_slot[s_, 1] = np.stack([c2[s_], np.full(len(s_), 4), np.full(len(s_), 5)], 1)
            extra_ids[s_] = exi[s_][:, [e1, e2]]
            valid[s_] = True
        any_ok = valid[:, 0]
        if not np.any(any_ok):
            return
        slot_pos = np.concatenate([np.broadcast_to(UNIT_CORNERS, (n, 4, 2)),
                                   np.zeros((n, 2, 2))], axis=1)
        # positions of the extras used by each row
        e_idx = np.where(one_ok[:, None], [0, 1], np.where(b_side[:, None], [2, 3], [0, 1]))
        slot_pos[:, 4] = exp[r, e_idx[:, 0]]
        slot_pos[:, 5] = exp[r, e_idx[:, 1]]
        tri_pos = slot_pos[r[:, None, None], tri_slot]
        qpt = np.stack([lx[rows, k], ly[rows, k]], 1)
        which, lam, st = pick_triangle(qpt, tri_pos, valid, self.opt.extrapolation)
        st = np.where(any_ok, st, FAIL)
        good = np.flatnonzero(st != FAIL)
        if len(good) == 0:
            return
        gr = rows[good]
        slots = tri_slot[good, which[good]]                               # (g, 3)
        wk = np.zeros((len(good), 6))
        np.add.at(wk, (np.arange(len(good))[:, None], slots), lam[good])
        w[gr, k] = wk
        sid[gr, k, 4:6] = extra_ids[good]
        lpos[gr, k, 4:6] = slot_pos[good, 4:6]
        dq_st[gr, k] = np.where(st[good] == EXTRAPOLATED, EXTRAPOLATED, EXTRA)
        is_extra[gr, k] = True

    # ------------------------------------------------------------------ Bala et al.'s policy
    def _raytree(self, o, d, tmax, q, alpha, beta, leaf, trees, lx, ly, ids, res, ans, why):
        tree = self.tree
        m = len(q)
        flat = ids.reshape(m, 16)
        th = tree.samples.tree[flat]
        cls = tree.sample_class(flat)
        same = np.all(th == th[:, :1], axis=1) & np.all(cls == cls[:, :1], axis=1) \
            & ~np.any(tree.samples.null[flat], axis=1)
        miss = same & (cls[:, 0] == -1)
        ans[q[miss]] = MISS
        interp = same & ~miss
        ans[q[~same]] = TRACED
        why[q[~same]] = WHY_RAYTREE
        g = np.flatnonzero(interp)
        if len(g):
            wdq = np.stack([np.stack([(1 - lx[g, k]) * (1 - ly[g, k]), lx[g, k] * (1 - ly[g, k]),
                                      (1 - lx[g, k]) * ly[g, k], lx[g, k] * ly[g, k]], 1)
                            for k in range(4)], 1)
            wq = np.stack([(1 - alpha[g]) * (1 - beta[g]), alpha[g] * (1 - beta[g]),
                           (1 - alpha[g]) * beta[g], alpha[g] * beta[g]], 1)
            weights = (wq[:, :, None] * wdq).reshape(len(g), 16)
            vals = tree.samples.gather(flat[g])
            scale = tree.dir_forest.cube_scale(leaf[g], trees[g], np.broadcast_to(
                UNIT_CORNERS[:, 0], (len(g), 4, 4)), np.broadcast_to(UNIT_CORNERS[:, 1],
                                                                   (len(g), 4, 4)))
            vals[:, :, 3:6] *= scale.reshape(len(g), 16)[:, :, None]
            out = np.einsum("nk,nkc->nc", weights, vals)
            od, nm = out[:, 3:6], out[:, 9:12]
            ans[q[g]] = FULL
            self._fill(res, ans, q[g], o, d, tmax, out[:, 0:3],
                       od / np.linalg.norm(od, axis=1)[:, None], out[:, 6:9],
                       nm / np.linalg.norm(nm, axis=1)[:, None], cls[g, 0],
                       tree.samples.patch[flat[g, 0]].astype(np.int64))
        return 0

    # ------------------------------------------------------------------ results
    def _patch_of(self, sid, weights):
        """The patch of the heaviest interpolant (a representative patch id)."""
        best = np.argmax(np.abs(weights), axis=1)
        return self.tree.samples.patch[sid[np.arange(len(sid)), best]].astype(np.int64)

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
