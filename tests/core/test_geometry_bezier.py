"""Bezier extraction, de Casteljau split, flat sub-patches and the batched evaluator."""

import re
from math import comb
from pathlib import Path

import numpy as np
import pytest

from riray.geometry.bezier import (bezier_eval, extract_bezier, nurbs_to_piece_param,
                                   piece_to_nurbs_param, split, subdivide_flat)
from riray.geometry.knots import blender_knots
from riray.geometry.nurbs import NurbsSurface, evaluate
from riray.geometry.primitives import bilinear, revolve, sphere, torus


def unclamped_surface(seed=0):
    """Uniform unclamped cubic x quadratic rational surface: domain ends are not knots of full
    multiplicity, so extraction must insert there too."""
    rng = np.random.default_rng(seed)
    return NurbsSurface(3, 2, blender_knots(4, 6, False, False, False),
                        blender_knots(3, 5, False, True, False),
                        rng.normal(size=(6, 5, 3)), rng.uniform(0.4, 2.0, (6, 5)))


SURFACES = [lambda: sphere((1, 2, 3), 2.0), lambda: torus((0, 0, 1), 2.0, 0.5),
            unclamped_surface,
            lambda: revolve([[0, -1], [0.6, -1], [1.2, -0.3], [1.0, 0.6], [0.5, 1.2], [0, 1.2]])]


def random_nets(n, p, q, seed):
    rng = np.random.default_rng(seed)
    ctrl = rng.normal(size=(n, p + 1, q + 1, 4))
    ctrl[..., 3] = rng.uniform(0.3, 2.0, (n, p + 1, q + 1))
    return ctrl


def definition_eval(ctrl, s, t):
    """Rational Bezier by the Bernstein definition (math.comb), per query."""
    p, q = ctrl.shape[1] - 1, ctrl.shape[2] - 1
    bu = np.stack([comb(p, i) * s ** i * (1 - s) ** (p - i) for i in range(p + 1)], 1)
    bv = np.stack([comb(q, j) * t ** j * (1 - t) ** (q - j) for j in range(q + 1)], 1)
    h = np.einsum("ni,nj,nijc->nc", bu, bv, ctrl)
    return h[:, :3] / h[:, 3:]


@pytest.mark.parametrize("make", SURFACES)
def test_extracted_pieces_evaluate_like_the_nurbs(make):
    surf = make()
    pieces = extract_bezier(surf)
    rng = np.random.default_rng(1)
    k = rng.integers(0, pieces.ctrl.shape[0], 3000)
    s, t = rng.random(3000), rng.random(3000)
    s[:8], t[:8] = [0, 1, 0, 1, 0.5, 0, 1, 0.5], [0, 0, 1, 1, 0, 0.5, 0.5, 1]
    got = bezier_eval(pieces.ctrl[k], s, t, 2)
    u, v = piece_to_nurbs_param(pieces, k, s, t)
    ref = evaluate(surf, u, v, 2)
    du = (pieces.u1 - pieces.u0)[k][:, None]
    dv = (pieces.v1 - pieces.v0)[k][:, None]
    chain = [1.0, du, dv, du * du, du * dv, dv * dv]      # local <-> NURBS parameter scaling
    for i, (g, r, f) in enumerate(zip(got, ref, chain)):
        # second derivatives may jump across piece borders (C1 knots): compare inside only
        rows = slice(8 if i >= 3 else 0, None)
        assert np.max(np.abs(g - r * f)[rows]) < 1e-11 * max(1.0, np.abs(r * f).max())
    # pieces tile the domain without gaps
    u0, u1, v0, v1 = surf.domain
    area = np.sum((pieces.u1 - pieces.u0) * (pieces.v1 - pieces.v0))
    assert np.isclose(area, (u1 - u0) * (v1 - v0), rtol=1e-14)
    assert np.all(pieces.u1 > pieces.u0) and np.all(pieces.v1 > pieces.v0)


def test_unclamped_extraction_covers_only_the_domain():
    pieces = extract_bezier(unclamped_surface())
    assert pieces.ctrl.shape == (3 * 3, 4, 3, 4)          # 3 u-spans x 3 v-spans
    assert pieces.u0.min() == 3.0 and pieces.u1.max() == 6.0


