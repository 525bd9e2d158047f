"""The environment's fast hit tests (quads against ray packets, apex grids for shadow rays,
the BVH for the rest) against a plain reference: Moller-Trumbore on every (ray, triangle) pair
in numpy, the nearest hit per ray, equal t to the lower triangle index. Small sets (a room)
take the quad path, large ones (and their non-parallelogram triangles) the BVH; both are
checked on random rays and on the hard ones: grazing, through shared edges and vertices and
a quad's diagonal, starting on a surface, cut by tmax, with zero direction components."""

import numpy as np
import pytest

import riray.trace.meshes as meshes_mod
from riray.scene.model import Mesh
from riray.scene.rooms import room
from riray.trace.bvh import BVH
from riray.trace.meshes import MeshSet
from riray.trace.planar import BARY_EPS, PARALLEL_EPS

T_RTOL = 1e-12          # t of a hit: relative agreement with the reference


def reference_t(ms, o, d, tmin, tmax):
    """(n, m) t of every (ray, triangle) pair, inf where it misses: Moller-Trumbore with the
    triangles grown by BARY_EPS (barycentric units), parallel below PARALLEL_EPS."""
    v = ms.vertices[ms.faces]                                   # (m, 3, 3)
    e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    p = np.cross(d[:, None, :], e2[None])                       # (n, m, 3)
    det = np.einsum("nmk,mk->nm", p, e1)
    area2 = np.linalg.norm(np.cross(e1, e2), axis=1)
    ok = np.abs(det) > PARALLEL_EPS * area2
    inv = 1.0 / np.where(ok, det, 1.0)
    s = o[:, None, :] - v[None, :, 0]
    b1 = np.einsum("nmk,nmk->nm", s, p) * inv
    q = np.cross(s, e1[None])
    b2 = np.einsum("nk,nmk->nm", d, q) * inv
    t = np.einsum("mk,nmk->nm", e2, q) * inv
    ok &= (b1 >= -BARY_EPS) & (b2 >= -BARY_EPS) & (b1 + b2 <= 1 + BARY_EPS)
    ok &= (t >= tmin[:, None]) & (t <= tmax[:, None])
    return np.where(ok, t, np.inf)


def check_closest(ms, o, d, tmin, tmax):
    """MeshSet.closest agrees with the reference: same hits and misses, t within T_RTOL, the
    triangle the reference's nearest (its lowest index among exactly equal t; among t equal
    within rounding, one of them), barycentrics that give the hit point."""
    ref = reference_t(ms, o, d, tmin, tmax)
    tref = ref.min(axis=1)
    h = ms.closest(o, d, tmin, tmax)
    hit = np.isfinite(tref)
    np.testing.assert_array_equal(h.tri >= 0, hit)
    assert np.all(np.isinf(h.t[~hit])) and np.all(h.b1[~hit] == 0) and np.all(h.b2[~hit] == 0)
    i = np.flatnonzero(hit)
    np.testing.assert_allclose(h.t[i], tref[i], rtol=T_RTOL, atol=1e-15)
    exact = ref[i] == tref[i, None]
    near = np.abs(ref[i] - tref[i, None]) <= T_RTOL * np.abs(tref[i, None]) + 1e-15
    lowest = np.argmax(exact, axis=1)
    unique_near = near.sum(axis=1) == 1
    np.testing.assert_array_equal(h.tri[i][unique_near], lowest[unique_near])
    assert near[np.arange(len(i)), h.tri[i]].all(), "the triangle is not one hit nearest"
    tied = exact.sum(axis=1) > 1                                 # exact ties: the lowest index
    np.testing.assert_array_equal(h.tri[i][tied], lowest[tied])
    v = ms.vertices[ms.faces[h.tri[i]]]
    w = np.stack([1 - h.b1[i] - h.b2[i], h.b1[i], h.b2[i]], axis=1)
    np.testing.assert_allclose(np.einsum("nc,nck->nk", w, v), o[i] + h.t[i, None] * d[i],
                               atol=1e-9)
    np.testing.assert_array_equal(ms.any_hit(o, d, tmin, tmax), hit)
    return h


def unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def hard_rays(rng, n):
    """Random rays in the room and the hard cases (origins, unit dirs, tmin, tmax)."""
    o = rng.uniform((-3.9, -3.9, 0.05), (3.9, 3.9, 3.9), (n, 3))
    d = unit(rng.normal(size=(n, 3)))
    tmin = np.where(np.arange(n) % 3 == 0, 0.5, 0.0)
    tmax = np.where(np.arange(n) % 4 == 0, 2.0, np.inf)
    x = rng.uniform(1.2, 3.5, 8) * np.where(np.arange(8) % 2, 1.0, -1.0)  # off the table
    cases = [  # (origin, direction, tmin, tmax)
        *[((a, a, 2.0), (0, 0, -1), 0.0, np.inf) for a in x],          # floor diagonal
        *[((a, -a, 2.0), (0, 0, -1), 0.0, np.inf) for a in x],         # off it
        ((0.5, 0.5, 2.0), (0, 0, -1), 0.0, 2.0),                      # tmax at the hit
        ((0.5, 0.5, 2.0), (0, 0, -1), 0.0, 2.0 - 1e-9),               # tmax just short
        ((1.0, 2.0, 0.0), unit((0.3, 0.2, 0.9)), 0.0, np.inf),        # on the floor, t = 0
        ((1.0, 2.0, 0.0), unit((0.3, 0.2, 0.9)), 1e-9, np.inf),       # ... tmin past it
        ((1.0, 2.0, 0.0), unit((0.3, 0.2, -0.9)), 1e-9, np.inf),      # ... going down
        *[((0.1, 0.2, 1.0), ax, 0.0, np.inf) for ax in np.vstack([np.eye(3), -np.eye(3)])],
        ((0.3, -0.2, 1.0), unit((1.0, 0.0, -1.0)), 0.0, np.inf),      # one zero component
        ((0.0, 0.0, 2.0), unit((-4.0, -4.0, -2.0)), 0.0, np.inf),     # into a room corner
        ((0.0, 1.0, 2.0), unit((4.0, 3.0, 0.0)), 0.0, np.inf),        # along the wall edge
        ((-3.0, 0.0, 1e-9), unit((1.0, 0.1, -1e-9)), 0.0, np.inf),    # grazing the floor
        ((-3.0, 0.0, 1e-3), unit((1.0, 0.1, 0.0)), 0.0, np.inf),      # parallel to it
        ((0.0, 0.0, 3.0), unit((0.8, 0.5, -1.0)), 0.0, np.inf),       # past the table edge
    ]
    co, cd, ct0, ct1 = (np.array([c[k] for c in cases], dtype=np.float64) for k in range(4))
    return (np.concatenate([o, co]), np.concatenate([d, unit(cd)]),
            np.concatenate([tmin, ct0]), np.concatenate([tmax, ct1]))


def soup(rng, m, center=(0.0, 0.0, 1.5), spread=1.5, size=0.3):
    """m random triangles (no two form a parallelogram)."""
    c = rng.uniform(-spread, spread, (m, 1, 3)) + center
    return Mesh("soup", (c + rng.normal(scale=size, size=(m, 3, 3))).reshape(-1, 3),
                np.arange(3 * m).reshape(-1, 3), "m")


def grid(n=24, z=0.4, size=6.0):
    """A flat n x n grid of squares (2 n^2 triangles sharing edges and vertices)."""
    s = np.linspace(-size / 2, size / 2, n + 1)
    x, y = np.meshgrid(s, s, indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    a, b, c, e = i, i + n + 1, i + n + 2, i + 1
    f = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, e], -1)], axis=1)
    return Mesh("grid", v, f.reshape(-1, 3), "m")


@pytest.fixture
def walk_counter(monkeypatch):
    """Counts the rays that walk a BVH for a closest hit."""
    calls = []
    real = BVH.closest_hit
    monkeypatch.setattr(BVH, "closest_hit", lambda self, o, *a, **k: calls.append(len(o))
                        or real(self, o, *a, **k))
    return calls


def test_room_takes_the_quad_path(walk_counter):
    ms = MeshSet(room()[0])
    assert ms.num_quads == ms.num_triangles // 2 and len(ms._rest) == 0
    o, d, tmin, tmax = hard_rays(np.random.default_rng(0), 3000)
    h = check_closest(ms, o, d, tmin, tmax)
    assert walk_counter == []
    # the floor's two triangles give exactly equal t on its diagonal: the lower index
    diag = (o[:, 0] == o[:, 1]) & (d[:, 2] == -1.0) & np.isinf(tmax)
    assert diag.sum() == 8 and np.all(h.tri[diag] == 0)


