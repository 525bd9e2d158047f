"""The piece of a NURBS parameter found for all rays at once (trace.polish's lookup over the
tracer's breakpoint table) against the per-patch ``bezier.nurbs_to_piece_param``; and Newton
from seeds without a point and normal against seeds given the surface's."""

from dataclasses import fields

import numpy as np
import pytest

from riray.geometry import bezier as bz
from riray.geometry.nurbs import NurbsSurface
from riray.geometry.primitives import cylinder, sphere
from riray.scene.model import Patch, SpecularObject
from riray.trace import polish
from riray.trace.patches import PatchTracer
from riray.trace.polish import Seeds, polish_hits, surface_at

# NURBS (degree u, degree v, knots u, knots v): uneven spans off [0, 1], 1 to 8 pieces a side
GRIDS = [(2, 3, [0.5] * 3 + [0.9, 1.7, 2.05] + [3.2] * 3, [-1.0] * 4 + [-0.3, 0.4] + [2.0] * 4),
         (3, 2, [0.0] * 4 + [0.1, 0.15, 0.4, 0.55, 0.6, 0.9] + [1.0] * 4,
          [2.0] * 3 + [2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 5.5] + [6.0] * 3),
         (1, 1, [0.0, 0.0, 1.0, 1.0], [0.0, 0.0, 0.25, 1.0, 1.0])]


def wavy(p, q, ku, kv, z0):
    """A height field z = z0 + bumps over the control grid of those knots."""
    nu, nv = len(ku) - p - 1, len(kv) - q - 1
    x, y = np.meshgrid(np.linspace(0, 1, nu), np.linspace(0, 1, nv), indexing="ij")
    z = z0 + 0.1 * np.sin(7 * x + 3 * y)
    return NurbsSurface(p, q, np.array(ku), np.array(kv), np.stack([x, y, z], axis=-1),
                        1.0 + 0.3 * x * y)


@pytest.fixture(scope="module")
def tracer():
    """A mesh patch first (no pieces), closed patches (sphere, cylinder), uneven grids."""
    tri = Patch("tri", 0, vertices=np.eye(3) + 5.0, triangles=np.array([[0, 1, 2]]))
    nurbs = [sphere((0, 0, 3), 0.5), cylinder((2, 0, 3), 0.4, 1.0)]
    nurbs += [wavy(*g, z0=-1.0 - i) for i, g in enumerate(GRIDS)]
    return PatchTracer(SpecularObject("o", [tri] + [Patch(f"p{i}", i, surface=s)
                                                     for i, s in enumerate(nurbs)]))


def reference(tracer, patch, u, v):
    """Each patch's rays through ``nurbs_to_piece_param`` on its own pieces."""
    k, s, t = np.zeros(len(patch), np.int64), np.zeros(len(patch)), np.zeros(len(patch))
    for pid in np.unique(patch):
        m = np.flatnonzero(patch == pid)
        kk, s[m], t[m] = bz.nurbs_to_piece_param(tracer.pieces[int(pid)], u[m], v[m])
        k[m] = tracer.piece_base[pid] + kk
    return k, s, t


def probes(lo, hi, starts, ends, rng):
    """Parameters along one side: piece starts and ends, one ulp either side, domain ends,
    outside the domain, random inside."""
    at = np.unique(np.concatenate([starts, ends]))
    return np.concatenate([at, np.nextafter(at, -np.inf), np.nextafter(at, np.inf),
                           [lo, hi, lo - 0.3, hi + 0.5, lo - 1e-300, -0.0, 1e9, -1e9],
                           lo + (hi - lo) * rng.random(8)])


