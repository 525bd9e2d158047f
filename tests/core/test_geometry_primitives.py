"""Exact primitives: distances, normals at poles and seams, revolve, patches, transforms."""

from math import comb

import numpy as np
import pytest

from riray.geometry.knots import GeometryError, check_surface
from riray.geometry.nurbs import evaluate, normals
from riray.geometry.primitives import (bezier_patch, bilinear, cylinder, revolve, sphere, torus,
                                       transform)


def dense_params(surf, n=4000, seed=0):
    """Random (u, v) plus the domain corners, the seams and the poles/edges exactly."""
    rng = np.random.default_rng(seed)
    u0, u1, v0, v1 = surf.domain
    u, v = rng.uniform(u0, u1, n), rng.uniform(v0, v1, n)
    edge_u = np.linspace(u0, u1, 41)
    edge_v = np.linspace(v0, v1, 41)
    u = np.concatenate([u, edge_u, edge_u, np.full(41, u0), np.full(41, u1), edge_u])
    v = np.concatenate([v, np.full(41, v0), np.full(41, v1), edge_v, edge_v,
                        rng.uniform(v0, v1, 41)])
    return u, v


def test_sphere_points_and_normals_are_exact():
    c, r = np.array([0.5, -2.0, 1.25]), 1.7
    surf = sphere(c, r)
    check_surface(surf)
    u, v = dense_params(surf)
    (s,) = evaluate(surf, u, v, 0)
    assert np.max(np.abs(np.linalg.norm(s - c, axis=1) - r)) < 1e-12
    n = normals(surf, u, v)
    assert np.max(np.abs(n - (s - c) / r)) < 1e-9
    # the poles: v = 0 south, v = 1 north, for any u
    (south,) = evaluate(surf, [0.3], [0.0], 0)
    assert np.allclose(south, c - [0, 0, r], atol=1e-14)
    uu = np.linspace(0, 1, 9)
    assert np.allclose(normals(surf, uu, np.zeros(9)), [0, 0, -1], atol=1e-12)
    assert np.allclose(normals(surf, uu, np.ones(9)), [0, 0, 1], atol=1e-12)
    # seam: u = 0 and u = 1 give the same points and normals
    vv = np.linspace(0, 1, 17)
    seam0, seam1 = evaluate(surf, np.zeros(17), vv, 0)[0], evaluate(surf, np.ones(17), vv, 0)[0]
    assert np.allclose(seam0, seam1, atol=1e-14)
    assert np.allclose(normals(surf, np.zeros(17), vv), normals(surf, np.ones(17), vv), atol=1e-12)


def test_cylinder_is_exact_open_tube():
    c = np.array([1.0, 2.0, 3.0])
    surf = cylinder(c, 0.75, 4.0)
    u, v = dense_params(surf)
    (s,) = evaluate(surf, u, v, 0)
    d = s - c
    assert np.max(np.abs(np.hypot(d[:, 0], d[:, 1]) - 0.75)) < 1e-12
    assert np.all(np.abs(d[:, 2]) <= 2.0 + 1e-12)
    assert np.isclose(d[:, 2].min(), -2.0) and np.isclose(d[:, 2].max(), 2.0)
    n = normals(surf, u, v)
    radial = d * [1, 1, 0] / 0.75
    assert np.max(np.abs(n - radial)) < 1e-9


def test_torus_distance_to_tube_circle_is_exact():
    c = np.array([-1.0, 0.5, 2.0])
    big, small = 2.0, 0.6
    surf = torus(c, big, small)
    u, v = dense_params(surf)
    (s,) = evaluate(surf, u, v, 0)
    d = s - c
    rho = np.hypot(d[:, 0], d[:, 1])
    assert np.max(np.abs(np.hypot(rho - big, d[:, 2]) - small)) < 1e-12
    # outward normals: from the nearest tube-centre point to the surface point
    centre = d * [1, 1, 0] * (big / rho)[:, None]
    n = normals(surf, u, v)
    assert np.max(np.abs(n - (d - centre) / small)) < 1e-9


