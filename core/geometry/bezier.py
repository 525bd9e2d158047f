"""Rational Bezier pieces of NURBS surfaces, de Casteljau subdivision into flat sub-patches with
conservative boxes, and the batched rational Bezier evaluator (the tracer's Newton kernel).

Control nets are homogeneous: ctrl[..., i, j, :] = (w*x, w*y, w*z, w) with i along u (s) and j
along v (t). Bezier-local coordinates (s, t) are in [0, 1]^2; a piece covers the NURBS parameter
rectangle [u0, u1] x [v0, v1], u = u0 + s (u1 - u0), v = v0 + t (v1 - v0).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from math import comb, cos, radians

import numpy as np

from .knots import insert_homogeneous
from .nurbs import NurbsSurface, homogeneous, partial_orders, rational_derivatives

# Queries per block in bezier_eval: the (block, n_partials, (p+1)(q+1)) tensor weights and the
# block's control nets stay in cache (measured fastest at 4-16k on bicubic nets).
BEZIER_BLOCK = 8192

# Sub-patch flatness: the normal cone of a sub-patch (largest angle between the cone axis and
# any cross product of a u- and a v-difference of its net) must stay below this half-angle,
# i.e. a full cone of about 30 degrees.
CONE_HALF_ANGLE_DEG = 15.0

# Box padding, world units: BOX_PAD_ABS covers rounding of the projected control points near
# the origin, BOX_PAD_REL (relative to the box's coordinate magnitude) their rounding far away
# (a few float64 ulps of x/w).
BOX_PAD_ABS = 1e-9
BOX_PAD_REL = 1e-12

# Cross products of net differences shorter than this fraction of the net size squared
# (dimensionless) are rounding noise of collapsed rows (poles) and carry no direction.
_DEGENERATE_CROSS = 1e-12

# Nets measured per block in subdivide_flat (bounds the (block, p(q+1) (p+1)q, 3) cross
# products to ~15 MiB at bicubic).
_MEASURE_BLOCK = 4096

# Split-direction tie-break, dimensionless: when both directions deviate equally from straight
# (e.g. bilinear nets), the longer side is split.
_LENGTH_TIE = 1e-3


@dataclass
class BezierPieces:
    """Rational Bezier pieces of one NURBS surface, u-major order (k = iu * n_pieces_v + iv)."""

    degree_u: int
    degree_v: int
    ctrl: np.ndarray        # (K, p+1, q+1, 4) homogeneous control nets
    u0: np.ndarray          # (K,) NURBS parameter range of each piece
    u1: np.ndarray
    v0: np.ndarray
    v1: np.ndarray


@dataclass
class SubPatches:
    """Flat sub-patches of Bezier pieces with conservative world-space boxes."""

    ctrl: np.ndarray        # (M, p+1, q+1, 4) homogeneous control nets
    piece: np.ndarray       # (M,) int64 index into BezierPieces
    s0: np.ndarray          # (M,) local range inside the piece, [0, 1]^2 piece coordinates
    s1: np.ndarray
    t0: np.ndarray
    t1: np.ndarray
    lo: np.ndarray          # (M, 3) box containing the sub-patch surface (padded)
    hi: np.ndarray          # (M, 3)


# --------------------------------------------------------------------------- extraction
def _full_multiplicity(pw: np.ndarray, knots: np.ndarray, p: int):
    """Insert every knot value of the domain (its ends included) to multiplicity >= p along axis 0.

    Returns (pw, knots, starts, ends, rows): rows (K, p+1) indexes the control rows of the K
    non-empty spans [starts[k], ends[k]].
    """
    n = pw.shape[0]
    lo, hi = knots[p], knots[n]
    values = np.unique(knots[(knots >= lo) & (knots <= hi)])
    for value in values:
        mult = int(np.count_nonzero(knots == value))
        if mult < p:
            pw, knots = insert_homogeneous(pw, knots, p, value, p - mult)
    span = np.searchsorted(knots, values[:-1], side="right") - 1
    rows = span[:, None] - p + np.arange(p + 1)
    return pw, knots, values[:-1], values[1:], rows


def extract_bezier(surf: NurbsSurface) -> BezierPieces:
    """Split a NURBS surface into rational Bezier pieces by knot insertion (empty spans skipped)."""
    p, q = surf.degree_u, surf.degree_v
    pw = homogeneous(surf)
    ku = np.asarray(surf.knots_u, dtype=np.float64)
    kv = np.asarray(surf.knots_v, dtype=np.float64)
    pw, ku, us, ue, ru = _full_multiplicity(pw, ku, p)
    pwt, kv, vs, ve, rv = _full_multiplicity(pw.transpose(1, 0, 2), kv, q)
    pw = pwt.transpose(1, 0, 2)
    nu, nv = ru.shape[0], rv.shape[0]
    ctrl = pw[ru[:, None, :, None], rv[None, :, None, :]]      # (nu, nv, p+1, q+1, 4)
    return BezierPieces(p, q, np.ascontiguousarray(ctrl.reshape(nu * nv, p + 1, q + 1, 4)),
                        np.repeat(us, nv), np.repeat(ue, nv), np.tile(vs, nu), np.tile(ve, nu))


def piece_to_nurbs_param(pieces: BezierPieces, piece_idx, s, t) -> tuple[np.ndarray, np.ndarray]:
    """NURBS (u, v) of piece-local (s, t) in piece ``piece_idx`` (arrays (N,))."""
    k = np.asarray(piece_idx)
    u = pieces.u0[k] + np.asarray(s) * (pieces.u1[k] - pieces.u0[k])
    v = pieces.v0[k] + np.asarray(t) * (pieces.v1[k] - pieces.v0[k])
    return u, v


def nurbs_to_piece_param(pieces: BezierPieces, u, v):
    """Inverse of piece_to_nurbs_param: (piece_idx, s, t) for NURBS parameters (u, v) (N,).

    Parameters outside the domain are clamped; on a shared piece border the upper piece is
    chosen (the lower one at the domain's upper end).
    """
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    us = np.unique(pieces.u0)
    vs = np.unique(pieces.v0)
    iu = np.clip(np.searchsorted(us, u, side="right") - 1, 0, us.shape[0] - 1)
    iv = np.clip(np.searchsorted(vs, v, side="right") - 1, 0, vs.shape[0] - 1)
    k = iu * vs.shape[0] + iv
    s = np.clip((u - pieces.u0[k]) / (pieces.u1[k] - pieces.u0[k]), 0.0, 1.0)
    t = np.clip((v - pieces.v0[k]) / (pieces.v1[k] - pieces.v0[k]), 0.0, 1.0)
    return k, s, t


# --------------------------------------------------------------------------- subdivision
def split(ctrl: np.ndarray, axis: int, t: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """de Casteljau split of control nets (M, p+1, q+1, 4) at local parameter t along ``axis``
    (1 = u/s, 2 = v/t); returns the nets of [0, t] and [t, 1], reparametrized to [0, 1]."""
    work = np.moveaxis(ctrl, axis, 0).copy()
    n = work.shape[0]
    left = np.empty_like(work)
    right = np.empty_like(work)
    left[0] = work[0]
    right[n - 1] = work[n - 1]
    for k in range(1, n):
        work[:n - k] = (1.0 - t) * work[:n - k] + t * work[1:n - k + 1]
        left[k] = work[0]
        right[n - 1 - k] = work[n - 1 - k]
    return np.moveaxis(left, 0, axis), np.moveaxis(right, 0, axis)


def _net_measures(pts: np.ndarray):
    """Per net (M, p+1, q+1, 3): deviation from the corners' bilinear interpolation, deviation of
    u-rows / v-columns from straight lines, polygon lengths along u / v, and the cosine of the
    normal cone's half-angle (1 where no usable direction exists).

    The cone holds every cross product of a u-difference with a v-difference of the net; for a
    polynomial patch Su x Sv is a non-negative combination of those, so the cone contains every
    normal (for rational patches the projected net makes it an estimate).
    """
    m = pts.shape[0]
    a = np.linspace(0.0, 1.0, pts.shape[1])[None, :, None, None]
    b = np.linspace(0.0, 1.0, pts.shape[2])[None, None, :, None]
    c00, c10 = pts[:, :1, :1], pts[:, -1:, :1]
    c01, c11 = pts[:, :1, -1:], pts[:, -1:, -1:]
    bil = (1 - a) * ((1 - b) * c00 + b * c01) + a * ((1 - b) * c10 + b * c11)
    dev = np.linalg.norm(pts - bil, axis=-1).max(axis=(1, 2))
    line_u = (1 - a) * pts[:, :1] + a * pts[:, -1:]
    line_v = (1 - b) * pts[:, :, :1] + b * pts[:, :, -1:]
    dev_u = np.linalg.norm(pts - line_u, axis=-1).max(axis=(1, 2))
    dev_v = np.linalg.norm(pts - line_v, axis=-1).max(axis=(1, 2))
    diff_u = np.diff(pts, axis=1)
    diff_v = np.diff(pts, axis=2)
    len_u = np.linalg.norm(diff_u, axis=-1).sum(axis=1).max(axis=1)
    len_v = np.linalg.norm(diff_v, axis=-1).sum(axis=2).max(axis=1)
    nrm = np.cross(diff_u.reshape(m, -1, 1, 3), diff_v.reshape(m, 1, -1, 3)).reshape(m, -1, 3)
    size = np.maximum(len_u, len_v)
    length = np.linalg.norm(nrm, axis=-1)
    usable = length > _DEGENERATE_CROSS * (size * size)[:, None]
    unit = nrm / np.where(usable, length, 1.0)[..., None]
    unit[~usable] = 0.0
    axis = unit.sum(axis=1)
    axis /= np.maximum(np.linalg.norm(axis, axis=-1), np.finfo(np.float64).tiny)[:, None]
    cosines = np.where(usable, np.einsum("mkc,mc->mk", unit, axis), 1.0)
    return dev, dev_u, dev_v, len_u, len_v, cosines.min(axis=1)


def normal_cone_half_angle(ctrl: np.ndarray) -> np.ndarray:
    """(M,) half-angle (radians) of the normal cone of homogeneous nets (M, p+1, q+1, 4):
    a bound for polynomial nets, an estimate for rational ones (see _net_measures)."""
    pts = ctrl[..., :3] / ctrl[..., 3:]
    return np.arccos(np.clip(_net_measures(pts)[5], -1.0, 1.0))


def subdivide_flat(pieces: BezierPieces, flat_tol: float, max_depth: int = 12) -> SubPatches:
    """Subdivide every piece until each sub-patch's control net deviates from the bilinear
    interpolation of its corner control points by <= flat_tol (world units) and its normal cone
    is narrower than about 30 degrees, or max_depth splits were made. All sub-patches of a level
    are split at once; the direction split is the less straight one (ties: the longer one)."""
    flat_tol = float(flat_tol)
    if not flat_tol > 0:
        raise ValueError(f"flat_tol: must be > 0, got {flat_tol!r}")
    if int(max_depth) != max_depth or max_depth < 0:
        raise ValueError(f"max_depth: must be an integer >= 0, got {max_depth!r}")
    cos_limit = cos(radians(CONE_HALF_ANGLE_DEG))
    ctrl = pieces.ctrl
    k = ctrl.shape[0]
    piece = np.arange(k)
    s0, s1, t0, t1 = np.zeros(k), np.ones(k), np.zeros(k), np.ones(k)
    done: list[tuple[np.ndarray, ...]] = []
    for depth in range(max_depth + 1):
        pts = ctrl[..., :3] / ctrl[..., 3:]
        dev, dev_u, dev_v, len_u, len_v, cos_min = (
            np.concatenate(x) for x in zip(*(_net_measures(pts[i:i + _MEASURE_BLOCK])
                                             for i in range(0, pts.shape[0], _MEASURE_BLOCK))))
        final = (dev <= flat_tol) & (cos_min >= cos_limit)
        if depth == max_depth:
            final[:] = True
        done.append((ctrl[final], piece[final], s0[final], s1[final], t0[final], t1[final],
                     pts[final]))
        keep = ~final
        if not keep.any():
            break
        ctrl, piece, s0, s1, t0, t1 = (x[keep] for x in (ctrl, piece, s0, s1, t0, t1))
        su = (dev_u + _LENGTH_TIE * len_u >= dev_v + _LENGTH_TIE * len_v)[keep]
        sm = 0.5 * (s0 + s1)
        tm = 0.5 * (t0 + t1)
        lu, ru = split(ctrl[su], 1)
        lv, rv = split(ctrl[~su], 2)
        ctrl = np.concatenate([lu, ru, lv, rv])
        piece = np.concatenate([piece[su], piece[su], piece[~su], piece[~su]])
        s0, s1, t0, t1 = (
            np.concatenate([s0[su], sm[su], s0[~su], s0[~su]]),
            np.concatenate([sm[su], s1[su], s1[~su], s1[~su]]),
            np.concatenate([t0[su], t0[su], t0[~su], tm[~su]]),
            np.concatenate([t1[su], t1[su], tm[~su], t1[~su]]))
    ctrl, piece, s0, s1, t0, t1, pts = (np.concatenate(x) for x in zip(*done))
    lo = pts.min(axis=(1, 2))
    hi = pts.max(axis=(1, 2))
    pad = BOX_PAD_ABS + BOX_PAD_REL * np.maximum(np.abs(lo), np.abs(hi)).max(axis=1)
    return SubPatches(ctrl, piece.astype(np.int64), s0, s1, t0, t1,
                      lo - pad[:, None], hi + pad[:, None])


# --------------------------------------------------------------------------- evaluation
@lru_cache(maxsize=None)
def _basis_plan(p: int, d: int):
    """For _bernstein: power indices (xi, yi) and binomials cc (K, 1) of every B_i^m(x) =
    C(m, i) x^i (1-x)^(m-i), m = p - k for k = 0..min(d, p) concatenated, and the matrix
    ((d+1)(p+1), K) taking them to the derivatives D^k B^p_i = p!/(p-k)! sum_j (-1)^(k-j)
    C(k, j) B^(p-k)_(i-j) (zero for k > p)."""
    xi, yi, cc, blocks = [], [], [], []
    for k in range(min(d, p) + 1):
        m = p - k
        xi += list(range(m + 1))
        yi += [m - i for i in range(m + 1)]
        cc += [comb(m, i) for i in range(m + 1)]
        blocks.append((k, m))
    mat = np.zeros((len(xi), d + 1, p + 1))
    row = 0
    for k, m in blocks:
        scale = float(np.prod(np.arange(m + 1, p + 1)))
        for i in range(p + 1):
            for j in range(k + 1):
                if 0 <= i - j <= m:
                    mat[row + i - j, k, i] += scale * (-1) ** (k - j) * comb(k, j)
        row += m + 1
    plan = (np.array(xi), np.array(yi), np.array(cc, np.float64)[:, None],
            np.ascontiguousarray(mat.reshape(len(xi), (d + 1) * (p + 1)).T))
    for a in plan:
        a.flags.writeable = False                   # shared by every call (cached)
    return plan


def _bernstein(x: np.ndarray, p: int, d: int) -> np.ndarray:
    """Bernstein polynomials B_i^p(x) and their derivatives up to order d: (n, d+1, p+1) view.
    Each B_i^m is a product of powers (no cancellation in the values; the derivatives'
    alternating sums cancel as in any Bernstein form), the derivatives one matrix product of
    them: a fixed handful of array operations, whatever p (small batches pay little)."""
    xi, yi, cc, matT = _basis_plan(p, d)
    pw = np.empty((2, p + 1, len(x)))               # x^j and (1-x)^j, j = 0..p (row-wise)
    pw[:, 0] = 1.0
    if p:
        pw[0, 1] = x
        np.subtract(1.0, x, out=pw[1, 1])
    for j in range(2, p + 1):
        np.multiply(pw[:, j - 1], pw[:, 1], out=pw[:, j])
    basis = pw[0][xi] * pw[1][yi] * cc                                      # (K, n)
    return (matT @ basis).reshape(d + 1, p + 1, len(x)).transpose(2, 0, 1)


def tensor_weights(s, t, p: int, q: int, derivatives: int = 1) -> np.ndarray:
    """Tensor-product Bernstein weights of a degree (p, q) net at (s, t) (n,), for each
    partial of ``partial_orders(derivatives)``: (n, partials, (p+1)(q+1)), so that
    ``tensor_weights(...) @ net.reshape(n, -1, c)`` evaluates every partial of a net of
    c-vectors at once."""
    orders = partial_orders(derivatives)
    bu = _bernstein(s, p, derivatives)[:, [k for k, _ in orders]]
    bv = _bernstein(t, q, derivatives)[:, [l for _, l in orders]]
    return np.einsum("nka,nkb->nkab", bu, bv).reshape(len(s), len(orders), -1)


def bezier_eval(ctrl: np.ndarray, s, t, derivatives: int = 1,
                index=None) -> tuple[np.ndarray, ...]:
    """Rational Bezier points and partials at local coordinates (s, t) in [0, 1]^2.

    ctrl (N, p+1, q+1, 4) homogeneous nets, one per query; or, with ``index`` (N,) int, ctrl is
    any (M, p+1, q+1, 4) stack and query n uses ctrl[index[n]] (no (N, ...) gather in memory).
    Returns Cartesian (N, 3) arrays: derivatives=0 -> (S,), 1 -> (S, Ss, St),
    2 -> (S, Ss, St, Sss, Sst, Stt), derivatives per unit of local coordinate.
    Per block: Bernstein bases, their tensor products for every partial (n, K, (p+1)(q+1)),
    then one batched matmul with the nets (measured fastest against einsum contractions and
    per-index loops) and the quotient rule.
    """
    orders = partial_orders(derivatives)
    s = np.asarray(s, dtype=np.float64).reshape(-1)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    n_all = s.shape[0]
    rows = n_all if index is None else np.shape(index)[0]
    if t.shape[0] != n_all or rows != n_all:
        raise ValueError(f"s, t, {'ctrl' if index is None else 'index'}: need the same length, "
                         f"got {n_all}, {t.shape[0]}, {rows}")
    p, q = ctrl.shape[1] - 1, ctrl.shape[2] - 1
    npart = len(orders)
    out = [np.empty((n_all, 3)) for _ in range(npart)]
    block = max(1, min(BEZIER_BLOCK, n_all))
    hbuf = np.empty((block, npart, 4))
    for b in range(0, n_all, block):
        e = min(b + block, n_all)
        n = e - b
        weights = tensor_weights(s[b:e], t[b:e], p, q, derivatives)
        nets = ctrl[b:e] if index is None else ctrl[index[b:e]]
        h = np.matmul(weights, nets.reshape(n, -1, 4), out=hbuf[:n])
        for dst, src in zip(out, rational_derivatives([h[:, i] for i in range(npart)],
                                                      derivatives)):
            dst[b:e] = src
    return tuple(out)