def test_piece_lookup_equals_the_per_patch_search(tracer):
    """Piece indices equal bit for bit, (s, t) within 1e-15, on every patch's grid of probes
    (breakpoints, their neighbours, domain ends, outside), the patches' rays interleaved."""
    rng = np.random.default_rng(11)
    patch, u, v = [], [], []
    for pid, pcs in tracer.pieces.items():
        du = probes(pcs.u0.min(), pcs.u1.max(), pcs.u0, pcs.u1, rng)
        dv = probes(pcs.v0.min(), pcs.v1.max(), pcs.v0, pcs.v1, rng)
        gu, gv = np.meshgrid(du, dv, indexing="ij")
        patch.append(np.full(gu.size, pid))
        u.append(gu.ravel())
        v.append(gv.ravel())
    order = rng.permutation(sum(len(x) for x in patch))
    patch, u, v = (np.concatenate(x)[order] for x in (patch, u, v))
    assert 0 not in tracer.pieces and tracer.piece_break_count[0].tolist() == [0, 0]
    assert tracer.closed[1:3, 0].all()                              # sphere, cylinder
    assert tracer.piece_break_count[1:].max() == 8                 # a full last search step
    k, s, t = polish._piece_of(tracer, patch, u, v)
    rk, rs, rt = reference(tracer, patch, u, v)
    np.testing.assert_array_equal(k, rk)
    np.testing.assert_allclose(s, rs, rtol=0, atol=1e-15)
    np.testing.assert_allclose(t, rt, rtol=0, atol=1e-15)
    # no rays
    assert all(len(x) == 0 for x in polish._piece_of(tracer, patch[:0], u[:0], v[:0]))


def facing_surface(tracer, patch, uvn, d):
    """``surface_at``'s points and normals, the normals turned to face the rays ``d``."""
    point, normal, _ = surface_at(tracer, patch, uvn)
    return point, np.where((np.einsum("ij,ij->i", normal, d) > 0)[:, None], -normal, normal)


def assert_same_hits(a, b):
    """Every field of two PatchHits equal, bit for bit."""
    for f in fields(a):
        np.testing.assert_array_equal(getattr(a, f.name), getattr(b, f.name), err_msg=f.name)


def test_seeds_without_point_take_the_surface(tracer):
    """Seeds without a point and normal give the same hits, bit for bit, as seeds given
    ``surface_at``'s (turned to face the ray) at the parameters each run starts from: the
    first, then the second for the rays still without a hit; mesh rows get none; the hits from
    seeds near the hit are the exact tracer's."""
    rng = np.random.default_rng(12)
    n = 3000
    pid = rng.integers(1, len(tracer.object.patches), n)
    aim, _, _ = surface_at(tracer, pid, rng.uniform(0.05, 0.95, (n, 2)))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    o = aim - 3.0 * d
    exact = tracer.intersect(o, d)
    ok = exact.hit
    o, d, exact = o[ok], d[ok], exact.take(np.flatnonzero(ok))
    m = len(o)
    patch = exact.patch.copy()
    uvn = tracer.normalized_uv(exact.patch, exact.u, exact.v)
    alt = np.clip(uvn + 1e-3 * rng.uniform(-1, 1, (m, 2)), 0.0, 1.0)
    # first parameters near the hit, but a third far off (their second ones near it); a few
    # rows on the mesh patch
    third = np.arange(m) % 3 == 0
    seed = np.where(third[:, None], 1.0 - alt, alt)
    patch[:20] = 0
    args = (0.05, np.cos(np.radians(20.0)), np.zeros(m), np.full(m, np.inf))
    implicit = Seeds(patch, seed, None, None, alt)
    got = polish_hits(tracer, o, d, implicit, *args)
    assert implicit.point is None and implicit.normal is None      # the caller's untouched
    want = polish_hits(tracer, o, d, Seeds(patch, seed, *facing_surface(tracer, patch, seed, d)),
                       *args)
    assert want.hit[third].mean() < 0.5
    r = np.flatnonzero(~want.hit)
    want.put(r, polish_hits(tracer, o[r], d[r],
                            Seeds(patch[r], alt[r], *facing_surface(tracer, patch[r], alt[r],
                                                                     d[r])),
                            args[0], args[1], args[2][r], args[3][r]))
    assert_same_hits(got, want)
    assert not got.hit[:20].any() and got.hit[20:].mean() > 0.95
    # from near the hit (the first parameters, else the second): the exact tracer's
    near = ~third.copy()
    near[r] = True
    hit = np.flatnonzero(got.hit & near)
    assert len(hit) > 0.9 * m
    np.testing.assert_array_equal(got.patch[hit], exact.patch[hit])
    # to Newton's tolerance, but for a grazing ray's other crossing close by
    err = np.linalg.norm(got.point[hit] - exact.point[hit], axis=1)
    assert np.mean(err < 1e-7 * tracer.diag) > 0.995
