"""Triangle meshes: closest hit vs a brute-force linear solve, watertightness of a closed cube
at its edges and vertices, grazing rays, interpolated attributes, any-hit."""

import numpy as np
import pytest

from riray.scene.model import Mesh
from riray.trace.meshes import MeshSet


def brute_closest(o, d, tris, tmin, tmax):
    """Nearest hit per ray by solving o + t d = v0 + b1 e1 + b2 e2 for every (ray, triangle)."""
    v0, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    n, m = len(o), len(tris)
    a = np.empty((n, m, 3, 3))
    a[..., 0] = -d[:, None, :]
    a[..., 1] = e1[None]
    a[..., 2] = e2[None]
    rhs = o[:, None, :] - v0[None]
    ok = np.abs(np.linalg.det(a)) > 1e-12
    sol = np.full((n, m, 3), np.nan)
    sol[ok] = np.linalg.solve(a[ok], rhs[ok][..., None])[..., 0]
    t, b1, b2 = sol[..., 0], sol[..., 1], sol[..., 2]
    with np.errstate(invalid="ignore"):
        hit = ok & (b1 >= 0) & (b2 >= 0) & (b1 + b2 <= 1) & (t >= tmin[:, None]) & (t <= tmax[:, None])
    t = np.where(hit, t, np.inf)
    return t.min(axis=1), t


def cube(center=(0.0, 0.0, 0.0), h=1.0, name="cube"):
    c = np.asarray(center)
    v = c + h * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return Mesh(name, v, f, "m")


