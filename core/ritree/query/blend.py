"""Blending: one weighted sum of sample-table rows per ray gives its output ray, first hit,
normal and patch parameters at once (paper 4.1-4.3); answer codes from the kind of
interpolation; null answers (QueryOptions.null_interp)."""

from __future__ import annotations

import numpy as np

from ...rowops import all_last, norm3
from ..answers import (COL, EXTRA_S, EXTRAPOLATED_S, FULL, NULL_S, REDUCED, TRACED, WHY_BLEND,
                       WHY_THRESHOLD, WHY_USABLE)
from ..interp import (BILINEAR, EXTRA, EXTRAPOLATED, FAIL, TRIANGLE, bilinear_weights,
                      cell_weights)
from .fill import Blended, fill, patch_of
from .sets import N_CORNERS, N_DQ, RAY_SLOTS, SET_CORNERS, SET_ITEMS

# Rays per block of a blend: bounds its (rays, 24, COL.N) float32 sample gather to 44 MB.
BLEND_BLOCK = 1 << 15
# Interpolated unit vectors shorter than this before normalization (opposed samples) are not
# trusted: the ray is traced.
MIN_BLEND_NORM = 1e-3


def blend(vals, rows, w) -> np.ndarray:
    """Weighted sums ``w`` (n, K) of the items ``vals[rows]`` (rows (n,) into vals (G, K, C))
    -> (n, C) float64, in blocks of BLEND_BLOCK rays (float32 gather and sums)."""
    n = len(rows)
    out = np.empty((n, vals.shape[-1]))
    for a in range(0, n, BLEND_BLOCK):
        z = min(a + BLEND_BLOCK, n)
        out[a:z] = np.matmul(w[a:z, None, :].astype(np.float32, copy=False),
                             vals.take(rows[a:z], axis=0))[:, 0]
    return out


def unit_rows(out):
    """Blended direction and normal of ``out`` (n, COL.N), their lengths, and which are long
    enough (> MIN_BLEND_NORM) to be normalized."""
    od, nm = out[:, COL.OUT_D], out[:, COL.NORMAL]
    lod, lnm = norm3(od), norm3(nm)
    return od, nm, lod, lnm, (lod > MIN_BLEND_NORM) & (lnm > MIN_BLEND_NORM)


def blend_easy(q, b) -> None:
    """The open rays of units whose 16 corners are all usable and pass the thresholds: every
    ray of them blends its 16 corners bilinearly at both levels, wherever it falls (the
    general path's answers without its per-ray rules); they are closed."""
    u = b.units
    # all 16 usable: two rows of 8 bools each, which rowops tests as one 64-bit word
    easy = (all_last(u.ok[:, :SET_CORNERS].reshape(-1, 2, 8)).all(axis=1) & ~u.far)[b.unit_of]
    if not easy.any():
        return
    e, h = np.flatnonzero(easy), np.flatnonzero(~easy)
    with b.clock("blend"):
        blend_bilinear(q, b, e)
    b.narrow(h)


def blend_bilinear(q, b, e) -> None:
    """Open rays ``e`` (positions in ``b.go``), all 16 corners usable: bilinear weights at both
    levels, one blend (the weights are formed in float32, the blend's precision, so the
    representative patch of two weights equal to float32 rounding may be the other's)."""
    loc, set_of, items = b.loc.take(b.go[e]), b.set_of[e], b.sets.items
    W = bilinear_weights(loc.alpha, loc.beta)                               # (n, 4)
    # W_k times DQ k's bilinear weights, float32 (the blend's precision)
    wr = np.empty((len(loc), N_DQ, N_CORNERS), np.float32)
    for j, wy in ((0, W * (1 - loc.ly)), (2, W * loc.ly)):
        wr[:, :, j] = wy * (1 - loc.lx)
        wr[:, :, j + 1] = wy * loc.lx
    wr = wr.reshape(len(loc), SET_CORNERS)
    out = blend(items.corner_vals, set_of, wr)
    best = np.argmax(wr, axis=1)                     # bilinear weights are >= 0
    od, nm, lod, lnm, ok = unit_rows(out)
    rows = loc.ray
    b.ans[rows] = np.where(ok, FULL, TRACED)
    b.why[rows] = np.where(ok, 0, WHY_BLEND)
    g = np.flatnonzero(ok)
    top = items.ids[set_of[g], best[g]]
    u = b.units
    fill(q, b, Blended(rows=rows[g], oo=out[g, COL.OUT_O], od=od[g] / lod[g, None],
                       pt=out[g, COL.POINT], nm=nm[g] / lnm[g, None], cls=b.pc[e][g],
                       patch=q.table.patch[top].astype(np.int64),
                       mirror=None if u.mirror is None else u.mirror[b.unit_of[e]][g],
                       uvn=out[g, COL.UV], alt_uvn=q.table.vals[top, COL.UV]))


