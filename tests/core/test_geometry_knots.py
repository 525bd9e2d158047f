"""Validation, knot insertion and Blender's knot rule."""

import dataclasses

import numpy as np
import pytest

from riray.geometry.knots import (GeometryError, blender_knots, check_surface, insert_knot,
                                  surface_from_blender)
from riray.geometry.nurbs import NurbsSurface, evaluate
from riray.geometry.primitives import sphere, torus


def rational_surface(seed=0, p=3, q=2, nu=6, nv=5):
    rng = np.random.default_rng(seed)
    ku = np.concatenate([np.zeros(p + 1), np.sort(rng.uniform(0.1, 0.9, nu - p - 1)),
                         np.ones(p + 1)])
    kv = np.concatenate([np.zeros(q + 1), np.sort(rng.uniform(0.1, 0.9, nv - q - 1)),
                         np.ones(q + 1)]) * 2.0 + 1.0
    return NurbsSurface(p, q, ku, kv, rng.normal(size=(nu, nv, 3)),
                        rng.uniform(0.3, 2.0, size=(nu, nv)))


# --------------------------------------------------------------------------- validation
def test_valid_surfaces_pass():
    check_surface(rational_surface())
    check_surface(sphere())
    check_surface(torus())


@pytest.mark.parametrize("change, field, words", [
    (dict(knots_u=np.linspace(0, 1, 9)), "knots_u", "expected"),
    (dict(knots_v=np.array([0, 0, 0, .6, .4, 1, 1, 1.])), "knots_v",
     r"decrease at index 4 \(0\.6 -> 0\.4\)"),          # plain numbers on numpy 1 and 2
    (dict(knots_u=np.array([0, 0, 0, 0, .5, .5, .5, .5, 1, 1, 1.])[:10]), "knots_u",
     "multiplicity"),
    (dict(knots_u=np.zeros(10)), "knots_u", "multiplicity"),
    (dict(degree_u=6), "degree_u", "1..5"),
    (dict(degree_v=0), "degree_v", "1..5"),
    (dict(degree_u=2.0), "degree_u", "integer"),
    (dict(weights=np.zeros((6, 5))), "weights", "> 0"),
    (dict(weights=-np.ones((6, 5))), "weights", r"> 0, minimum is -1\.0$"),
    (dict(weights=np.ones((5, 6))), "weights", "shape"),
    (dict(points=np.ones((6, 5, 2))), "points", "shape"),
    (dict(knots_v=np.ones((8, 1))), "knots_v", "1-D"),
])
def test_invalid_surfaces_raise_naming_the_field(change, field, words):
    surf = dataclasses.replace(rational_surface(), **change)
    with pytest.raises(GeometryError, match=f"patch7.{field}.*{words}"):
        check_surface(surf, "patch7")


def test_non_finite_values_raise_naming_the_field():
    for field in ("points", "weights", "knots_u"):
        surf = rational_surface()
        arr = getattr(surf, field).copy()
        arr.flat[3] = np.nan
        with pytest.raises(GeometryError, match=f"surface.{field}.*non-finite"):
            check_surface(dataclasses.replace(surf, **{field: arr}))


def test_zero_length_domain_and_too_few_points_raise():
    surf = NurbsSurface(2, 1, np.array([0, .5, 1, 1, 2, 3]), np.array([0, 0, 1, 1.]),
                        np.zeros((3, 2, 3)), np.ones((3, 2)))
    with pytest.raises(GeometryError, match="knots_u.*zero-length domain"):
        check_surface(surf)
    few = NurbsSurface(3, 1, np.array([0, 0, 0, 1, 1, 1.]), np.array([0, 0, 1, 1.]),
                       np.zeros((2, 2, 3)), np.ones((2, 2)))
    with pytest.raises(GeometryError, match="points.*need at least degree_u"):
        check_surface(few)
    assert issubclass(GeometryError, ValueError)


