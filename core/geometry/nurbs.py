"""Rational NURBS surfaces: the data type (evaluation lives beside it, vectorized over (u, v)).

Convention: ``points[i, j]`` is the Cartesian control point with index i along u and j along v,
``weights[i, j] > 0`` its weight; the surface is
    S(u, v) = sum N_i,p(u) N_j,q(v) w_ij P_ij / sum N_i,p(u) N_j,q(v) w_ij
on the domain [knots_u[p], knots_u[n_u]] x [knots_v[q], knots_v[n_v]].
Cyclic surfaces are represented unrolled (wrapped control points + periodic knots), so every
surface here is an ordinary NURBS surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class NurbsSurface:
    degree_u: int
    degree_v: int
    knots_u: np.ndarray      # (n_u + degree_u + 1,) non-decreasing float64
    knots_v: np.ndarray      # (n_v + degree_v + 1,)
    points: np.ndarray       # (n_u, n_v, 3) float64 Cartesian
    weights: np.ndarray      # (n_u, n_v) float64, > 0

    @property
    def domain(self) -> tuple[float, float, float, float]:
        """(u0, u1, v0, v1) parameter domain."""
        p, q = self.degree_u, self.degree_v
        nu, nv = self.points.shape[:2]
        return (float(self.knots_u[p]), float(self.knots_u[nu]),
                float(self.knots_v[q]), float(self.knots_v[nv]))


# Points evaluated per block: bounds the (block, p+1, q+1, 4) gathered control nets (~8 MiB at
# bicubic) so memory stays flat for any N.
EVAL_BLOCK = 16384

# Degenerate-normal threshold, dimensionless. Partials are first rescaled to length units
# (Su * (u1 - u0), Suv * (u1 - u0) * (v1 - v0), ...) and cross products compared with D^2, D the
# control net's bounding-box diagonal. Below NORMAL_EPS the relative rounding error of
# Su x Sv (~1e-16 / NORMAL_EPS) exceeds the error of the first-order limit normal used instead
# (~NORMAL_EPS, the distance to the degenerate point); 1e-8 balances the two at ~1e-8.
NORMAL_EPS = 1e-8


def _basis_derivatives(knots: np.ndarray, p: int, span: np.ndarray, x: np.ndarray,
                       d: int) -> np.ndarray:
    """B-spline basis functions N_{span-p+r, p}(x) and their derivatives up to order d.

    Returns (d+1, p+1, N): [k, r] is the k-th derivative of N_{span-p+r}. Vectorized form of the
    triangular scheme (Piegl & Tiller A2.3); every knot difference used is >= the span length > 0.
    """
    n = x.shape[0]
    ndu = np.empty((p + 1, p + 1, n))       # upper triangle: basis values, lower: knot gaps
    ndu[0, 0] = 1.0
    left = np.empty((p + 1, n))
    right = np.empty((p + 1, n))
    for j in range(1, p + 1):
        left[j] = x - knots[span + 1 - j]
        right[j] = knots[span + j] - x
        saved = np.zeros(n)
        for r in range(j):
            ndu[j, r] = right[r + 1] + left[j - r]
            temp = ndu[r, j - 1] / ndu[j, r]
            ndu[r, j] = saved + right[r + 1] * temp
            saved = left[j - r] * temp
        ndu[j, j] = saved
    ders = np.zeros((d + 1, p + 1, n))
    ders[0] = ndu[:, p]
    a = np.empty((2, p + 1, n))
    for r in range(p + 1):
        s1, s2 = 0, 1
        a[0, 0] = 1.0
        for k in range(1, min(d, p) + 1):
            dd = np.zeros(n)
            rk, pk = r - k, p - k
            if r >= k:
                a[s2, 0] = a[s1, 0] / ndu[pk + 1, rk]
                dd += a[s2, 0] * ndu[rk, pk]
            j1 = 1 if rk >= -1 else -rk
            j2 = k - 1 if r - 1 <= pk else p - r
            for j in range(j1, j2 + 1):
                a[s2, j] = (a[s1, j] - a[s1, j - 1]) / ndu[pk + 1, rk + j]
                dd += a[s2, j] * ndu[rk + j, pk]
            if r <= pk:
                a[s2, k] = -a[s1, k - 1] / ndu[pk + 1, r]
                dd += a[s2, k] * ndu[r, pk]
            ders[k, r] = dd
            s1, s2 = s2, s1
    factor = float(p)
    for k in range(1, min(d, p) + 1):
        ders[k] *= factor
        factor *= p - k
    return ders


def _find_span(knots: np.ndarray, p: int, n: int, x: np.ndarray) -> np.ndarray:
    """Index i with knots[i] <= x < knots[i+1] (x already clamped to the domain); at the domain's
    upper end the last non-empty span."""
    last = int(np.searchsorted(knots, knots[n], side="left")) - 1
    return np.clip(np.searchsorted(knots, x, side="right") - 1, p, last)


def homogeneous(surf: NurbsSurface) -> np.ndarray:
    """(n_u, n_v, 4) homogeneous control points (w*x, w*y, w*z, w)."""
    w = surf.weights[..., None]
    return np.concatenate([surf.points * w, w], axis=-1)


def rational_derivatives(h: list[np.ndarray], d: int) -> tuple[np.ndarray, ...]:
    """Cartesian S and its partials from homogeneous partials by the quotient rule.

    h holds the homogeneous (N, 4) partials in the order A, Au, Av, Auu, Auv, Avv (as many as d
    needs); returns S, Su, Sv[, Suu, Suv, Svv], each (N, 3).
    """
    w = h[0][:, 3:]
    s = h[0][:, :3] / w
    if d == 0:
        return (s,)
    wu, wv = h[1][:, 3:], h[2][:, 3:]
    su = (h[1][:, :3] - wu * s) / w
    sv = (h[2][:, :3] - wv * s) / w
    if d == 1:
        return s, su, sv
    suu = (h[3][:, :3] - 2.0 * wu * su - h[3][:, 3:] * s) / w
    suv = (h[4][:, :3] - wu * sv - wv * su - h[4][:, 3:] * s) / w
    svv = (h[5][:, :3] - 2.0 * wv * sv - h[5][:, 3:] * s) / w
    return s, su, sv, suu, suv, svv


def partial_orders(derivatives: int) -> tuple[tuple[int, int], ...]:
    """(k, l) orders (d^k/du^k d^l/dv^l) of the partials up to total order ``derivatives``
    (0, 1 or 2), in the order S, Su, Sv, Suu, Suv, Svv used by every evaluator."""
    if derivatives not in (0, 1, 2):
        raise ValueError(f"derivatives: must be 0, 1 or 2, got {derivatives!r}")
    count = (derivatives + 1) * (derivatives + 2) // 2
    return ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))[:count]


def evaluate(surf: NurbsSurface, u, v, derivatives: int = 1) -> tuple[np.ndarray, ...]:
    """Points and partial derivatives at parameters (u, v), each (N,), clamped to the domain.

    derivatives=0 -> (S,); 1 -> (S, Su, Sv); 2 -> (S, Su, Sv, Suu, Suv, Svv); each (N, 3) in
    world units per parameter unit to the derivative's order. Exact for rational surfaces.
    """
    orders = partial_orders(derivatives)
    u = np.atleast_1d(np.asarray(u, dtype=np.float64))
    v = np.atleast_1d(np.asarray(v, dtype=np.float64))
    u, v = np.broadcast_arrays(u, v)
    p, q = surf.degree_u, surf.degree_v
    nu, nv = surf.points.shape[:2]
    u0, u1, v0, v1 = surf.domain
    ku = np.asarray(surf.knots_u, dtype=np.float64)
    kv = np.asarray(surf.knots_v, dtype=np.float64)
    pw = homogeneous(surf)
    out = [np.empty((u.shape[0], 3)) for _ in orders]
    ar_u, ar_v = np.arange(p + 1), np.arange(q + 1)
    for b in range(0, u.shape[0], EVAL_BLOCK):
        uu = np.clip(u[b:b + EVAL_BLOCK], u0, u1)
        vv = np.clip(v[b:b + EVAL_BLOCK], v0, v1)
        su_ = _find_span(ku, p, nu, uu)
        sv_ = _find_span(kv, q, nv, vv)
        bu = _basis_derivatives(ku, p, su_, uu, derivatives)     # (d+1, p+1, n)
        bv = _basis_derivatives(kv, q, sv_, vv, derivatives)
        iu = su_[:, None] - p + ar_u                             # (n, p+1)
        iv = sv_[:, None] - q + ar_v
        net = pw[iu[:, :, None], iv[:, None, :]]                 # (n, p+1, q+1, 4)
        by_v = [np.einsum("nabc,bn->nac", net, bv[l]) for l in range(derivatives + 1)]
        h = [np.einsum("nac,an->nc", by_v[l], bu[k]) for k, l in orders]
        for dst, src in zip(out, rational_derivatives(h, derivatives)):
            dst[b:b + EVAL_BLOCK] = src
    return tuple(out)


def limit_normals(s_u, s_v, s_uu, s_uv, s_vv, a, b, scale) -> np.ndarray:
    """Unit normals from first and second partials (N, 3), with limits at degenerate points.

    Regular points: normalize(Su x Sv). Where that cross product is degenerate (relative to
    ``scale``, the squared length unit of the partials), the first non-degenerate Taylor term of
    Su x Sv along the parameter direction (a, b) (each +-1, pointing into the domain) is used:
        Su x (a Suv + b Svv) + (a Suu + b Suv) x Sv,   then   (a Suu + b Suv) x (a Suv + b Svv).
    These are the limits of the neighbouring regular normals approached along (a, b), so the
    orientation matches them. A point with all of these zero (a surface collapsed to a curve or
    a point) gets +z. Partials must already be scaled to comparable (length) units.
    """
    a = a[:, None]
    b = b[:, None]
    n = np.cross(s_u, s_v)
    tu = a * s_uu + b * s_uv          # d/dstep of Su along (a, b)
    tv = a * s_uv + b * s_vv          # d/dstep of Sv along (a, b)
    tol = NORMAL_EPS * scale
    for candidate in (np.cross(s_u, tv) + np.cross(tu, s_v), np.cross(tu, tv)):
        weak = np.linalg.norm(n, axis=1) <= tol
        n[weak] = candidate[weak]
    length = np.linalg.norm(n, axis=1)
    dead = length <= tol
    n[dead] = (0.0, 0.0, 1.0)
    length[dead] = 1.0
    return n / length[:, None]


def normals(surf: NurbsSurface, u, v) -> np.ndarray:
    """Unit normals (N, 3) = normalize(Su x Sv), with limit normals at poles and collapsed edges
    (see ``limit_normals``). u, v (N,) are clamped to the domain. Never NaN for valid input."""
    _, s_u, s_v, s_uu, s_uv, s_vv = evaluate(surf, u, v, derivatives=2)
    u0, u1, v0, v1 = surf.domain
    du, dv = u1 - u0, v1 - v0
    u = np.clip(np.broadcast_to(np.asarray(u, dtype=np.float64), (s_u.shape[0],)), u0, u1)
    v = np.clip(np.broadcast_to(np.asarray(v, dtype=np.float64), (s_u.shape[0],)), v0, v1)
    a = np.where(u - u0 <= u1 - u, 1.0, -1.0)
    b = np.where(v - v0 <= v1 - v, 1.0, -1.0)
    pts = surf.points.reshape(-1, 3)
    diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    return limit_normals(s_u * du, s_v * dv, s_uu * du * du, s_uv * du * dv, s_vv * dv * dv,
                         a, b, max(diag, np.finfo(np.float64).tiny) ** 2)