def blend_items(items, set_of, wt, cand):
    """Blend rays ``cand`` (rows of the weights ``wt``, of sets ``set_of``): viewpoint weights
    times each DQ's slot weights over its items; rays without extras blend their 16 corners
    only. Returns (values (c, COL.N), the heaviest item of each ray (c,))."""
    W, w = wt.W, wt.w
    out = np.empty((len(cand), items.corner_vals.shape[-1]))
    best = np.empty(len(cand), np.int64)
    ex = wt.is_extra[cand].any(axis=1)
    k = np.flatnonzero(~ex)
    r = cand[k]
    wr = (W[r, :, None] * w[r, :, :N_CORNERS]).reshape(len(r), SET_CORNERS)
    out[k] = blend(items.corner_vals, set_of[r], wr)
    best[k] = np.argmax(np.abs(wr), axis=1)
    k = np.flatnonzero(ex)
    if len(k):
        r = cand[k]
        wr = np.zeros((len(r), SET_ITEMS))
        np.put_along_axis(wr, wt.item[r].reshape(len(r), RAY_SLOTS),
                          (W[r, :, None] * w[r]).reshape(len(r), RAY_SLOTS), axis=1)
        out[k] = blend(items.corner_vals, set_of[r], wr[:, :SET_CORNERS]) \
            + blend(items.extra_vals, set_of[r], wr[:, SET_CORNERS:])
        best[k] = np.argmax(np.abs(wr), axis=1)
    return out, best


def answer(q, b) -> None:
    """Blend the open rays with their weights (``b.weights``) and answer them: the kind of
    interpolation gives the code; too few interpolants, thresholds or a degenerate blend trace
    the ray; with null_interp a ray short of interpolants may be answered null."""
    wt, items, set_of = b.weights, b.sets.items, b.set_of
    with b.clock("blend"):
        cand = np.flatnonzero(~wt.few & wt.thr)
        out, best = blend_items(items, set_of, wt, cand)
        od, nm, lod, lnm, norm_ok = unit_rows(out)
        blend_ok = np.ones(len(wt.few), bool)
        blend_ok[cand] = norm_ok
        good = ~wt.few & wt.thr & blend_ok
        kind = np.maximum(wt.dq_st.max(axis=1, where=wt.dq_ok, initial=BILINEAR), wt.qst)
        code = np.select([kind == BILINEAR, kind == TRIANGLE, kind == EXTRA,
                          kind == EXTRAPOLATED], [FULL, REDUCED, EXTRA_S, EXTRAPOLATED_S],
                         TRACED)
        rows = wt.loc.ray
        b.ans[rows] = np.where(good, code, TRACED)
        b.why[rows] = np.select([wt.few, ~wt.thr, ~blend_ok],
                                [WHY_USABLE, WHY_THRESHOLD, WHY_BLEND], 0)
        gc = good[cand]
        g = cand[gc]
        top = items.ids[set_of[g], best[gc]]
        u = b.units
        fill(q, b, Blended(rows=rows[g], oo=out[gc, COL.OUT_O], od=od[gc] / lod[gc, None],
                           pt=out[gc, COL.POINT], nm=nm[gc] / lnm[gc, None], cls=b.pc[g],
                           patch=q.table.patch[top].astype(np.int64),
                           mirror=None if u.mirror is None else u.mirror[b.unit_of[g]],
                           uvn=out[gc, COL.UV], alt_uvn=q.table.vals[top, COL.UV]))
        if q.opt.null_interp:
            # units holding a null sample of their class: their failed rays may be null
            ids, cls = b.sets.ids[u.set], b.sets.cls[u.set]
            u_null = np.any(q.table.null[ids] & (cls == u.pc[:, None]), axis=1)
            r = np.flatnonzero(wt.few & u_null[b.unit_of])
            if len(r):
                null(q, b, r)


def null(q, b, r) -> None:
    """Open rays ``r`` that had too few usable interpolants: the same interpolation with the
    null samples of the query's class as the usable ones (null as a state of its own, like a
    class: four null corners, or three with the query inside their triangle, at both levels).
    Where it succeeds the query ray is answered null (trapped), with the interpolated
    first-hit point and normal for its local illumination."""
    tab = q.table
    loc, flat, pc = b.weights.loc.take(r), b.sets.ids[b.set_of[r]], b.pc[r]
    m = len(loc)
    use = ((tab.cls[flat] == pc[:, None]) & tab.null[flat]).reshape(m, N_DQ, N_CORNERS)
    w = np.zeros((m, N_DQ, N_CORNERS))
    st = np.zeros((m, N_DQ), np.int8)
    for k in range(N_DQ):
        w[:, k], st[:, k] = cell_weights(use[:, k], loc.lx[:, k], loc.ly[:, k])
    W, qst = cell_weights(st != FAIL, loc.alpha, loc.beta)
    weights = (W[:, :, None] * w).reshape(m, SET_CORNERS)
    ok = np.flatnonzero(qst != FAIL)
    if len(ok) == 0:
        return
    out = blend(tab.vals[flat[ok]], np.arange(len(ok)), weights[ok])
    pt, nm = out[:, COL.POINT], out[:, COL.NORMAL]
    ln = np.linalg.norm(nm, axis=1)
    keep = ln > MIN_BLEND_NORM
    ok, pt, nm, ln = ok[keep], pt[keep], nm[keep], ln[keep]
    rows = loc.ray[ok]
    b.ans[rows] = NULL_S
    b.why[rows] = 0
    fill(q, b, Blended(rows=rows, oo=pt, od=np.zeros_like(pt), pt=pt, nm=nm / ln[:, None],
                       cls=pc[ok], patch=patch_of(q, flat[ok], weights[ok]), null=True))
