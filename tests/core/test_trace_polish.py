"""Newton's hit on a known patch from a nearby seed (trace.polish) against the closed-form
sphere; the normalized hit parameters the tracer reports; closed-patch detection; the
parameter codes of the cache."""

import numpy as np
import pytest

from riray.geometry.nurbs import evaluate
from riray.geometry.primitives import bilinear, cylinder, sphere
from riray.ritree.codec import PARAM_LEVELS, decode_params, encode_params
from riray.scene.model import ObjectMaterial, Patch, SpecularObject
from riray.trace.objectfn import trace_object
from riray.trace.patches import PatchTracer
from riray.trace.polish import Seeds, polish_hits, surface_at

R = 1.3
C = np.array([0.2, -0.1, 0.4])
MAX_MOVE = 0.05 * R
MIN_COS = np.cos(np.radians(10.0))


def angle(a, b):
    """Angle between unit vectors, stable for tiny angles."""
    return 2 * np.arctan2(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))


@pytest.fixture(scope="module")
def tracer():
    return PatchTracer(SpecularObject("s", [Patch("sphere", 0, surface=sphere(C, R))]))


def front_hits(n, rng, b_max=0.95, b_min=0.0):
    """Rays from outside at impact parameters in [b_min, b_max] R: (o, d, t, point, outward
    normal) of their analytic first hits."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    perp = np.cross(d, rng.normal(size=(n, 3)))
    perp /= np.linalg.norm(perp, axis=1)[:, None]
    b = R * np.sqrt(b_min ** 2 + (b_max ** 2 - b_min ** 2) * rng.random(n))
    o = C - 4 * R * d + b[:, None] * perp
    oc = o - C
    bb = np.einsum("ij,ij->i", oc, d)
    t = -bb - np.sqrt(bb * bb - (np.einsum("ij,ij->i", oc, oc) - R * R))
    p = o + t[:, None] * d
    return o, d, t, p, (p - C) / R


def seeds_of(tracer, o, d, p, nrm, rng, jitter):
    """Seeds from the tracer's own hit parameters, jittered by ``jitter`` (normalized units),
    with the analytic point and outward normal (it faces these rays)."""
    h = tracer.intersect(o, d)
    assert h.hit.all()
    uvn = tracer.normalized_uv(h.patch, h.u, h.v) + jitter * rng.uniform(-1, 1, (len(o), 2))
    return Seeds(h.patch, np.clip(uvn, 0.0, 1.0), p, nrm), h


def test_newton_hits_match_the_closed_form(tracer):
    """From seeds up to 2e-3 of the domain off, across Bezier piece borders, every ray's hit
    is the analytic one: point within 1e-9 R, normal within 1e-9 rad, t within 1e-9 R."""
    rng = np.random.default_rng(3)
    o, d, t, p, nrm = front_hits(4000, rng)
    seeds, _ = seeds_of(tracer, o, d, p, nrm, rng, 2e-3)
    h = polish_hits(tracer, o, d, seeds, MAX_MOVE, MIN_COS, np.zeros(len(o)),
                    np.full(len(o), np.inf))
    assert h.hit.all()
    assert np.abs(h.t - t).max() < 1e-9 * R
    assert np.linalg.norm(h.point - p, axis=1).max() < 1e-9 * R
    assert angle(h.normal, nrm).max() < 1e-9            # the sphere's normals point outward
    assert (h.patch == 0).all() and (h.cls == 0).all()


def test_seeds_across_the_seam_and_the_poles(tracer):
    """A hit just past the closed sphere's seam (u = 0 = 1) is found from a seed on the other
    side of it (the parameters wrap around); hits near the poles (collapsed rows, limit
    normals) are found too."""
    rng = np.random.default_rng(4)
    phi = rng.uniform(-0.02, 0.02, 300)                   # around the seam at phi = 0
    theta = rng.uniform(-1.2, 1.2, 300)
    theta[:40] = np.sign(theta[:40]) * rng.uniform(1.50, 1.565, 40)   # near the poles
    nrm = np.stack([np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi), np.sin(theta)], 1)
    p = C + R * nrm
    d = -nrm
    o = p - 2 * R * d
    seeds, h = seeds_of(tracer, o, d, p, nrm, rng, 0.0)
    u = seeds.uvn[:, 0].copy()
    seeds.uvn[:, 0] = np.where(u > 0.5, u - 0.999, u + 0.999)    # the seam's other side
    assert np.abs(seeds.uvn[:, 0] - u).min() > 0.95
    got = polish_hits(tracer, o, d, seeds, MAX_MOVE, MIN_COS, np.zeros(len(o)),
                      np.full(len(o), np.inf))
    assert got.hit.all()
    assert np.linalg.norm(got.point - p, axis=1).max() < 1e-9 * R
    assert angle(got.normal, nrm).max() < 1e-7


def test_far_roots_and_far_seeds_are_refused(tracer):
    """Newton's root is kept only near the seed's point, facing the seed's normal, inside
    (tmin, tmax): a seed at a grazing ray's second crossing (where it leaves the sphere, near
    the first: its normal turned to face the ray points the other way) gives no hit; so does a seed point farther than max_move, a tmax in
    front of the hit, and a patch id of a mesh patch."""
    rng = np.random.default_rng(5)
    o, d, t, p, nrm = front_hits(200, rng, b_max=0.999, b_min=0.99)    # grazing
    seeds, _ = seeds_of(tracer, o, d, p, nrm, rng, 0.0)
    # the second crossing's parameters: the far root of the same ray
    oc = o - C
    bb = np.einsum("ij,ij->i", oc, d)
    t2 = -bb + np.sqrt(bb * bb - (np.einsum("ij,ij->i", oc, oc) - R * R))
    far = tracer.intersect(o + (t[:, None] + 1e-6) * d, d)
    assert np.abs(far.t + t + 1e-6 - t2).max() < 1e-8
    inf, zero = np.full(len(o), np.inf), np.zeros(len(o))
    back = Seeds(seeds.patch, tracer.normalized_uv(far.patch, far.u, far.v), far.point, nrm)
    # with the facing test off, Newton from there lands on the far root (for most rays)...
    loose = polish_hits(tracer, o, d, back, 10 * R, -1.0, zero, inf)
    at_far = loose.hit & (np.abs(loose.t - t2) < 1e-9 * R)
    assert at_far.sum() > 0.9 * len(o)
    # ...which the facing test refuses; what it keeps is the front root
    strict = polish_hits(tracer, o, d, back, 10 * R, MIN_COS, zero, inf)
    assert not strict.hit[at_far].any()
    assert np.abs(strict.t[strict.hit] - t[strict.hit]).max(initial=0.0) < 1e-9 * R
    moved = Seeds(seeds.patch, seeds.uvn, p + 2 * MAX_MOVE * nrm, seeds.normal)
    assert not polish_hits(tracer, o, d, moved, MAX_MOVE, MIN_COS, zero, inf).hit.any()
    assert not polish_hits(tracer, o, d, seeds, MAX_MOVE, MIN_COS, zero, t - 1e-6).hit.any()
    assert polish_hits(tracer, o, d, seeds, MAX_MOVE, MIN_COS, zero, t + 1e-6).hit.all()
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    mixed = PatchTracer(SpecularObject("m", [Patch("mesh", 0, vertices=tri,
                                                   triangles=np.array([[0, 1, 2]]))]))
    h = polish_hits(mixed, np.array([[0.2, 0.2, 1.0]]), np.array([[0.0, 0.0, -1.0]]),
                    Seeds(np.array([0]), np.array([[0.2, 0.2]]), np.array([[0.2, 0.2, 0.0]]),
                          np.array([[0.0, 0.0, 1.0]])), 1.0, MIN_COS, np.zeros(1), np.full(1, 9.0))
    assert not h.hit.any()


def test_reported_parameters_are_normalized_hit_parameters(tracer):
    """trace_object's uv, scaled back to the patch's knot domain, evaluates to the first-hit
    point; misses report (0, 0)."""
    rng = np.random.default_rng(6)
    o, d, _, p, _ = front_hits(500, rng)
    o = np.concatenate([o, o[:50] + 10 * R])                  # the last 50 miss
    d = np.concatenate([d, -d[:50]])
    res = trace_object(tracer, ObjectMaterial("mirror"), o, d)
    surf = tracer.object.patches[0].surface
    u0, u1, v0, v1 = surf.domain
    hit = res.hit
    assert hit[:500].all() and not hit[500:].any()
    assert ((res.uv[hit] >= 0) & (res.uv[hit] <= 1)).all()
    s = evaluate(surf, u0 + res.uv[hit, 0] * (u1 - u0), v0 + res.uv[hit, 1] * (v1 - v0), 0)[0]
    assert np.linalg.norm(s - res.point[hit], axis=1).max() < 1e-9 * R
    assert not res.uv[~hit].any()


def test_closed_patches_are_detected():
    """A sphere and a cylinder are closed in u (around the axis), not in v; a bilinear patch
    is closed in neither."""
    t = PatchTracer(SpecularObject("c", [Patch("s", 0, surface=sphere(C, R)),
                                         Patch("c", 1, surface=cylinder(C, R, 2.0)),
                                         Patch("b", 2, surface=bilinear([0, 0, 0], [1, 0, 0],
                                                                        [0, 1, 0], [1, 1, 0]))]))
    assert t.closed.tolist() == [[True, False], [True, False], [False, False]]


def test_parameter_codes_round_trip():
    """Codes of [0, 1]^2 parameters come back within half a code step; values outside are
    clamped; non-finite values are refused."""
    rng = np.random.default_rng(7)
    uv = rng.random((10000, 2))
    q = encode_params(uv)
    assert q.dtype == np.uint16
    assert np.abs(decode_params(q) - uv).max() <= 0.5 / PARAM_LEVELS + 1e-15
    assert decode_params(encode_params(np.array([[-0.5, 1.5]]))).tolist() == [[0.0, 1.0]]
    with pytest.raises(ValueError, match="non-finite"):
        encode_params(np.array([[np.nan, 0.0]]))


def test_surface_at_matches_the_nurbs_evaluator_and_the_sphere():
    """``surface_at`` (the cache's derived hit points and normals, via Bezier pieces) against
    the NURBS evaluator and the closed-form sphere, poles and seam included; mesh patches and
    misses get no surface."""
    rng = np.random.default_rng(5)
    surf = sphere(C, R)
    mesh = Patch("tri", 1, vertices=np.eye(3), triangles=np.array([[0, 1, 2]]))
    tr = PatchTracer(SpecularObject("s", [Patch("sphere", 0, surface=surf), mesh]))
    uvn = np.concatenate([rng.random((500, 2)), [[0.3, 0.0], [0.7, 1.0], [0.0, 0.4],
                                                 [1.0, 0.4]]])
    p, n, ok = surface_at(tr, np.zeros(len(uvn), np.int64), uvn)
    assert ok.all()
    u0, u1, v0, v1 = surf.domain
    P, Su, Sv = evaluate(surf, u0 + uvn[:, 0] * (u1 - u0), v0 + uvn[:, 1] * (v1 - v0))
    assert np.abs(p - P).max() < 1e-12 * R
    assert np.abs(np.linalg.norm(p - C, axis=1) - R).max() < 1e-12 * R
    # the sphere's own outward normal, oriented as the surface is (Su x Sv), at the poles too
    outward = (p - C) / R
    side = np.sign(np.einsum("ij,ij->i", np.cross(Su, Sv)[:-4], outward[:-4]))
    assert np.all(side == side[0])
    assert angle(n, side[0] * outward).max() < 1e-9
    p2, n2, ok2 = surface_at(tr, np.array([1, -1]), np.full((2, 2), 0.5))
    assert not ok2.any() and not p2.any() and not n2.any()
