"""Interpolation weights shared by the bake (midpoint test) and the renderer (paper 4.1, 4.2,
4.3, 5.1, 5.3): bilinear over four usable corners, barycentric over three, barycentric over the
extra samples of one-/two-interpolant cells, the extrapolation threshold, and the pairwise
angle/distance thresholds (far pairs make interpolants unusable: an outlier is dropped).
Everything works on whole arrays of queries.

Cell-local coordinates (lx, ly) are in [0, 1]^2; corners are ordered (0,0), (1,0), (0,1), (1,1).
"""

from __future__ import annotations

import numpy as np

UNIT_CORNERS = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])

# Status codes of an interpolation (ordered: a larger code is a weaker kind of answer).
FAIL, BILINEAR, TRIANGLE, EXTRA, EXTRAPOLATED = 0, 1, 2, 3, 4

# Barycentric coordinates down to -INSIDE_SLACK count as inside (queries exactly on an edge
# of the triangle, rounding of cell-local coordinates ~1e-16).
INSIDE_SLACK = 1e-12
# Triangles whose doubled area (cell units, cell = 1 x 1) is below this are degenerate
# (collinear extra samples, an extra sample on its corner): no weights, the ray is traced.
DEGENERATE_AREA = 1e-9
# Rows per block of the pairwise threshold test: its (rows, K, K) Gram matrices stay in cache
# (blocks of 4096 rows ran 4x slower than 512).
PAIR_CHUNK = 512
# Relative rounding allowance of a squared distance from the Gram matrix: identical points
# are never "far", even at a zero threshold.
PAIR_ROUND = 1e-13


def bilinear_weights(lx, ly) -> np.ndarray:
    """Bilinear weights of the four corners on a new last axis: lx, ly (...) -> (..., 4)."""
    return np.stack([(1 - lx) * (1 - ly), lx * (1 - ly), (1 - lx) * ly, lx * ly], axis=-1)


