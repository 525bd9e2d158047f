"""The exact tracer's culling and twin-root search against independent truths: the end-on
control-hull test against a triangle cover of the projected control points (Caratheodory), and
the nearest hit on the Utah teapot against a fine tessellation traced by the mesh tracer."""

import numpy as np
import pytest

from riray.geometry.tessellate import tessellate
from riray.render.camera import camera_rays
from riray.scene.model import Mesh
from riray.scene.samples import build
from riray.trace.meshes import MeshSet
from riray.trace.patches import PatchTracer, _hull_meets, _project, _ray_planes


def in_some_triangle(p, eps):
    """(N,) whether the origin lies in a triangle of three of the 2D points p (N, K, 2),
    i.e. in their convex hull (Caratheodory); ``eps`` widens every triangle (-1: shrinks)."""
    n, k, _ = p.shape
    i, j, l = np.array([(a, b, c) for a in range(k) for b in range(a + 1, k)
                        for c in range(b + 1, k)]).T
    a, b, c = p[:, i], p[:, j], p[:, l]

    def cross(u, v):
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
    area = cross(b - a, c - a)
    s1, s2, s3 = cross(b - a, -a), cross(c - b, -b), cross(a - c, -c)
    sg = np.sign(area)
    inside = (sg * s1 >= -eps) & (sg * s2 >= -eps) & (sg * s3 >= -eps) & (np.abs(area) > 0)
    return inside.any(axis=1)


def test_end_on_hull_test_matches_triangle_cover():
    """Random rational nets (weights > 0) and rays aimed near them: _hull_meets is True
    wherever the ray's line passes through the control hull (never a false miss), and False
    wherever it clearly does not."""
    rng = np.random.default_rng(11)
    n = 3000
    pts = rng.normal(size=(n, 1, 1, 3)) * 0.2 + rng.normal(size=(n, 4, 4, 3)) * \
        rng.choice([0.02, 0.1, 0.5], (n, 1, 1, 1))
    w = rng.uniform(0.3, 2.0, (n, 4, 4, 1))
    ctrl = np.concatenate([pts * w, w], axis=-1)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    aim = pts.reshape(n, 16, 3).mean(axis=1) + rng.normal(size=(n, 3)) * 0.15
    o = aim - 3.0 * d
    got = _hull_meets(_project(ctrl, o, d))
    n1, n2 = _ray_planes(d)
    flat = pts.reshape(n, 16, 3) - o[:, None, :]
    p2 = np.stack([flat @ n1.T, flat @ n2.T], -1)[np.arange(n), :, np.arange(n)]
    scale = np.abs(p2).max(axis=(1, 2))[:, None]
    surely_in = in_some_triangle(p2 / scale[..., None], -1e-9)
    maybe_in = in_some_triangle(p2 / scale[..., None], 1e-9)
    assert np.all(got[surely_in])
    assert not np.any(got[~maybe_in])
    assert 0.2 < surely_in.mean() < 0.8


@pytest.fixture(scope="module")
def teapot():
    scene = build("teapot")
    tracer = PatchTracer(scene.object)
    meshes = []
    for p in scene.object.patches:
        v, t = tessellate(p.surface, 96, 96)
        meshes.append(Mesh(name=p.name, vertices=v, triangles=t, material=""))
    return scene, tracer, MeshSet(meshes)


@pytest.mark.parametrize("camera", ["close", "zoom"])
def test_teapot_nearest_hits_match_fine_tessellation(teapot, camera):
    """Camera rays on the teapot (grazing rays at the spout, handle and lid knob have two roots
    in one net): no patch hit lies behind a clearly nearer hit of a fine tessellation, and the
    two agree on nearly every ray. A missed twin root shows up as a hit ~0.01 too far."""
    scene, tracer, mesh = teapot
    o, d = camera_rays(scene.camera(camera), 160, 160)
    ph = tracer.intersect(o, d)
    mh = mesh.closest_hit(o, d, np.full(len(o), 1e-9), np.full(len(o), np.inf))
    both = ph.hit & mh.hit
    assert both.sum() > 3000
    # tessellation error of a 96 x 96 grid on the teapot is ~1e-4 of its size
    assert not np.any(ph.t[both] > mh.t[both] + 2e-3)
    assert np.mean(np.abs(ph.t[both] - mh.t[both]) < 2e-3) > 0.999
