"""Knot vectors: surface validation, Boehm knot insertion and Blender's knot rule.

Knot vectors are plain float64 arrays; a surface of degree p with n control points in a
direction has n + p + 1 knots and the domain [knots[p], knots[n]] (see ``nurbs``).
"""

from __future__ import annotations

import dataclasses
from numbers import Integral

import numpy as np

from .nurbs import NurbsSurface, homogeneous

MAX_DEGREE = 5          # highest degree accepted (Blender's maximum order is 6)
# The range of weights and knots the tracer carries in float64 (docs/scene-format.md).
# Weights are scale-free (a common factor leaves the surface unchanged), so bounding them costs
# nothing: within a patch max/min <= MAX_WEIGHT_RATIO, as the rational derivatives grow like
# the ratio (first order) and its square (second). Measured on the sample sphere reparametrized
# to weight ratio r (same surface): 1.4e6 traces exactly like r = 2, 1.4e10 loses hits, 1.4e20
# divides by zero. MIN_WEIGHT keeps weighted sums normal floats (a 5e-324 weight is 0 * 0.7).
MAX_WEIGHT_RATIO = 1e6
MIN_WEIGHT = 1e-12
# Knots (parameter units): basis derivatives grow like 1/h per order for a span of length h,
# and normals take cross products of second derivatives and their squared norms, i.e. h^-8.
# A domain of at least MIN_KNOT_DOMAIN, whose non-empty spans are at least MIN_SPAN_FRACTION of
# it, keeps every derivative below ~1e61 (|points| <= 1e5, weight ratio <= 1e6, degree <= 5)
# and those squares finite. Precision sets the fraction: parameters inside a span of 2e-9 of
# the domain resolve to ~1e-7 of it, and normals there (weight ratio 6e5) stay within 5e-8 of
# the truth; at 2e-12 they are off by 1e-2 (measured on the sample sphere).
MIN_KNOT_DOMAIN = 1e-12
MIN_SPAN_FRACTION = 1e-9


class GeometryError(ValueError):
    """Invalid geometry; the message names the field and the problem."""


