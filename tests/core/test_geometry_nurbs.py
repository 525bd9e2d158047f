"""NURBS evaluation and normals against independent truths (definition, finite differences)."""

import numpy as np
import pytest

from riray.geometry.nurbs import NurbsSurface, evaluate, normals
from riray.geometry.primitives import bilinear, sphere, torus


def random_surface(seed=0, p=3, q=2, nu=7, nv=5):
    """A rational surface with non-uniform clamped knots, a double interior knot in u."""
    rng = np.random.default_rng(seed)
    inner_u = np.sort(rng.uniform(0.1, 0.9, nu - p - 2))
    inner_u = np.concatenate([inner_u, inner_u[-1:]])          # double knot
    inner_v = np.sort(rng.uniform(0.1, 0.9, nv - q - 1))
    ku = np.concatenate([np.zeros(p + 1), np.sort(inner_u), np.ones(p + 1)]) * 2.0 - 0.5
    kv = np.concatenate([np.zeros(q + 1), inner_v, np.ones(q + 1)]) * 3.0
    pts = rng.normal(size=(nu, nv, 3))
    w = rng.uniform(0.3, 2.5, size=(nu, nv))
    return NurbsSurface(p, q, ku, kv, pts, w)


def cox_de_boor(knots, i, p, x, last):
    """N_{i,p}(x) by the recursive definition (half-open spans, closed at the domain end)."""
    if p == 0:
        if knots[i] <= x < knots[i + 1]:
            return 1.0
        return 1.0 if (x == last and knots[i] < knots[i + 1] == last) else 0.0
    out = 0.0
    if knots[i + p] > knots[i]:
        out += (x - knots[i]) / (knots[i + p] - knots[i]) * cox_de_boor(knots, i, p - 1, x, last)
    if knots[i + p + 1] > knots[i + 1]:
        out += ((knots[i + p + 1] - x) / (knots[i + p + 1] - knots[i + 1])
                * cox_de_boor(knots, i + 1, p - 1, x, last))
    return out


def definition_point(surf, u, v):
    nu, nv = surf.points.shape[:2]
    u0, u1, v0, v1 = surf.domain
    bu = np.array([cox_de_boor(surf.knots_u, i, surf.degree_u, u, u1) for i in range(nu)])
    bv = np.array([cox_de_boor(surf.knots_v, j, surf.degree_v, v, v1) for j in range(nv)])
    r = bu[:, None] * bv[None, :] * surf.weights
    return (r[..., None] * surf.points).sum(axis=(0, 1)) / r.sum()


def params_off_knots(surf, n, h, seed):
    """Random (u, v) at least 3h away from every knot, so derivatives are smooth there."""
    rng = np.random.default_rng(seed)
    u0, u1, v0, v1 = surf.domain
    out = []
    for lo, hi, knots in ((u0, u1, surf.knots_u), (v0, v1, surf.knots_v)):
        x = rng.uniform(lo, hi, 4 * n)
        x = x[np.min(np.abs(x[:, None] - np.asarray(knots)[None, :]), axis=1) > 3 * h]
        out.append(x[:n])
    return out


def test_evaluate_matches_the_definition_including_domain_ends():
    surf = random_surface()
    u0, u1, v0, v1 = surf.domain
    rng = np.random.default_rng(3)
    u = np.concatenate([rng.uniform(u0, u1, 60), [u0, u1, u1, u0], surf.knots_u[4:6]])
    v = np.concatenate([rng.uniform(v0, v1, 60), [v0, v1, v0, v1], surf.knots_v[3:5]])
    (s,) = evaluate(surf, u, v, derivatives=0)
    truth = np.array([definition_point(surf, a, b) for a, b in zip(u, v)])
    assert np.max(np.abs(s - truth)) < 1e-12
    # clamped corners interpolate the corner control points
    assert np.allclose(s[60:64], surf.points[[0, -1, -1, 0], [0, -1, 0, -1]], atol=1e-13)


def test_evaluate_clamps_parameters_to_the_domain():
    surf = random_surface()
    u0, u1, v0, v1 = surf.domain
    a = evaluate(surf, [u0 - 5.0, u1 + 1.0], [v1 + 2.0, v0 - 1.0], 1)
    b = evaluate(surf, [u0, u1], [v1, v0], 1)
    for x, y in zip(a, b):
        assert np.array_equal(x, y)


@pytest.mark.parametrize("make", [random_surface, lambda: sphere((0.3, -1, 2), 1.7),
                                  lambda: torus((1, 2, 3), 2.0, 0.6)])
