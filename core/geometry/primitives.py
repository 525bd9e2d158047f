"""Exact rational NURBS primitives, surfaces of revolution, Bezier patches, affine transforms.

Units are world units (metres). Circles are the rational quadratic 9-point circle (weights
1, sqrt(2)/2, ...) on the parameter range [0, 1] with quarter knots. For every surface of
revolution u runs counter-clockwise about +z (seen from above) and v along the profile, so
Su x Sv points to the right of the profile direction in the (r, z) half-plane: outward for a
profile walked upward (south to north) on the outside.
"""

from __future__ import annotations

import numpy as np

from .knots import GeometryError, check_surface
from .nurbs import NurbsSurface

_S = np.sqrt(0.5)
# Unit circle: 9 control points (x, y), weights and knots, u in [0, 1].
_CIRCLE_XY = np.array([[1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0],
                       [-1, -1], [0, -1], [1, -1], [1, 0]], dtype=np.float64)
_CIRCLE_W = np.array([1, _S, 1, _S, 1, _S, 1, _S, 1], dtype=np.float64)
_CIRCLE_KNOTS = np.array([0, 0, 0, .25, .25, .5, .5, .75, .75, 1, 1, 1], dtype=np.float64)


def _vec3(value, field: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise GeometryError(f"{field}: must be 3 finite numbers, got {value!r}")
    return arr


def _positive(value, field: str) -> float:
    x = float(value)
    if not (np.isfinite(x) and x > 0):
        raise GeometryError(f"{field}: must be a finite number > 0, got {value!r}")
    return x


def _clamped_uniform(count: int, degree: int) -> np.ndarray:
    inner = np.linspace(0.0, 1.0, count - degree + 1)
    return np.concatenate([np.zeros(degree), inner, np.ones(degree)])


def revolve(profile, degree: int = 3, weights=None, knots=None) -> NurbsSurface:
    """Surface of revolution of the (r, z) profile curve about the z axis.

    profile (n, 2) control points (r >= 0, z); degree, weights (n,) and knots (n + degree + 1,)
    describe the profile NURBS curve (default: clamped uniform knots on [0, 1], unit weights).
    u = angle (rational circle, degree 2, domain [0, 1]), v = profile parameter. Profile points
    with r = 0 become collapsed control rows (poles).
    """
    prof = np.asarray(profile, dtype=np.float64)
    if prof.ndim != 2 or prof.shape[1] != 2 or prof.shape[0] < 2:
        raise GeometryError(f"profile: must have shape (n >= 2, 2), got {prof.shape}")
    if not np.all(np.isfinite(prof)) or np.any(prof[:, 0] < 0):
        raise GeometryError("profile: points must be finite with radius r >= 0")
    n = prof.shape[0]
    if not 1 <= int(degree) <= n - 1:
        raise GeometryError(f"degree: must be in 1..n-1 = {n - 1} for {n} profile points, "
                            f"got {degree}")
    degree = int(degree)
    wv = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    kv = _clamped_uniform(n, degree) if knots is None else np.asarray(knots, dtype=np.float64)
    points = np.empty((9, n, 3))
    points[..., 0] = _CIRCLE_XY[:, None, 0] * prof[None, :, 0]
    points[..., 1] = _CIRCLE_XY[:, None, 1] * prof[None, :, 0]
    points[..., 2] = prof[None, :, 1]
    if wv.shape != (n,):
        raise GeometryError(f"weights: must have shape ({n},), got {wv.shape}")
    surf = NurbsSurface(2, degree, _CIRCLE_KNOTS.copy(), kv, points, _CIRCLE_W[:, None] * wv)
    check_surface(surf, "revolve")
    return surf


def _translated(surf: NurbsSurface, center) -> NurbsSurface:
    surf.points += _vec3(center, "center")
    return surf


def sphere(center=(0.0, 0.0, 0.0), radius: float = 1.0) -> NurbsSurface:
    """Exact sphere: u around z, v from the south pole (v = 0) to the north pole (v = 1);
    the poles are collapsed control rows. Normals Su x Sv point outward."""
    r = _positive(radius, "radius")
    profile = [[0, -r], [r, -r], [r, 0], [r, r], [0, r]]
    knots = [0, 0, 0, .5, .5, 1, 1, 1]
    return _translated(revolve(profile, 2, [1, _S, 1, _S, 1], knots), center)


def cylinder(center=(0.0, 0.0, 0.0), radius: float = 1.0, height: float = 2.0) -> NurbsSurface:
    """Open tube about the z axis through ``center`` (its mid-height), v = 0 at the bottom rim;
    normals point outward. Degree (2, 1)."""
    r = _positive(radius, "radius")
    h = 0.5 * _positive(height, "height")
    return _translated(revolve([[r, -h], [r, h]], degree=1), center)


def torus(center=(0.0, 0.0, 0.0), major: float = 1.0, minor: float = 0.25) -> NurbsSurface:
    """Ring torus about the z axis: ``major`` = distance of the tube centre from the axis,
    ``minor`` = tube radius (< major). u around z, v around the tube starting at the outer
    equator; normals point outward. Degree (2, 2)."""
    big = _positive(major, "major")
    small = _positive(minor, "minor")
    if small >= big:
        raise GeometryError(f"minor: must be < major ({big!r}) for a ring torus, got {small!r}")
    profile = _CIRCLE_XY * small + (big, 0.0)
    return _translated(revolve(profile, 2, _CIRCLE_W, _CIRCLE_KNOTS), center)


def bezier_patch(ctrl, weights=None) -> NurbsSurface:
    """A (rational) tensor Bezier patch: ctrl (p+1, q+1, 3) with ctrl[i, j] at index i along u;
    domain [0, 1]^2."""
    pts = np.array(ctrl, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[2] != 3 or min(pts.shape[:2]) < 2:
        raise GeometryError(f"ctrl: must have shape (p+1, q+1, 3) with p, q >= 1, "
                            f"got {pts.shape}")
    p, q = pts.shape[0] - 1, pts.shape[1] - 1
    w = np.ones(pts.shape[:2]) if weights is None else np.array(weights, dtype=np.float64)
    surf = NurbsSurface(p, q, np.repeat([0.0, 1.0], p + 1), np.repeat([0.0, 1.0], q + 1), pts, w)
    check_surface(surf, "bezier_patch")
    return surf


def bilinear(p00, p10, p01, p11) -> NurbsSurface:
    """The bilinear patch with corners S(0,0)=p00, S(1,0)=p10, S(0,1)=p01, S(1,1)=p11."""
    corners = [[_vec3(p00, "p00"), _vec3(p01, "p01")], [_vec3(p10, "p10"), _vec3(p11, "p11")]]
    return bezier_patch(corners)


def transform(surf: NurbsSurface, matrix) -> NurbsSurface:
    """A copy of ``surf`` with control points mapped by the affine 4x4 ``matrix`` (column
    vectors: x' = M[:3, :3] x + M[:3, 3]); weights and knots are unchanged."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise GeometryError(f"matrix: must be a finite 4x4 array, got shape {m.shape}")
    if not np.array_equal(m[3], [0.0, 0.0, 0.0, 1.0]):
        raise GeometryError(f"matrix: last row must be (0, 0, 0, 1) (affine), got {m[3]}")
    return NurbsSurface(surf.degree_u, surf.degree_v, np.array(surf.knots_u, dtype=np.float64),
                        np.array(surf.knots_v, dtype=np.float64),
                        surf.points @ m[:3, :3].T + m[:3, 3],
                        np.array(surf.weights, dtype=np.float64))


def box_faces(lo, hi) -> list[NurbsSurface]:
    """The six faces of the axis-aligned box [lo, hi] as bilinear patches, ordered
    -Z, +Z, -Y, +Y, -X, +X (orientation: as built, not necessarily outward)."""
    x0, y0, z0 = _vec3(lo, "lo")
    x1, y1, z1 = _vec3(hi, "hi")
    P = np.array
    corners = [
        (P([x0, y0, z0]), P([x1, y0, z0]), P([x0, y1, z0]), P([x1, y1, z0])),
        (P([x0, y0, z1]), P([x1, y0, z1]), P([x0, y1, z1]), P([x1, y1, z1])),
        (P([x0, y0, z0]), P([x1, y0, z0]), P([x0, y0, z1]), P([x1, y0, z1])),
        (P([x0, y1, z0]), P([x1, y1, z0]), P([x0, y1, z1]), P([x1, y1, z1])),
        (P([x0, y0, z0]), P([x0, y1, z0]), P([x0, y0, z1]), P([x0, y1, z1])),
        (P([x1, y0, z0]), P([x1, y1, z0]), P([x1, y0, z1]), P([x1, y1, z1])),
    ]
    return [bilinear(*c) for c in corners]