# --------------------------------------------------------------------------- knot insertion
def test_knot_insertion_leaves_the_surface_unchanged():
    surf = rational_surface(seed=4)
    rng = np.random.default_rng(0)
    u0, u1, v0, v1 = surf.domain
    u, v = rng.uniform(u0, u1, 500), rng.uniform(v0, v1, 500)
    u[:4], v[:4] = [u0, u1, u0, u1], [v0, v1, v1, v0]
    before = evaluate(surf, u, v, 2)
    ins = surf
    for direction, value, times in [("u", 0.37, 1), ("u", 0.37, 2), ("v", 2.2, 2),
                                    ("u", surf.knots_u[4], 1), ("v", v1, 0), ("v", 1.5, 1)]:
        ins = insert_knot(ins, direction, value, times)
        check_surface(ins)
    assert ins.points.shape == (6 + 4, 5 + 3, 3)
    assert np.count_nonzero(ins.knots_u == 0.37) == 3
    after = evaluate(ins, u, v, 2)
    for x, y in zip(before, after):
        assert np.max(np.abs(x - y)) < 1e-12 * max(1.0, np.abs(x).max())


def test_knot_insertion_on_unclamped_vector_at_domain_ends():
    k = np.arange(9, dtype=float)                     # uniform, degree 3, 5 points: [3, 5]
    rng = np.random.default_rng(1)
    surf = NurbsSurface(3, 1, k, np.array([0, 0, 1, 1.]), rng.normal(size=(5, 2, 3)),
                        rng.uniform(0.5, 2, (5, 2)))
    u = np.linspace(3, 5, 41)
    before = evaluate(surf, u, np.full(41, 0.3), 1)
    ins = insert_knot(insert_knot(surf, "u", 3.0, 2), "u", 5.0, 2)
    after = evaluate(ins, u, np.full(41, 0.3), 1)
    for x, y in zip(before, after):
        assert np.max(np.abs(x - y)) < 1e-12


def test_knot_insertion_rejects_bad_requests():
    surf = rational_surface()
    with pytest.raises(GeometryError, match="times.*multiplicity"):
        insert_knot(surf, "u", 0.5, 4)
    with pytest.raises(GeometryError, match="times.*multiplicity"):
        insert_knot(surf, "u", 0.0, 1)                 # clamped end already has p+1
    with pytest.raises(GeometryError, match="value.*outside"):
        insert_knot(surf, "v", 0.5, 1)
    with pytest.raises(GeometryError, match="direction"):
        insert_knot(surf, "w", 0.5, 1)


# --------------------------------------------------------------------------- Blender's rule
COMBOS = [(order, count, cyc, end, bez)
          for order in (2, 3, 4, 5, 6) for count in (6, 7, 9, 13)
          for cyc in (False, True) for end in (False, True) for bez in (False, True)
          if count >= order and not (bez and cyc and count % (order - 1))
          and not (bez and not cyc and not end and count <= order)]


@pytest.mark.parametrize("order, count, cyclic, endpoint, bezier", COMBOS)
def test_blender_knots_shape_and_structure(order, count, cyclic, endpoint, bezier):
    k = blender_knots(order, count, cyclic, endpoint, bezier)
    assert k.shape == (count + order + (order - 1 if cyclic else 0),)
    assert np.all(np.diff(k) >= 0) and k[0] == 0.0
    assert np.all(k == np.round(k))                     # unit steps
    if endpoint and not bezier and not cyclic:          # clamped uniform
        assert np.all(k[:order] == 0) and np.all(k[-order:] == k[-1])
        assert np.array_equal(np.diff(k[order - 1:count + 1]), np.ones(count - order + 1))
    if cyclic:                                          # periodic: spacing repeats every count
        d = np.diff(k)
        assert np.array_equal(d[count:], d[:d.shape[0] - count])
    if not (endpoint or bezier or cyclic):
        assert np.array_equal(k, np.arange(count + order))