def test_revolve_profile_touching_axis_has_polar_normals():
    # Cubic profile from the axis (south) to the axis (north), horizontal at both poles.
    profile = [[0.0, -1.0], [0.6, -1.0], [1.2, -0.3], [1.0, 0.6], [0.5, 1.2], [0.0, 1.2]]
    surf = revolve(profile)
    assert surf.degree_u == 2 and surf.degree_v == 3
    u = np.linspace(0.0, 1.0, 33)
    south = normals(surf, u, np.zeros(33))
    north = normals(surf, u, np.ones(33))
    assert np.allclose(south, [0, 0, -1], atol=1e-12)
    assert np.allclose(north, [0, 0, 1], atol=1e-12)
    # consistent with the neighbouring regular normals
    near_s = normals(surf, u, np.full(33, 1e-4))
    near_n = normals(surf, u, np.full(33, 1 - 1e-4))
    assert np.all(np.einsum("ij,ij->i", south, near_s) > 0.999)
    assert np.all(np.einsum("ij,ij->i", north, near_n) > 0.999)
    # the surface is a surface of revolution: distance to the axis is u-independent
    v = np.linspace(0, 1, 21)
    uu, vv = np.meshgrid(np.linspace(0, 1, 13), v)
    (s,) = evaluate(surf, uu.ravel(), vv.ravel(), 0)
    rho = np.hypot(s[:, 0], s[:, 1]).reshape(uu.shape)
    assert np.max(np.abs(rho - rho[:, :1])) < 1e-12
    z = s[:, 2].reshape(uu.shape)
    assert np.max(np.abs(z - z[:, :1])) < 1e-12


def test_revolve_of_a_segment_is_a_cone_frustum():
    surf = revolve([[1.0, 0.0], [2.0, 1.0]], degree=1)
    u, v = dense_params(surf, 500)
    (s,) = evaluate(surf, u, v, 0)
    assert np.max(np.abs(np.hypot(s[:, 0], s[:, 1]) - (1.0 + s[:, 2]))) < 1e-12


def test_revolve_rejects_bad_profiles():
    with pytest.raises(GeometryError, match="profile"):
        revolve([[1.0, 0.0, 0.0]])
    with pytest.raises(GeometryError, match="profile.*r >= 0"):
        revolve([[-1.0, 0.0], [1.0, 1.0]], degree=1)
    with pytest.raises(GeometryError, match="degree"):
        revolve([[1.0, 0.0], [1.0, 1.0]], degree=3)
    with pytest.raises(GeometryError, match="minor"):
        torus((0, 0, 0), 1.0, 1.5)
    with pytest.raises(GeometryError, match="radius"):
        sphere((0, 0, 0), -1.0)


def test_bezier_patch_and_bilinear_match_bernstein_definition():
    rng = np.random.default_rng(0)
    ctrl = rng.normal(size=(4, 3, 3))
    w = rng.uniform(0.5, 2.0, (4, 3))
    surf = bezier_patch(ctrl, w)
    u, v = rng.random(50), rng.random(50)

    def bern(n, i, x):
        return comb(n, i) * x ** i * (1 - x) ** (n - i)

    bu = np.array([bern(3, i, u) for i in range(4)])          # (4, N)
    bv = np.array([bern(2, j, v) for j in range(3)])
    r = bu[:, None, :] * bv[None, :, :] * w[:, :, None]
    truth = np.einsum("ijn,ijc->nc", r, ctrl) / r.sum(axis=(0, 1))[:, None]
    assert np.max(np.abs(evaluate(surf, u, v, 0)[0] - truth)) < 1e-13
    p00, p10, p01, p11 = rng.normal(size=(4, 3))
    (s,) = evaluate(bilinear(p00, p10, p01, p11), u, v, 0)
    lin = ((1 - u) * (1 - v))[:, None] * p00 + (u * (1 - v))[:, None] * p10 \
        + ((1 - u) * v)[:, None] * p01 + (u * v)[:, None] * p11
    assert np.max(np.abs(s - lin)) < 1e-14


def test_transform_maps_points_affinely():
    surf = torus((0, 0, 0), 1.5, 0.4)
    rng = np.random.default_rng(2)
    m = np.eye(4)
    m[:3, :3] = rng.normal(size=(3, 3))
    m[:3, 3] = [1.0, -2.0, 0.5]
    moved = transform(surf, m)
    u, v = rng.random(200), rng.random(200)
    (a,) = evaluate(surf, u, v, 0)
    (b,) = evaluate(moved, u, v, 0)
    assert np.max(np.abs(a @ m[:3, :3].T + m[:3, 3] - b)) < 1e-12
    assert moved.points is not surf.points
    bad = np.eye(4)
    bad[3, 0] = 0.1
    with pytest.raises(GeometryError, match="matrix.*affine"):
        transform(surf, bad)