def test_first_and_second_derivatives_match_central_differences(make):
    surf = make()
    h = 1e-5
    u, v = params_off_knots(surf, 200, h, seed=1)
    s, su, sv, suu, suv, svv = evaluate(surf, u, v, derivatives=2)
    scale = np.max(np.abs(s)) + 1.0
    # Central differences: truncation h^2/6 |S'''| (~2e-11 |S'''|, with |S'''| up to ~1e2 times
    # the first-derivative magnitude here) and rounding eps |S| / h ~ 2e-11 scale. Observed
    # errors are 5-20x below these tolerances; a wrong derivative is off by O(|S'|).
    tol1 = 1e-8 * scale * max(1.0, np.abs(su).max(), np.abs(sv).max())
    fd_u = (evaluate(surf, u + h, v, 0)[0] - evaluate(surf, u - h, v, 0)[0]) / (2 * h)
    fd_v = (evaluate(surf, u, v + h, 0)[0] - evaluate(surf, u, v - h, 0)[0]) / (2 * h)
    assert np.max(np.abs(fd_u - su)) < tol1
    assert np.max(np.abs(fd_v - sv)) < tol1
    # Second derivatives: differences of the (verified) analytic first derivatives.
    tol2 = 2e-8 * scale * max(1.0, np.abs(suu).max(), np.abs(svv).max(), np.abs(suv).max())
    up, um = evaluate(surf, u + h, v, 1), evaluate(surf, u - h, v, 1)
    vp, vm = evaluate(surf, u, v + h, 1), evaluate(surf, u, v - h, 1)
    assert np.max(np.abs((up[1] - um[1]) / (2 * h) - suu)) < tol2
    assert np.max(np.abs((vp[2] - vm[2]) / (2 * h) - svv)) < tol2
    assert np.max(np.abs((vp[1] - vm[1]) / (2 * h) - suv)) < tol2
    assert np.max(np.abs((up[2] - um[2]) / (2 * h) - suv)) < tol2
    # lower derivative counts return the same leading arrays
    for d in (0, 1):
        for x, y in zip(evaluate(surf, u, v, d), (s, su, sv)):
            assert np.array_equal(x, y)


def test_evaluate_is_blocked_without_changing_results():
    surf = random_surface(seed=5)
    rng = np.random.default_rng(0)
    u0, u1, v0, v1 = surf.domain
    n = 40000                                 # > EVAL_BLOCK: several blocks
    u, v = rng.uniform(u0, u1, n), rng.uniform(v0, v1, n)
    full = evaluate(surf, u, v, 1)
    part = evaluate(surf, u[-7:], v[-7:], 1)
    for x, y in zip(full, part):
        assert np.allclose(x[-7:], y, rtol=0, atol=1e-14)


def test_bad_derivative_order_raises():
    with pytest.raises(ValueError, match="derivatives"):
        evaluate(random_surface(), [0.0], [0.0], derivatives=3)


def test_normals_are_unit_and_match_cross_product_at_regular_points():
    surf = random_surface(seed=2)
    u, v = params_off_knots(surf, 300, 1e-6, seed=4)
    _, su, sv = evaluate(surf, u, v, 1)
    cross = np.cross(su, sv)
    keep = np.linalg.norm(cross, axis=1) > 1e-3
    n = normals(surf, u, v)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-14)
    ref = cross[keep] / np.linalg.norm(cross[keep], axis=1)[:, None]
    assert np.max(np.abs(n[keep] - ref)) < 1e-12


def test_normals_on_collapsed_edge_use_the_limit_and_keep_orientation():
    # Triangle as a bilinear patch with the v = 0 edge collapsed to one point: Su = 0 there.
    tri = bilinear((0, 0, 0), (0, 0, 0), (1, 0, 0), (0, 1, 0))
    u = np.linspace(0.0, 1.0, 11)
    n_edge = normals(tri, u, np.zeros(11))
    n_in = normals(tri, u, np.full(11, 0.5))
    assert np.allclose(n_in, [0, 0, -1], atol=1e-14)      # orientation of Su x Sv inside
    assert np.allclose(n_edge, n_in, atol=1e-14)
    # also when the collapsed edge is at the domain's upper end (u = 1 collapsed: Sv = 0)
    tri2 = bilinear((0, 0, 0), (2, 0, 0), (0, 2, 0), (2, 0, 0))
    n2 = normals(tri2, np.ones(5), np.linspace(0, 1, 5))
    assert np.allclose(n2, normals(tri2, np.full(5, 0.5), np.linspace(0.1, 0.9, 5))[:1],
                       atol=1e-14)


def test_normals_of_fully_degenerate_surface_are_finite():
    point = bilinear((1, 2, 3), (1, 2, 3), (1, 2, 3), (1, 2, 3))
    n = normals(point, np.linspace(0, 1, 5), np.linspace(0, 1, 5))
    assert np.all(np.isfinite(n))
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