def test_blender_knots_hand_derived_vectors():
    # Worked through Blender's calcknots() by hand.
    assert blender_knots(4, 7, False, True, True).tolist() == [0, 0, 0, 0, 1, 1, 1, 2, 2, 2, 2]
    assert blender_knots(3, 5, False, True, False).tolist() == [0, 0, 0, 1, 2, 3, 3, 3]
    assert blender_knots(4, 5, False, False, True).tolist() == [0, 0, 1, 1, 1, 2, 2, 2, 3]
    assert blender_knots(3, 4, True, True, False).tolist() == [0, 1, 1, 2, 3, 4, 4, 5, 6]
    assert blender_knots(4, 6, True, False, True).tolist() == [0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3,
                                                               4, 4]


def test_blender_knots_rejects_counts_blender_refuses():
    with pytest.raises(GeometryError, match="count"):
        blender_knots(4, 3, False, True, False)
    with pytest.raises(GeometryError, match="count.*multiple"):
        blender_knots(4, 7, True, False, True)
    with pytest.raises(GeometryError, match="count.*more than order"):
        blender_knots(4, 4, False, False, True)
    with pytest.raises(GeometryError, match="order"):
        blender_knots(7, 9, False, True, False)


def blender_points(count_u, count_v, seed):
    rng = np.random.default_rng(seed)
    pts = np.empty((count_u * count_v, 4))
    pts[:, :3] = rng.normal(size=(count_u * count_v, 3))
    pts[:, 3] = rng.uniform(0.5, 2.0, count_u * count_v)
    return pts


def test_surface_from_blender_endpoint_corners_and_u_fastest_order():
    pts = blender_points(5, 4, 0)
    surf = surface_from_blender(pts, 5, 4, 3, 4, False, False, True, True, False, False)
    u0, u1, v0, v1 = surf.domain
    assert (u0, u1, v0, v1) == (0.0, 3.0, 0.0, 1.0)
    (s,) = evaluate(surf, [u0, u1, u0, u1], [v0, v0, v1, v1], 0)
    # clamped ends interpolate corners; u varies fastest in Blender's point list
    assert np.allclose(s, pts[[0, 4, 15, 19], :3], atol=1e-13)


def test_surface_from_blender_cyclic_closes_smoothly():
    pts = blender_points(6, 5, 1)
    for endpoint in (False, True):
        surf = surface_from_blender(pts, 6, 5, 4, 3, True, False, endpoint, True, False, False)
        if not endpoint:                  # unrolled: first order-1 columns wrapped
            assert surf.points.shape == (6 + 3, 5, 3)
            assert np.array_equal(surf.points[6:], surf.points[:3])
        u0, u1, v0, v1 = surf.domain
        v = np.linspace(v0, v1, 13)
        a = evaluate(surf, np.full(13, u0), v, 1)
        b = evaluate(surf, np.full(13, u1), v, 1)
        assert np.max(np.abs(a[0] - b[0])) < 1e-12           # closed seam
        if not endpoint:                                     # periodic: C2, tangents agree
            assert np.max(np.abs(a[1] - b[1])) < 1e-11


def test_surface_from_blender_bezier_interpolates_segment_ends():
    pts = blender_points(7, 3, 2)
    surf = surface_from_blender(pts, 7, 3, 4, 3, False, False, True, True, True, False)
    (s,) = evaluate(surf, [0.0, 1.0, 2.0], [0.0, 0.0, 0.0], 0)
    assert np.allclose(s, pts[[0, 3, 6], :3], atol=1e-13)


def test_surface_from_blender_drops_points_without_influence():
    # endpoint+bezier with 6 points of order 4: Blender evaluates only the first Bezier segment.
    pts = blender_points(6, 2, 3)
    surf = surface_from_blender(pts, 6, 2, 4, 2, False, False, True, True, True, False)
    assert surf.points.shape[0] == 4
    assert surf.domain[:2] == (0.0, 1.0)
    (s,) = evaluate(surf, [1.0], [0.0], 0)
    assert np.allclose(s[0], pts[3, :3], atol=1e-13)


def test_surface_from_blender_checks_point_count():
    with pytest.raises(GeometryError, match="points_xyzw.*shape"):
        surface_from_blender(np.zeros((11, 4)), 4, 3, 3, 3, False, False, True, True, False,
                             False)
