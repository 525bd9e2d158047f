"""Newton's proven stop (trace.newton): a full step whose Taylor remainder, bounded by the net's
second-derivative bounds, is at most tol / 2 ends the run without a confirming iteration. The
bounds against sampled second partials (and exactly where S'' is constant); the residual at
every proven stop against the surface evaluated independently; polish hits with the stop
against the closed-form sphere and cylinder, grazing rays and rays next to piece edges
included."""

import numpy as np
import pytest

from riray.geometry import bezier as bz
from riray.geometry.primitives import cylinder, sphere
from riray.scene.model import Patch, SpecularObject
from riray.trace.newton import newton, project_nets, second_derivative_bounds
from riray.trace.patches import PatchTracer
from riray.trace.polish import Seeds, polish_hits

R = 1.3
C = np.array([0.2, -0.1, 0.4])
H = 2.0                                  # cylinder height
MIN_COS = np.cos(np.radians(10.0))


def _grid(n):
    s, t = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    return s.ravel(), t.ravel()


def test_bounds_hold_on_random_rational_nets():
    """Every sampled |S_ss|, |S_st|, |S_tt| of random rational nets of several degrees (weights
    0.3-2) lies within the bounds."""
    rng = np.random.default_rng(11)
    s, t = _grid(41)
    for p, q in ((1, 1), (2, 1), (2, 2), (3, 3), (3, 2)):
        ctrl = np.empty((20, p + 1, q + 1, 4))
        ctrl[..., 3] = rng.uniform(0.3, 2.0, (20, p + 1, q + 1))
        ctrl[..., :3] = rng.normal(size=(20, p + 1, q + 1, 3)) * ctrl[..., 3:]
        bound = second_derivative_bounds(ctrl)
        idx = np.repeat(np.arange(20), len(s))
        _, _, _, Sss, Sst, Stt = bz.bezier_eval(ctrl, np.tile(s, 20), np.tile(t, 20), 2,
                                               index=idx)
        got = np.stack([np.linalg.norm(x, axis=1).reshape(20, -1).max(1)
                        for x in (Sss, Sst, Stt)], 1)
        assert (got <= bound * (1 + 1e-12) + 1e-12).all()


def test_bounds_are_exact_where_the_second_partials_are_constant():
    """A polynomial net of degree (2, 1) with a parabola along s: S_ss, S_st constant, S_tt 0;
    the bounds equal them (the degree factors p (p - 1), p q are right)."""
    x = np.array([0.0, 0.5, 1.0])
    ctrl = np.zeros((1, 3, 2, 4))
    ctrl[0, :, 0, :3] = np.stack([x, [0.0, 0.0, 0.0], [0.0, 2.0, 0.0]], 1)     # z: 0, 2, 0
    ctrl[0, :, 1, :3] = np.stack([x, [1.0, 1.5, 2.0], [0.0, 2.0, 0.0]], 1)     # y: 1, 1.5, 2
    ctrl[0, ..., 3] = 1.0
    s, t = _grid(5)
    _, _, _, Sss, Sst, Stt = bz.bezier_eval(np.repeat(ctrl, len(s), 0), s, t, 2)
    truth = [np.linalg.norm(Sss, axis=1).max(), np.linalg.norm(Sst, axis=1).max(), 0.0]
    assert np.allclose(truth, [8.0, 1.0, 0.0])
    assert np.allclose(second_derivative_bounds(ctrl)[0], truth, rtol=1e-12, atol=1e-12)


@pytest.fixture(scope="module")
def shapes():
    return PatchTracer(SpecularObject("s", [Patch("sphere", 0, surface=sphere(C, R)),
                                            Patch("tube", 1, surface=cylinder(C, R, H))]))


def _rays_at(tracer, rng, n, grazing):
    """Rays whose exact crossing is at random points (s*, t*) of random pieces, half of them
    within 1e-3 of a piece edge; with ``grazing`` at 1-4 degrees to the tangent plane. Returns
    (group, local piece, o, d, s*, t*)."""
    g = 0 if tracer.piece_nets[0].shape[1:3] == (3, 3) else 1
    nets = tracer.piece_nets[g]
    k = rng.integers(0, len(nets), n)
    st = rng.uniform(0.05, 0.95, (n, 2))
    edge = rng.random(n) < 0.5
    st[edge, 0] = np.where(rng.random(edge.sum()) < 0.5, 1e-3, 1 - 1e-3) * rng.uniform(0.2, 1)
    P, Ps, Pt = bz.bezier_eval(nets, st[:, 0], st[:, 1], 1, index=k)
    nrm = np.cross(Ps, Pt)
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    tang = np.cross(nrm, rng.normal(size=(n, 3)))
    tang /= np.linalg.norm(tang, axis=1)[:, None]
    ang = np.radians(rng.uniform(1, 4, n)) if grazing else np.radians(rng.uniform(20, 90, n))
    d = np.cos(ang)[:, None] * tang - np.sin(ang)[:, None] * nrm
    return g, k, P - 0.3 * R * d, d, st[:, 0], st[:, 1]