def test_quads_and_leftover_triangles_together(walk_counter):
    rng = np.random.default_rng(1)
    ms = MeshSet(room()[0] + [soup(rng, 40)])
    assert ms.num_quads == 36 and len(ms._rest) == 40
    check_closest(ms, *hard_rays(rng, 3000))
    assert sum(walk_counter) > 0


def test_large_sets_walk_the_bvh(walk_counter):
    rng = np.random.default_rng(2)
    walls = room(table=False)[0]
    ms = MeshSet(walls + [soup(rng, 300), grid()])
    assert ms.num_triangles > meshes_mod.SMALL_SET
    assert ms.num_quads == 6 and len(ms._rest) == ms.num_triangles - 12   # walls only
    o, d, tmin, tmax = hard_rays(rng, 2000)
    # rays through the grid's shared vertices and edges, from above and below
    g = np.linspace(-3.0, 3.0, 7)
    pts = np.array([(x, y, 0.4) for x in g for y in g] + [(x + 0.125, y, 0.4) for x in g
                                                              for y in g])
    for side in (1.0, -1.0):
        o = np.concatenate([o, pts + (0.2, 0.1, 0.3 * side)])
        d = np.concatenate([d, unit(np.tile((-0.2, -0.1, -0.3 * side), (len(pts), 1)))])
    tmin = np.concatenate([tmin, np.zeros(2 * len(pts))])
    tmax = np.concatenate([tmax, np.full(2 * len(pts), np.inf)])
    check_closest(ms, o, d, tmin, tmax)
    assert sum(walk_counter) > 0


@pytest.mark.parametrize("meshes", ["room", "large"])
def test_shadow_rays_toward_a_point_light(meshes):
    rng = np.random.default_rng(3)
    ms = MeshSet(room()[0] if meshes == "room"
                 else room(table=False)[0] + [soup(rng, 200, size=0.15), grid(20)])
    light = np.array([1.6, -1.2, 3.6])
    pad = 4e-6
    p = rng.uniform((-3.9, -3.9, 0.0), (3.9, 3.9, 3.9), (4000, 3))
    p[:1000, 2] = 1e-6                                   # just above the floor
    to = light - p
    dist = np.linalg.norm(to, axis=1)
    dirs = to / dist[:, None]
    bent = np.arange(len(p)) % 5 == 0                    # these do not end at the light
    dirs[bent] = unit(dirs[bent] + rng.normal(scale=0.05, size=(bent.sum(), 3)))
    ref = np.isfinite(reference_t(ms, p, dirs, np.zeros(len(p)), dist)).any(axis=1)
    got = ms.any_hit(p, dirs, 0.0, dist, light, pad)
    np.testing.assert_array_equal(got, ref)
    assert 0.01 < ref.mean() < 0.99
    if meshes == "large":
        assert ms.prepare_apex(light, pad) is not None   # the rest went through the grid
    np.testing.assert_array_equal(ms.any_hit(p, dirs, 0.0, dist), ref)


def test_quad_and_bvh_paths_agree(monkeypatch):
    rng = np.random.default_rng(4)
    meshes = room()[0]
    fast = MeshSet(meshes)
    monkeypatch.setattr(meshes_mod, "SMALL_SET", 0)
    monkeypatch.setattr(meshes_mod, "MAX_PLANES", 0)
    slow = MeshSet(meshes)
    assert fast.num_quads == 36 and slow.num_quads == 0
    o, d, tmin, tmax = hard_rays(rng, 3000)
    a, b = fast.closest(o, d, tmin, tmax), slow.closest(o, d, tmin, tmax)
    np.testing.assert_array_equal(a.tri, b.tri)
    for f in ("t", "b1", "b2"):
        np.testing.assert_allclose(getattr(a, f), getattr(b, f), rtol=T_RTOL, atol=1e-12)
    np.testing.assert_array_equal(fast.any_hit(o, d, tmin, tmax), slow.any_hit(o, d, tmin, tmax))


def test_bench_reports_the_environment_pass_and_its_floor():
    from riray.bench.exact_bench import bench_scene
    row = bench_scene("glass_sphere", size=12, workers=1)
    assert row["environment_rays"] >= 144 and row["environment_cpu_s"] > 0
    for key in ("environment_cpu_us_per_ray", "environment_floor_cpu_us_per_ray"):
        assert np.isfinite(row[key]) and row[key] > 0, key