def test_closest_hit_matches_brute_force():
    rng = np.random.default_rng(0)
    m, n = 150, 600
    centers = rng.uniform(-3, 3, (m, 1, 3))
    tris = centers + rng.normal(scale=0.6, size=(m, 3, 3))
    meshes = [Mesh(f"m{i}", tris[i:i + 50].reshape(-1, 3), np.arange(150).reshape(-1, 3) % 150,
                   "x") for i in range(0, m, 50)]
    ms = MeshSet(meshes)
    o = rng.uniform(-5, 5, (n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    tmin = rng.uniform(0, 0.5, n)
    tmax = np.where(rng.random(n) < 0.3, rng.uniform(1, 5, n), np.inf)
    hit = ms.closest_hit(o, d, tmin, tmax)
    t_ref, t_all = brute_closest(o, d, tris, tmin, tmax)
    np.testing.assert_array_equal(hit.hit, np.isfinite(t_ref))
    h = hit.hit
    np.testing.assert_allclose(hit.t[h], t_ref[h], rtol=1e-9)
    np.testing.assert_allclose(t_all[np.flatnonzero(h), hit.tri[h]], t_ref[h], rtol=1e-9)
    np.testing.assert_array_equal(hit.mesh[h], hit.tri[h] // 50)
    np.testing.assert_allclose(hit.point[h], o[h] + hit.t[h, None] * d[h], atol=1e-9)
    # geometric normal: unit, orthogonal to the triangle's edges
    e1 = tris[hit.tri[h], 1] - tris[hit.tri[h], 0]
    np.testing.assert_allclose(np.linalg.norm(hit.geo_normal[h], axis=1), 1.0)
    np.testing.assert_allclose(np.einsum("ij,ij->i", hit.geo_normal[h], e1), 0, atol=1e-9)
    assert np.all(hit.tri[~h] == -1) and np.all(np.isinf(hit.t[~h]))
    np.testing.assert_array_equal(ms.any_hit(o, d, tmin, tmax), h)


def test_cube_edges_and_vertices_never_leak():
    ms = MeshSet([cube(center=(0.3, -0.2, 0.1), h=0.7)])
    v = ms.vertices
    edges = {tuple(sorted((int(a), int(b)))) for f in ms.faces for a, b in zip(f, np.roll(f, 1))}
    targets = [v]                                                  # vertices
    for frac in (0.5, 1 / 3, 0.123456789):
        targets += [v[a] + frac * (v[b] - v[a]) for a, b in edges]  # cube and diagonal edges
    targets = np.vstack([np.atleast_2d(x) for x in targets])
    rng = np.random.default_rng(1)
    k = 40
    tgt = np.repeat(targets, k, axis=0)
    for inside in (False, True):
        if inside:
            o = 0.3 + rng.uniform(-0.5, 0.5, (len(tgt), 3)) + np.array([0, -0.5, -0.2])
        else:
            dirs = rng.normal(size=(len(tgt), 3))
            o = tgt + 5 * dirs / np.linalg.norm(dirs, axis=1)[:, None]
        d = tgt - o
        dist = np.linalg.norm(d, axis=1)
        d /= dist[:, None]
        hit = ms.closest_hit(o, d)
        assert hit.hit.all(), f"{(~hit.hit).sum()} leaks (inside={inside})"
        if inside:
            np.testing.assert_allclose(hit.t, dist, rtol=1e-9)
        else:
            assert np.all(hit.t <= dist * (1 + 1e-9))
        assert ms.any_hit(o, d).all()


def test_grazing_ray_gives_no_nan():
    ms = MeshSet([Mesh("tri", np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float),
                       np.array([[0, 1, 2]]), "m")])
    o = np.array([[-1.0, 0.2, 0.0], [-1.0, 0.0, 0.0], [-1.0, 0.2, 1e-300], [0.2, 0.2, 0.0]])
    d = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    with np.errstate(all="raise"):
        hit = ms.closest_hit(o, d)
        ms.any_hit(o, d)
    assert not hit.hit.any()
    for f in (hit.t, hit.b1, hit.point, hit.normal, hit.uv):
        assert not np.isnan(f).any()


def test_interpolated_uv_and_smooth_normal():
    # a roof: two triangles folded along x = 0, smooth; uv = (x, y)
    v = np.array([[-1, 0, 0], [0, 0, 1], [0, 1, 1], [-1, 1, 0], [1, 0, 0], [1, 1, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])
    roof = Mesh("roof", v, f, "m", uvs=v[:, :2].copy(), smooth=True)
    flat = Mesh("flat", v + [0, 0, -5], f, "m", smooth=False)
    ms = MeshSet([roof, flat])
    o = np.array([[-0.5, 0.3, 5.0], [0.0, 0.7, 5.0], [0.5, 0.4, 5.0]])
    d = np.tile([0.0, 0.0, -1.0], (3, 1))
    hit = ms.closest_hit(o, d)
    assert hit.hit.all() and np.all(hit.mesh == 0)
    np.testing.assert_allclose(hit.uv, o[:, :2], atol=1e-12)
    s = np.sqrt(0.5)
    np.testing.assert_allclose(hit.normal[1], [0, 0, 1], atol=1e-12)         # on the ridge
    # vertex normals: ridge (0,0,1); eaves (-+s, 0, s); halfway between -> normalised mean
    left = np.array([-s * 0.5, 0, 0.5 * (1 + s)])
    np.testing.assert_allclose(hit.normal[0], left / np.linalg.norm(left), atol=1e-12)
    np.testing.assert_allclose(hit.geo_normal[0], [-s, 0, s], atol=1e-12)
    below = ms.closest_hit(o + [0, 0, -5.5], d)
    assert np.all(below.mesh == 1)
    np.testing.assert_allclose(below.normal, below.geo_normal)
    np.testing.assert_array_equal(below.uv, 0.0)


def test_empty_and_invalid():
    ms = MeshSet([])
    hit = ms.closest_hit(np.zeros((2, 3)), np.tile([0, 0, 1.0], (2, 1)))
    assert not hit.hit.any() and not ms.any_hit(np.zeros((2, 3)), np.tile([0, 0, 1.0], (2, 1))).any()
    with pytest.raises(ValueError, match="'bad'.*triangles"):
        MeshSet([Mesh("bad", np.zeros((3, 3)), np.array([[0, 1, 3]]), "m")])
    with pytest.raises(ValueError, match="'bad'.*uvs"):
        MeshSet([Mesh("bad", np.zeros((3, 3)), np.array([[0, 1, 2]]), "m", uvs=np.zeros((2, 2)))])