def test_nurbs_to_piece_param_inverts_piece_to_nurbs_param():
    pieces = extract_bezier(torus())
    rng = np.random.default_rng(2)
    k = rng.integers(0, pieces.ctrl.shape[0], 500)
    s, t = rng.uniform(0.01, 0.99, 500), rng.uniform(0.01, 0.99, 500)
    u, v = piece_to_nurbs_param(pieces, k, s, t)
    k2, s2, t2 = nurbs_to_piece_param(pieces, u, v)
    assert np.array_equal(k, k2)
    assert np.max(np.abs(s2 - s)) < 1e-13 and np.max(np.abs(t2 - t)) < 1e-13
    k3, s3, t3 = nurbs_to_piece_param(pieces, [1.0], [1.0])    # domain corner: last piece
    assert k3[0] == pieces.ctrl.shape[0] - 1 and s3[0] == 1.0 and t3[0] == 1.0


@pytest.mark.parametrize("axis", [1, 2])
def test_split_halves_reproduce_the_net(axis):
    ctrl = random_nets(50, 3, 2, 0)
    rng = np.random.default_rng(3)
    a, b = rng.random(50), rng.random(50)
    for tau in (0.5, 0.3):
        left, right = split(ctrl, axis, tau)
        if axis == 1:
            sl, tl, sr, tr, so, to = a, b, a, b, a * tau, b
            so_r = tau + a * (1 - tau)
            to_r = b
        else:
            sl, tl, sr, tr, so, to = a, b, a, b, a, b * tau
            so_r = a
            to_r = tau + b * (1 - tau)
        assert np.allclose(definition_eval(left, sl, tl), definition_eval(ctrl, so, to),
                           atol=1e-13)
        assert np.allclose(definition_eval(right, sr, tr), definition_eval(ctrl, so_r, to_r),
                           atol=1e-13)


@pytest.mark.parametrize("make, tol", [(lambda: sphere((1, 2, 3), 2.0), 1e-2),
                                       (lambda: torus((0, 0, 1), 2.0, 0.5), 1e-2),
                                       (unclamped_surface, 3e-2)])
def test_sub_patches_match_nurbs_and_boxes_contain_samples(make, tol):
    surf = make()
    pieces = extract_bezier(surf)
    sub = subdivide_flat(pieces, tol)
    m = sub.ctrl.shape[0]
    assert m > pieces.ctrl.shape[0]
    # the sub-patches tile every piece
    area = np.bincount(sub.piece, (sub.s1 - sub.s0) * (sub.t1 - sub.t0), pieces.ctrl.shape[0])
    assert np.allclose(area, 1.0, rtol=1e-13)
    rng = np.random.default_rng(4)
    j = np.repeat(np.arange(m), 16)
    a, b = rng.random(j.shape[0]), rng.random(j.shape[0])
    a[::16], b[::16] = 0.0, 0.0
    a[1::16], b[1::16] = 1.0, 1.0
    (pts,) = bezier_eval(sub.ctrl, a, b, 0, index=j)
    s = sub.s0[j] + a * (sub.s1 - sub.s0)[j]
    t = sub.t0[j] + b * (sub.t1 - sub.t0)[j]
    u, v = piece_to_nurbs_param(pieces, sub.piece[j], s, t)
    (ref,) = evaluate(surf, u, v, 0)
    assert np.max(np.abs(pts - ref)) < 1e-12
    assert np.all((ref >= sub.lo[j]) & (ref <= sub.hi[j]))
    # flat: sample points stay within flat_tol of the bilinear corner interpolation, loosely
    # (the criterion is on the control net, which bounds polynomial patches)
    corners = np.stack([bezier_eval(sub.ctrl, np.full(m, x), np.full(m, y), 0)[0]
                        for x, y in ((0, 0), (1, 0), (0, 1), (1, 1))])
    c00, c10, c01, c11 = (c[j] for c in corners)
    bil = (((1 - a) * (1 - b))[:, None] * c00 + (a * (1 - b))[:, None] * c10
           + ((1 - a) * b)[:, None] * c01 + (a * b)[:, None] * c11)
    assert np.max(np.linalg.norm(pts - bil, axis=1)) < 2 * tol


def test_subdivision_normal_cone_splits_flat_but_bent_patches():
    # A bilinear, twisted patch: the control net equals its bilinear interpolation (deviation
    # 0) but normals turn by ~90 degrees, so the cone criterion must split it.
    surf = bilinear((0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 1))
    sub = subdivide_flat(extract_bezier(surf), 1.0)
    assert sub.ctrl.shape[0] > 1
    untwisted = subdivide_flat(extract_bezier(bilinear((0, 0, 0), (1, 0, 0), (0, 1, 0),
                                                       (1, 1, 0))), 1.0)
    assert untwisted.ctrl.shape[0] == 1


