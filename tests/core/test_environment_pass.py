"""The environment pass: every camera ray's environment hit found once and reused, a room's
parallelograms tested as quads against ray packets (same hits as the BVH of their triangles),
shadow rays skip quads whose planes have both ends on one side, constant colours not
evaluated per ray."""

import numpy as np

import riray.trace.meshes as meshes_mod
import riray.trace.planar as planar_mod
import riray.trace.shading as shading_mod
from riray.render.frame import ExactAnswerer, shade_share
from riray.scene.camera import Shot, camera_rays
from riray.scene.model import Mesh
from riray.scene.rooms import room
from riray.scene.samples import build
from riray.trace.meshes import MeshSet
from riray.trace.scene_tracer import SceneTracer


def random_rays(n, seed, lo=(-3.9, -3.9, 0.05), hi=(3.9, 3.9, 3.9)):
    rng = np.random.default_rng(seed)
    o = rng.uniform(lo, hi, (n, 3))
    d = rng.normal(size=(n, 3))
    return o, d / np.linalg.norm(d, axis=1)[:, None]


def test_room_quads_have_the_same_hits(monkeypatch):
    meshes = room()[0]
    fast = MeshSet(meshes)
    assert fast.num_quads == 36 and len(fast._rest) == 0
    monkeypatch.setattr(meshes_mod, "SMALL_SET", 0)
    monkeypatch.setattr(meshes_mod, "MAX_PLANES", 0)
    slow = MeshSet(meshes)
    assert slow.num_quads == 0
    o, d = random_rays(4000, 1)
    tmin = np.where(np.arange(4000) % 3 == 0, 0.5, 0.0)
    tmax = np.where(np.arange(4000) % 4 == 0, 2.0, np.inf)
    a, b = fast.closest(o, d, tmin, tmax), slow.closest(o, d, tmin, tmax)
    np.testing.assert_array_equal(a.tri, b.tri)
    for f in ("t", "b1", "b2"):     # quads: plane and parallelogram coordinates, same to rounding
        np.testing.assert_allclose(getattr(a, f), getattr(b, f), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(fast.any_hit(o, d, tmin, tmax), slow.any_hit(o, d, tmin, tmax))


def test_only_parallelograms_pair():
    # a square (two triangles on a diagonal) and a kite (its fourth corner moved off)
    sq = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    kite = sq + [[3, 0, 0], [3, 0, 0], [3.2, 0.3, 0], [3, 0, 0]]
    f = np.array([[0, 1, 2], [0, 2, 3]])
    ms = MeshSet([Mesh("sq", sq, f, "m"), Mesh("kite", kite, f, "m")])
    ta, tb, q0, eu, ev = meshes_mod.parallelograms(ms.vertices, ms.faces, np.arange(4))
    assert sorted(zip(ta.tolist(), tb.tolist())) == [(0, 1)]
    np.testing.assert_allclose(np.abs(np.cross(eu, ev))[:, 2], [1.0])


def test_shadow_rays_between_points_inside_skip_the_quads(monkeypatch):
    ms = MeshSet(room(table=False)[0])
    assert ms.num_quads == 6
    pairs = []
    real = planar_mod.Packets.dots
    monkeypatch.setattr(planar_mod.Packets, "dots",
                        lambda self, dirs, axis, k, *a: pairs.append(len(k)) or
                        real(self, dirs, axis, k, *a))
    o, _ = random_rays(500, 2)
    light = np.array([1.6, -1.2, 3.6])
    to = light - o
    dist = np.linalg.norm(to, axis=1)
    assert not ms.any_hit(o, to / dist[:, None], 0.0, dist, light, 1e-6).any()
    assert sum(pairs) == 0                   # both ends inside: no quad tested in full
    assert ms.any_hit(o, -to / dist[:, None], 0.0, np.full(len(o), 1e3)).all()
    assert sum(pairs) > 0


def test_camera_rays_meet_the_environment_once():
    st = SceneTracer(build("glass_sphere"))
    cam, w, h = Shot("close", 24, 24).resolve(st.scene)
    o, d = camera_rays(cam, w, h)
    traced = []
    real = st.env.meshes.closest
    st.env.meshes.closest = lambda o_, *a, **k: traced.append(len(o_)) or real(o_, *a, **k)
    res = shade_share(st, o, d, ExactAnswerer(st))
    s = res.stats
    # camera rays once, then each object hit's output and reflected ray once
    assert sum(traced) == len(o) + s["output_rays"] + s.get("reflected_rays", 0)
    st.env.meshes.closest = real
    env_only = np.setdiff1d(np.arange(len(o)), res.hit)
    np.testing.assert_array_equal(res.color[env_only], st.env.shade_rays(o[env_only], d[env_only]))


def test_shade_rays_takes_a_hit_record():
    st = SceneTracer(build("teapot"))
    o, d = random_rays(3000, 3)
    hits = st.env.closest(o, d)
    np.testing.assert_array_equal(st.env.shade_rays(o, d, hits=hits), st.env.shade_rays(o, d))
    np.testing.assert_array_equal(hits.t, st.env.hit_distance(o, d))


def test_constant_colours_are_not_evaluated_per_ray(monkeypatch):
    st = SceneTracer(build("glass_sphere"))
    o, d = random_rays(2000, 4)
    ref = st.env.shade_rays(o, d)
    seen = []
    real = shading_mod.eval_texture
    monkeypatch.setattr(shading_mod, "eval_texture",
                        lambda tex, *a: seen.append(tex.kind) or real(tex, *a))
    np.testing.assert_array_equal(st.env.shade_rays(o, d), ref)
    assert seen and "constant" not in seen          # ceiling and legs: constant colours
