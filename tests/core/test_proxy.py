"""The occlusion proxy (trace/proxy.py) against the exact tracer: it never misses a segment that
meets the surface away from its ends, grazing rays on a convex patch included, and it stays
within its stated deviation of the surface."""

import numpy as np

from riray.geometry.nurbs import evaluate
from riray.geometry.primitives import sphere
from riray.scene.model import ObjectMaterial, Patch, RenderSettings, Scene, SpecularObject
from riray.trace.proxy import Proxy
from riray.trace.scene_tracer import SceneTracer

R = 0.5


def ball():
    obj = SpecularObject("ball", [Patch("s", 0, surface=sphere((0.0, 0.0, 0.0), R))],
                         ObjectMaterial(kind="mirror"))
    return SceneTracer(Scene(objects=[obj], render=RenderSettings()))


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_grazing_rays_that_hit_meet_the_proxy():
    """Rays passing the sphere at 0.995-1.0005 R from its centre (grazing: a chord
    tessellation lies inside the sphere and misses many of those that hit): every ray the
    exact tracer finds hitting meets the proxy."""
    st = ball()
    proxy = Proxy.of(st.tracer)
    rng = np.random.default_rng(3)
    n = 20000
    d = unit(rng.normal(size=(n, 3)))
    side = unit(np.cross(d, rng.normal(size=(n, 3))))
    o = side * R * rng.uniform(0.995, 1.0005, n)[:, None] - 3 * d
    exact = st.tracer.intersect(o, d)
    assert 1000 < exact.hit.sum() < n
    met = proxy.crossed(o, d, np.full(n, np.inf), d)
    assert np.all(met[exact.hit])


def test_shells_lie_within_the_deviation_of_the_surface():
    """The deviation is small against the sphere, and a segment along the normal through a
    random surface point, from 10 deviations outside to 2 inside, meets a shell."""
    st = ball()
    proxy = Proxy.of(st.tracer)
    assert 0 < proxy.deviation < 1e-3 * 2 * R
    surf = st.scene.object.patches[0].surface
    rng = np.random.default_rng(4)
    u0, u1, v0, v1 = surf.domain
    (p,) = evaluate(surf, rng.uniform(u0, u1, 5000), rng.uniform(v0, v1, 5000), derivatives=0)
    n = unit(p)
    start = p + 10 * proxy.deviation * n
    near = proxy.crossed(start, -n, np.full(len(p), 12 * proxy.deviation), -n)
    assert np.all(near)


def test_rays_in_a_flat_sheets_plane_meet_the_proxy():
    """A flat open square (z = 0): rays lying in its plane through a point of the square
    touch the surface all along, yet pass between the two shells without crossing either; the
    wall along the rim catches them (the proxy is conservative: it may report what the exact
    search, for such a degenerate ray, does not). Rays in the plane whose line passes beyond
    the square's corners meet nothing."""
    from riray.geometry.primitives import bilinear
    P = lambda x, y: np.array([x, y, 0.0])  # noqa: E731
    sheet = SpecularObject("sheet", [Patch("m", 0, surface=bilinear(
        P(-1, -1), P(1, -1), P(-1, 1), P(1, 1)))], ObjectMaterial(kind="mirror"))
    proxy = Proxy.of(SceneTracer(Scene(objects=[sheet], render=RenderSettings())).tracer)
    rng = np.random.default_rng(5)
    n = 4000
    ang = rng.uniform(0, 2 * np.pi, n)
    d = np.stack([np.cos(ang), np.sin(ang), np.zeros(n)], axis=1)
    side = np.stack([-d[:, 1], d[:, 0], np.zeros(n)], axis=1)
    on = np.concatenate([rng.uniform(-0.9, 0.9, (n, 2)), np.zeros((n, 1))], axis=1)
    met = proxy.crossed(on - 4 * d, d, np.full(n, np.inf), d)
    assert np.all(met)
    beside = side * rng.choice([-1, 1], n)[:, None] * rng.uniform(1.5, 3, n)[:, None]
    assert not proxy.crossed(beside - 4 * d, d, np.full(n, np.inf), d).any()