@pytest.mark.parametrize("grazing", [False, True])
@pytest.mark.parametrize("tol_rel", [1e-4, 1e-6, 1e-8])
def test_proven_stops_end_within_tolerance(shapes, grazing, tol_rel):
    """From seeds 2e-3 off their crossing, every run the proven stop converged ends within tol
    of the ray (the surface evaluated afresh at its (s, t)), and the stop saves iterations:
    fewer in all than with the residual test alone, whose runs converge the same."""
    rng = np.random.default_rng(21 + int(grazing))
    g, k, o, d, s0, t0 = _rays_at(shapes, rng, 3000, grazing)
    nets = shapes.piece_nets[g][k]
    p, q = nets.shape[1] - 1, nets.shape[2] - 1
    tol = tol_rel * R
    proj = project_nets(nets, o, d)
    seed = (np.clip(s0 + rng.uniform(-2e-3, 2e-3, len(k)), 0, 1),
            np.clip(t0 + rng.uniform(-2e-3, 2e-3, len(k)), 0, 1))
    runs = {}
    for bounded in (False, True):
        s, t = seed[0].copy(), seed[1].copy()
        stats = {"newton_iters": 0}
        ok = newton(proj, p, q, s, t, tol, stats,
                    shapes.piece_bounds[g][k] if bounded else None)
        runs[bounded] = ok, s, t, stats["newton_iters"]
    ok, s, t, iters = runs[True]
    assert ok.mean() > 0.99 and (ok == runs[False][0]).all()
    P = bz.bezier_eval(nets[ok], s[ok], t[ok], 0)[0]
    rel = P - o[ok]
    dist = np.linalg.norm(rel - np.einsum("ij,ij->i", rel, d[ok])[:, None] * d[ok], axis=1)
    assert dist.max() <= tol
    assert iters < 0.9 * runs[False][3]


@pytest.mark.parametrize("grazing", [False, True])
def test_polish_hits_on_sphere_and_cylinder_match_the_closed_form(shapes, grazing):
    """Polish hits (the proven stop on) from seeds up to 1e-3 of the domain off land on the
    closed-form crossing of the sphere (|P - C| = R) and the cylinder (distance R from its axis,
    within its height) and on the ray, within 1e-9 R, grazing rays and rays next to piece
    edges included."""
    rng = np.random.default_rng(31 + int(grazing))
    for pid in (0, 1):
        base = shapes.piece_base[pid]
        n_pieces = len(shapes.pieces[pid].ctrl)
        g = shapes.piece_group[base]
        k = base + rng.integers(0, n_pieces, 2000)
        loc = shapes.piece_local[k]
        st = rng.uniform(0.05, 0.95, (2000, 2))
        st[:1000, 1] = np.where(rng.random(1000) < 0.5, 2e-3, 1 - 2e-3)     # next to an edge
        P, Ps, Pt = bz.bezier_eval(shapes.piece_nets[g], st[:, 0], st[:, 1], 1, index=loc)
        nrm = np.cross(Ps, Pt)
        nrm /= np.linalg.norm(nrm, axis=1)[:, None]
        tang = np.cross(nrm, rng.normal(size=(2000, 3)))
        tang /= np.linalg.norm(tang, axis=1)[:, None]
        ang = np.radians(rng.uniform(6, 10, 2000) if grazing else rng.uniform(30, 90, 2000))
        d = np.cos(ang)[:, None] * tang - np.sin(ang)[:, None] * nrm
        o = P - 0.5 * R * d
        rect = shapes.piece_rect[k]
        u = rect[:, 0] + st[:, 0] * (rect[:, 1] - rect[:, 0])
        v = rect[:, 2] + st[:, 1] * (rect[:, 3] - rect[:, 2])
        uvn = shapes.normalized_uv(np.full(2000, pid), u, v)
        uvn = np.clip(uvn + rng.uniform(-1e-3, 1e-3, uvn.shape), 0.0, 1.0)
        seeds = Seeds(np.full(2000, pid), uvn, P, nrm)
        h = polish_hits(shapes, o, d, seeds, 0.05 * R, MIN_COS, np.zeros(2000),
                        np.full(2000, np.inf))
        assert h.hit.all()
        rel = h.point - o
        off_ray = rel - np.einsum("ij,ij->i", rel, d)[:, None] * d
        assert np.linalg.norm(off_ray, axis=1).max() < 1e-9 * R
        if pid == 0:
            assert np.abs(np.linalg.norm(h.point - C, axis=1) - R).max() < 1e-9 * R
        else:
            assert np.abs(np.linalg.norm((h.point - C)[:, :2], axis=1) - R).max() < 1e-9 * R
            assert np.abs(h.point[:, 2] - C[2]).max() <= 0.5 * H + 1e-9 * R
        assert np.abs(h.t - 0.5 * R).max() < 1e-9 * R / np.sin(ang).min()