def barycentric(q, tri):
    """Barycentric coordinates (N, 3) of points q (N, 2) in triangles tri (N, 3, 2), and a mask
    of non-degenerate triangles (degenerate rows get zeros)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    e1, e2, w = b - a, c - a, q - a
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    ok = np.abs(det) > DEGENERATE_AREA
    safe = np.where(ok, det, 1.0)
    l1 = (w[:, 0] * e2[:, 1] - w[:, 1] * e2[:, 0]) / safe
    l2 = (e1[:, 0] * w[:, 1] - e1[:, 1] * w[:, 0]) / safe
    lam = np.stack([1 - l1 - l2, l1, l2], axis=1)
    return np.where(ok[:, None], lam, 0.0), ok


def triangle_status(lam, ok, extrapolation):
    """Status of barycentric answers: TRIANGLE inside, EXTRAPOLATED outside but allowed
    (``extrapolation`` is None = never, else the largest allowed distance below zero of the
    smallest barycentric coordinate), FAIL otherwise."""
    mn = lam.min(axis=1)
    inside = ok & (mn >= -INSIDE_SLACK)
    st = np.where(inside, TRIANGLE, FAIL)
    if extrapolation is not None:
        st = np.where(ok & ~inside & (mn >= -float(extrapolation)), EXTRAPOLATED, st)
    return st


def cell_weights(usable, lx, ly, extrapolation=None):
    """Weights (N, 4) over a cell's corners from the usable ones: four -> bilinear, three ->
    barycentric on their triangle (with the extrapolation rule), fewer -> FAIL (zero weights).
    Returns (weights, status)."""
    usable = np.asarray(usable, bool)
    cnt = np.count_nonzero(usable, axis=1)
    four = cnt == 4
    w = bilinear_weights(lx, ly) * four[:, None]
    status = np.where(four, BILINEAR, FAIL).astype(np.int8)
    three = np.flatnonzero(cnt == 3)
    if len(three):
        idx = np.argsort(~usable[three], axis=1, kind="stable")[:, :3]   # the usable corners
        lam, ok = barycentric(np.stack([lx[three], ly[three]], 1), UNIT_CORNERS[idx])
        st = triangle_status(lam, ok, extrapolation)
        good = st != FAIL
        rows = three[good]
        w[rows[:, None], idx[good]] = lam[good]
        status[three] = st
    return w, status


def pick_triangle(q, tris, valid, extrapolation=None):
    """Barycentric interpolation over the first of two candidate triangles that contains q,
    else extrapolation over the last valid one (the paper's Figure 12(c) regions).

    q (N, 2); tris (N, 2, 3, 2) vertex positions; valid (N, 2) which candidates exist.
    Returns (which (N,) 0/1, lam (N, 3), status)."""
    n = len(q)
    which = np.zeros(n, np.int64)
    lam = np.zeros((n, 3))
    status = np.full(n, FAIL, np.int8)
    lams, oks = [], []
    for k in range(2):
        l_k, ok_k = barycentric(q, tris[:, k])
        lams.append(l_k)
        oks.append(ok_k & valid[:, k])
    # inside one of them
    for k in (1, 0):
        inside = oks[k] & (lams[k].min(axis=1) >= -INSIDE_SLACK)
        which = np.where(inside, k, which)
        lam = np.where(inside[:, None], lams[k], lam)
        status = np.where(inside, TRIANGLE, status)
    if extrapolation is not None:
        last = np.where(valid[:, 1], 1, 0)
        rows = np.arange(n)
        l_last = np.stack(lams, 1)[rows, last]
        ok_last = np.stack(oks, 1)[rows, last]
        ext = (status == FAIL) & ok_last & (l_last.min(axis=1) >= -float(extrapolation))
        which = np.where(ext, last, which)
        lam = np.where(ext[:, None], l_last, lam)
        status = np.where(ext, EXTRAPOLATED, status)
    return which, lam, status


def angle_between(a, b):
    """Angle (radians) between unit vectors along the last axis, accurate for tiny angles."""
    return 2.0 * np.arctan2(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))


def _pair_tests(dirs, origins, used, max_angle, max_dist):
    """Per metric (directions by chord, origins by distance; None: no limit): (points, limit,
    centroid of the used points (N, 3), unsure (N,)). A row whose used points all lie within
    limit/2 of their centroid has no far pair (triangle inequality): it is not unsure."""
    tests = []
    cnt = np.maximum(used.sum(axis=1), 1)
    for pts, lim in ((dirs, None if max_angle is None else 2.0 * np.sin(min(max_angle, np.pi) / 2)),
                     (origins, max_dist)):
        if lim is None:
            continue
        c = np.einsum("nk,nkc->nc", used.astype(np.float64), pts) / cnt[:, None]
        r = np.where(used, np.linalg.norm(pts - c[:, None, :], axis=2), 0.0).max(axis=1)
        tests.append((pts, lim, c, r > 0.5 * lim))
    return tests


def may_have_far_pairs(dirs, origins, used, max_angle=None, max_dist=None) -> np.ndarray:
    """(N,) rows of interpolants (N, K) that may hold a far pair (see ``far_pairs``); a row
    that may not has none among any subset of its used interpolants either."""
    used = np.asarray(used, bool)
    tests = _pair_tests(dirs, origins, used, max_angle, max_dist)
    return np.any([t[3] for t in tests], axis=0) if tests else np.zeros(len(used), bool)


def far_pairs(dirs, origins, used, max_angle=None, max_dist=None):
    """Paper 5.3: the pairs of used interpolants (N, K) whose output directions are more than
    ``max_angle`` radians apart or whose output origins are more than ``max_dist`` apart
    (None: no limit). Returns (rows (R,), far (R, K, K)): only ``rows`` can hold a far pair.

    Directions are compared by chord length (a metric equivalent to the angle). Rows whose
    used points all lie near their centroid skip the pairwise test, so smooth rows cost O(K)."""
    used = np.asarray(used, bool)
    n, k = used.shape
    tests = _pair_tests(dirs, origins, used, max_angle, max_dist)
    rows = np.flatnonzero(np.any([t[3] for t in tests], axis=0)) if tests else \
        np.zeros(0, np.int64)
    far = np.zeros((len(rows), k, k), bool)
    for pts, lim, c, unsure in tests:
        for a in range(0, len(rows), PAIR_CHUNK):
            blk = slice(a, a + PAIR_CHUNK)
            sel = rows[blk][unsure[rows[blk]]]
            if len(sel) == 0:
                continue
            # squared distances by the Gram matrix about the centroid (small coordinates: the
            # rounding of |p|^2 + |q|^2 - 2 p.q stays ~1e-16 of the spread squared)
            p = (pts[sel] - c[sel, None, :]).astype(np.float64)
            u = used[sel]
            sq = np.einsum("nkc,nkc->nk", p, p)
            d2 = sq[:, :, None] + sq[:, None, :] - 2.0 * np.matmul(p, p.transpose(0, 2, 1))
            spread = np.where(u, sq, 0.0).max(axis=1)       # of the used points only
            hit = (d2 > lim * lim + PAIR_ROUND * (spread + 1e-300)[:, None, None]) \
                & u[:, :, None] & u[:, None, :]
            far[a + np.flatnonzero(unsure[rows[blk]])] |= hit
    return rows, far


def drop_outlier(far, used, pos, q):
    """Paper 5.3: interpolants in a far pair are not usable. Of the used interpolants (N, K)
    the one in most far pairs is dropped - on a tie the one farthest from the query point q
    (N, 2) (positions ``pos`` (K, 2) or (N, K, 2)), whose loss leaves the query inside the
    triangle of the other three corners of a cell. A row still holding a far pair after that
    one drop loses all its interpolants. Returns (usable (N, K), changed (N,) rows that had a
    far pair)."""
    f = far & used[:, :, None] & used[:, None, :]
    deg = f.sum(axis=2)
    bad = deg.any(axis=1)
    if not bad.any():
        return used, bad
    dist = np.linalg.norm(np.asarray(pos) - q[:, None, :], axis=-1)
    score = np.where(used, deg * (1.0 + dist.max()) + dist, -1.0)
    out = used.copy()
    rows = np.flatnonzero(bad)
    out[rows, np.argmax(score[rows], axis=1)] = False
    left = np.any(f & out[:, :, None] & out[:, None, :], axis=(1, 2))
    out[left] = False
    return out, bad


def drop_outlier_units(far, used, unit, pos, q):
    """drop_outlier(far[unit], used[unit], pos, q) for rows that share their far pairs and
    used interpolants with a unit (far (U, K, K), used (U, K), unit (N,)): degrees and what a
    drop leaves are found once per unit, only the tie-break by distance per row."""
    f = far & used[:, :, None] & used[:, None, :]
    deg = f.sum(axis=2)                                                    # (U, K)
    bad_u = deg.any(axis=1)
    bad = bad_u[unit]
    out = used[unit]
    rows = np.flatnonzero(bad)
    if len(rows) == 0:
        return out, bad
    uu = unit[rows]
    top = used & (deg == deg.max(axis=1, keepdims=True))                   # most far pairs
    dist = np.linalg.norm(np.asarray(pos) - q[rows, None, :], axis=-1)
    drop = np.argmax(np.where(top[uu], dist, -1.0), axis=1)
    # far pairs left once interpolant j is dropped: all but row j and column j
    left = (deg.sum(axis=1, keepdims=True) - deg - f.sum(axis=1)
            + np.diagonal(f, axis1=1, axis2=2)) > 0                           # (U, K)
    out[rows, drop] = False
    out[rows[left[uu, drop]]] = False
    return out, bad