def test_max_depth_limits_subdivision():
    pieces = extract_bezier(sphere())
    sub = subdivide_flat(pieces, 1e-9, max_depth=3)
    assert sub.ctrl.shape[0] == pieces.ctrl.shape[0] * 8
    with pytest.raises(ValueError, match="flat_tol"):
        subdivide_flat(pieces, 0.0)


@pytest.mark.parametrize("p, q", [(3, 3), (2, 1), (1, 4), (5, 2)])
def test_bezier_eval_matches_definition_and_finite_differences(p, q):
    n = 400
    ctrl = random_nets(n, p, q, p * 10 + q)
    rng = np.random.default_rng(5)
    s, t = rng.uniform(0.05, 0.95, n), rng.uniform(0.05, 0.95, n)
    S, Ss, St, Sss, Sst, Stt = bezier_eval(ctrl, s, t, 2)
    assert np.max(np.abs(S - definition_eval(ctrl, s, t))) < 1e-12
    h = 1e-5
    # Central differences: truncation h^2/6 |D^3 S| plus rounding eps |S| / h ~ 1e-11. These
    # random rational nets have derivatives up to ~scale (first/second) and ~scale^2 (third
    # and fourth), so 1e-8 scale^2 bounds the error with margin, while a wrong derivative is
    # off by O(scale) >> tolerance.
    scale = max(1.0, np.abs(Ss).max(), np.abs(St).max(), np.abs(Sss).max(), np.abs(Stt).max(),
                np.abs(Sst).max())
    tol = 1e-8 * scale ** 2
    fs = (definition_eval(ctrl, s + h, t) - definition_eval(ctrl, s - h, t)) / (2 * h)
    ft = (definition_eval(ctrl, s, t + h) - definition_eval(ctrl, s, t - h)) / (2 * h)
    assert np.max(np.abs(fs - Ss)) < tol
    assert np.max(np.abs(ft - St)) < tol
    ps, ms = bezier_eval(ctrl, s + h, t, 1), bezier_eval(ctrl, s - h, t, 1)
    pt, mt = bezier_eval(ctrl, s, t + h, 1), bezier_eval(ctrl, s, t - h, 1)
    assert np.max(np.abs((ps[1] - ms[1]) / (2 * h) - Sss)) < tol
    assert np.max(np.abs((pt[2] - mt[2]) / (2 * h) - Stt)) < tol
    assert np.max(np.abs((pt[1] - mt[1]) / (2 * h) - Sst)) < tol
    assert np.max(np.abs((ps[2] - ms[2]) / (2 * h) - Sst)) < tol
    for d in (0, 1):
        for x, y in zip(bezier_eval(ctrl, s, t, d), (S, Ss, St)):
            assert np.allclose(x, y, rtol=1e-13, atol=1e-13)


def test_bezier_eval_index_form_equals_gathered_form():
    ctrl = random_nets(30, 3, 3, 9)
    rng = np.random.default_rng(6)
    idx = rng.integers(0, 30, 20000)                       # > one block
    s, t = rng.random(20000), rng.random(20000)
    a = bezier_eval(ctrl[idx], s, t, 1)
    b = bezier_eval(ctrl, s, t, 1, index=idx)
    for x, y in zip(a, b):
        assert np.array_equal(x, y)
    with pytest.raises(ValueError, match="derivatives"):
        bezier_eval(ctrl, s, t, 3)


def test_geometry_sources_avoid_numpy2_only_api():
    """The engine must run on numpy 1.26: none of the numpy-2-only names may appear."""
    banned = r"np\.(trapezoid|concat\b|astype\b|unique_values|unique_counts|unique_all|" \
             r"unique_inverse|permute_dims|matrix_transpose|vecdot|vecmat|matvec|isdtype|" \
             r"cumulative_sum|cumulative_prod|bitwise_count|linalg\.vecdot|linalg\.matrix_norm)"
    root = Path(__file__).resolve().parents[2] / "core" / "geometry"
    for path in root.glob("*.py"):
        text = path.read_text()
        assert not re.search(banned, text), f"{path.name} uses a numpy-2-only API"
        assert not re.search(r"asarray\([^)]*copy=", text), f"{path.name}: asarray(copy=)"