def _as_float_array(value, field: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise GeometryError(f"{field}: not a numeric array ({exc})") from None
    if not np.all(np.isfinite(arr)):
        raise GeometryError(f"{field}: contains non-finite values (NaN or inf)")
    return arr


def _check_knots(knots, degree: int, count: int, field: str, dname: str) -> None:
    k = _as_float_array(knots, field)
    if k.ndim != 1:
        raise GeometryError(f"{field}: must be 1-D, got shape {k.shape}")
    if k.shape[0] != count + degree + 1:
        raise GeometryError(
            f"{field}: has {k.shape[0]} knots, expected n + {dname} + 1 = "
            f"{count} + {degree} + 1 = {count + degree + 1}")
    steps = np.diff(k)
    if np.any(steps < 0):
        i = int(np.argmax(steps < 0))
        raise GeometryError(f"{field}: knots decrease at index {i + 1} "
                            f"({float(k[i])!r} -> {float(k[i + 1])!r})")
    values, mult = np.unique(k, return_counts=True)
    inner = mult[1:-1]
    if inner.size and inner.max() > degree:
        i = int(np.argmax(inner)) + 1
        raise GeometryError(f"{field}: interior knot {float(values[i])!r} has multiplicity {mult[i]} "
                            f"> {dname} {degree}")
    if mult.max() > degree + 1:
        i = int(np.argmax(mult))
        raise GeometryError(f"{field}: end knot {float(values[i])!r} has multiplicity {mult[i]} "
                            f"> {dname} + 1 = {degree + 1}")
    if not k[count] > k[degree]:
        raise GeometryError(f"{field}: zero-length domain [{float(k[degree])!r}, {float(k[count])!r}]")
    _check_spans(k[degree:count + 1], degree, field)


def _check_spans(dom: np.ndarray, degree: int, field: str) -> None:
    """The domain knots ``dom`` (knots[p..n]) span at least MIN_KNOT_DOMAIN and each non-empty
    span at least MIN_SPAN_FRACTION of it (see there)."""
    length = float(dom[-1] - dom[0])
    if not length >= MIN_KNOT_DOMAIN:
        raise GeometryError(f"{field}: domain length {length!r} is below {MIN_KNOT_DOMAIN:g}: "
                            "derivatives would overflow; scale the knots up (that does not "
                            "change the surface)")
    steps = np.diff(dom)
    short = (steps > 0) & (steps < MIN_SPAN_FRACTION * length)
    if short.any():
        j = int(np.argmax(short))
        raise GeometryError(f"{field}[{j + degree + 1}]: span [{float(dom[j])!r}, "
                            f"{float(dom[j + 1])!r}] is shorter than {MIN_SPAN_FRACTION:g} of "
                            f"the domain length {length!r}: derivatives would overflow; make "
                            "the two knots equal or spread them")


def _check_weights(weights: np.ndarray, field: str) -> None:
    """Weights in [MIN_WEIGHT, inf) with max/min <= MAX_WEIGHT_RATIO (see there)."""
    lo, hi = float(weights.min()), float(weights.max())
    if not lo > 0:
        raise GeometryError(f"{field}: must be > 0, minimum is {lo!r}")
    at = "".join(f"[{int(i)}]" for i in np.unravel_index(int(np.argmin(weights)), weights.shape))
    if not hi <= MAX_WEIGHT_RATIO * lo:
        raise GeometryError(f"{field}{at}: weight {lo!r} is more than {MAX_WEIGHT_RATIO:g} times "
                            f"smaller than the largest weight {hi!r}: the rational derivatives "
                            "would lose all precision")
    if lo < MIN_WEIGHT:
        raise GeometryError(f"{field}{at}: weight {lo!r} is below {MIN_WEIGHT:g}; scale all "
                            "weights of the patch up (a common factor does not change the surface)")


def check_surface(surf: NurbsSurface, name: str = "surface") -> None:
    """Raise GeometryError (naming ``name.field``) unless ``surf`` is a valid NURBS surface."""
    for dname in ("degree_u", "degree_v"):
        deg = getattr(surf, dname)
        if isinstance(deg, bool) or not isinstance(deg, Integral):
            raise GeometryError(f"{name}.{dname}: must be an integer, got {deg!r}")
        if not 1 <= deg <= MAX_DEGREE:
            raise GeometryError(f"{name}.{dname}: must be in 1..{MAX_DEGREE}, got {deg}")
    points = _as_float_array(surf.points, f"{name}.points")
    if points.ndim != 3 or points.shape[2] != 3:
        raise GeometryError(f"{name}.points: must have shape (n_u, n_v, 3), got {points.shape}")
    nu, nv = points.shape[:2]
    weights = _as_float_array(surf.weights, f"{name}.weights")
    if weights.shape != (nu, nv):
        raise GeometryError(f"{name}.weights: must have shape {(nu, nv)} like points, "
                            f"got {weights.shape}")
    for d in ("u", "v"):
        degree, count = getattr(surf, f"degree_{d}"), (nu if d == "u" else nv)
        if count < degree + 1:
            raise GeometryError(f"{name}.points: {count} control points along {d}, need at "
                                f"least degree_{d} + 1 = {degree + 1}")
    _check_weights(weights, f"{name}.weights")
    for d in ("u", "v"):
        degree, count = getattr(surf, f"degree_{d}"), (nu if d == "u" else nv)
        _check_knots(getattr(surf, f"knots_{d}"), degree, count, f"{name}.knots_{d}",
                     f"degree_{d}")


# --------------------------------------------------------------------------- knot insertion
def insert_homogeneous(pw: np.ndarray, knots: np.ndarray, p: int, value: float,
                       times: int) -> tuple[np.ndarray, np.ndarray]:
    """Boehm insertion of ``value`` ``times`` times along axis 0 of homogeneous points.

    pw (n, ..., 4) (any trailing axes ride along, vectorized); returns (new pw, new knots).
    Piegl & Tiller A5.1; the caller guarantees times >= 1, knots[p] <= value <= knots[n] and
    that the resulting multiplicity stays <= p.
    """
    n = pw.shape[0]
    k = int(np.searchsorted(knots, value, side="right")) - 1    # last knot <= value
    s = int(np.count_nonzero(knots == value))
    r = times
    q = np.empty((n + r,) + pw.shape[1:])
    q[:k - p + 1] = pw[:k - p + 1]
    q[k - s + r:] = pw[k - s:]
    rw = pw[k - p:k - s + 1].copy()
    for j in range(1, r + 1):
        last = k - p + j
        for i in range(p - j - s + 1):
            alpha = (value - knots[last + i]) / (knots[i + k + 1] - knots[last + i])
            rw[i] = alpha * rw[i + 1] + (1.0 - alpha) * rw[i]
        q[last] = rw[0]
        q[k + r - j - s] = rw[p - j - s]
    q[last + 1:k - s] = rw[1:k - s - last]
    new_knots = np.concatenate([knots[:k + 1], np.full(r, float(value)), knots[k + 1:]])
    return q, new_knots


def _from_homogeneous(pw: np.ndarray, surf: NurbsSurface, knots_u, knots_v) -> NurbsSurface:
    w = pw[..., 3]
    return NurbsSurface(surf.degree_u, surf.degree_v, knots_u, knots_v,
                        pw[..., :3] / w[..., None], w.copy())


def insert_knot(surf: NurbsSurface, direction: str, value: float, times: int = 1) -> NurbsSurface:
    """The same surface with ``value`` inserted ``times`` times into knots_<direction>.

    Boehm's algorithm in homogeneous coordinates, vectorized over the other direction; the
    resulting multiplicity must stay <= the degree and value must lie in the domain.
    """
    if direction not in ("u", "v"):
        raise GeometryError(f"direction: must be 'u' or 'v', got {direction!r}")
    if isinstance(times, bool) or not isinstance(times, Integral) or times < 0:
        raise GeometryError(f"times: must be a non-negative integer, got {times!r}")
    value = float(value)
    along_u = direction == "u"
    p = surf.degree_u if along_u else surf.degree_v
    knots = np.asarray(surf.knots_u if along_u else surf.knots_v, dtype=np.float64)
    n = surf.points.shape[0 if along_u else 1]
    if not knots[p] <= value <= knots[n]:
        raise GeometryError(f"value: {value!r} outside the {direction} domain "
                            f"[{float(knots[p])!r}, {float(knots[n])!r}]")
    mult = int(np.count_nonzero(knots == value))
    if times and mult + times > p:
        raise GeometryError(f"times: inserting {value!r} {times} more time(s) gives multiplicity "
                            f"{mult + times} > degree_{direction} {p}")
    if times == 0:
        return dataclasses.replace(surf, knots_u=np.array(surf.knots_u, dtype=np.float64),
                                   knots_v=np.array(surf.knots_v, dtype=np.float64),
                                   points=np.array(surf.points, dtype=np.float64),
                                   weights=np.array(surf.weights, dtype=np.float64))
    pw = homogeneous(surf)
    if along_u:
        pw, new = insert_homogeneous(pw, knots, p, value, times)
        return _from_homogeneous(pw, surf, new, np.array(surf.knots_v, dtype=np.float64))
    pw, new = insert_homogeneous(pw.transpose(1, 0, 2), knots, p, value, times)
    return _from_homogeneous(pw.transpose(1, 0, 2), surf,
                             np.array(surf.knots_u, dtype=np.float64), new)


# --------------------------------------------------------------------------- Blender's rule
def blender_knots(order: int, count: int, cyclic: bool, endpoint: bool, bezier: bool) -> np.ndarray:
    """The knot vector Blender derives for one direction of a NURBS spline/surface.

    Blender (calcknots in blenkernel/intern/curve.cc) does not store knots; it builds them from
    the flags with unit steps starting at 0:
      - inner knots repeat once, or order-1 times with ``bezier``;
      - the first value repeats ``order`` times with ``endpoint`` (order-1 if also cyclic, after a
        single leading knot), 2 times (at most order-1) with ``bezier`` alone, else once;
      - the last ``order`` knots (endpoint) or 2*order-1 knots (cyclic) continue the spacing of
        the first ones, which clamps the end / makes the vector periodic.
    Length: count + order, plus order - 1 when cyclic (the wrapped control points). Raises
    GeometryError for the point counts Blender itself refuses to evaluate.
    """
    order, count = int(order), int(count)
    if not 2 <= order <= MAX_DEGREE + 1:
        raise GeometryError(f"order: must be in 2..{MAX_DEGREE + 1}, got {order}")
    if count < max(2, order):
        raise GeometryError(f"count: {count} points, need at least max(2, order) = "
                            f"{max(2, order)}")
    if bezier and cyclic and count % (order - 1):
        raise GeometryError(f"count: cyclic Bezier knots need a multiple of order - 1 = "
                            f"{order - 1} points, got {count}")
    if bezier and not (cyclic or endpoint) and count <= order:
        raise GeometryError(f"count: Bezier knots without endpoint need more than order = "
                            f"{order} points, got {count}")
    repeat_inner = order - 1 if bezier else 1
    if endpoint:
        head = order - 1 if cyclic else order
    else:
        head = min(2, repeat_inner) if bezier else 1
    tail = 2 * order - 1 if cyclic else (order if endpoint else 0)
    total = count + order + (order - 1 if cyclic else 0)
    knots = np.zeros(total)
    current = 0.0
    start = 0
    if endpoint and cyclic:       # one leading knot, then the (order-1)-fold first value
        start, current = 1, 1.0
    left = head
    for i in range(start, total - tail):
        knots[i] = current
        left -= 1
        if left == 0:
            current += 1.0
            left = repeat_inner
    for i in range(tail):         # sequential: may read knots this loop has just written
        knots[total - tail + i] = current + knots[i] - knots[0]
    return knots


def surface_from_blender(points_xyzw, count_u: int, count_v: int, order_u: int, order_v: int,
                         cyclic_u: bool, cyclic_v: bool, endpoint_u: bool, endpoint_v: bool,
                         bezier_u: bool, bezier_v: bool) -> NurbsSurface:
    """The NurbsSurface equal to a Blender NURBS surface spline.

    points_xyzw: (count_u * count_v, 4) from ``points.foreach_get('co')``, u varying fastest,
    Cartesian xyz and weight w. Cyclic directions are unrolled: the first order-1 rows/columns are
    appended again and the knot vector is the periodic one from ``blender_knots``.
    Domain: exactly the range Blender samples, [knots[order-1], knots[count]] (non-cyclic) or
    [knots[order-1], knots[count+order-1]] (cyclic), e.g. [0, count-order+1] for endpoint knots.
    Blender's evaluated mesh puts count*resolution samples uniformly over it per direction, the
    last one at the end for non-cyclic directions and one step short of it for cyclic ones.
    """
    pts = _as_float_array(points_xyzw, "points_xyzw")
    if pts.shape != (count_u * count_v, 4):
        raise GeometryError(f"points_xyzw: expected shape ({count_u * count_v}, 4) for "
                            f"count_u={count_u}, count_v={count_v}, got {pts.shape}")
    net = pts.reshape(count_v, count_u, 4).transpose(1, 0, 2)   # [i_u, i_v]
    if cyclic_u:
        net = np.concatenate([net, net[:order_u - 1]], axis=0)
    if cyclic_v:
        net = np.concatenate([net, net[:, :order_v - 1]], axis=1)
    ku = blender_knots(order_u, count_u, cyclic_u, endpoint_u, bezier_u)
    kv = blender_knots(order_v, count_v, cyclic_v, endpoint_v, bezier_v)
    # Blender accepts endpoint+Bezier counts that are not k*(order-1)+1; the surplus trailing
    # points then have basis functions vanishing on the domain (the end knot repeats more than
    # order times), so they are dropped: same surface, valid knot vector.
    keep_u = int(np.searchsorted(ku, ku[net.shape[0]], side="left"))
    keep_v = int(np.searchsorted(kv, kv[net.shape[1]], side="left"))
    net = net[:keep_u, :keep_v]
    surf = NurbsSurface(
        degree_u=int(order_u) - 1, degree_v=int(order_v) - 1,
        knots_u=ku[:keep_u + int(order_u)], knots_v=kv[:keep_v + int(order_v)],
        points=np.ascontiguousarray(net[..., :3]), weights=np.ascontiguousarray(net[..., 3]))
    check_surface(surf, "blender surface")
    return surf
