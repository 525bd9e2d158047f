"""First hits next to degenerate edges and patch boundaries, against closed forms.

The rational sphere's poles are collapsed control rows (an edge of every polar Bezier piece
shrinks to a point, where S_u = 0), and its seam and knot lines are piece boundaries. Rays
aimed within 1e-9 ... 1e-3 rad of a pole, or across the seam, a quarter boundary or the
equator, from outside at incidences from head-on to near-grazing, must report the entry (not
the exit, a chord 2 R cos behind it), its point and normal, and leave the glass ball in the
direction two Snell refractions give. Truth: the ray-sphere quadratic; for an ellipsoid (the
sphere scaled and turned, its poles off the axes), the same quadratic in the unit sphere's
coordinates.
"""

import numpy as np
import pytest

from riray.geometry.bezier import bezier_eval
from riray.geometry.primitives import sphere, transform
from riray.scene.model import Patch, SpecularObject
from riray.scene.samples import build
from riray.trace.objectfn import refract, trace_object
from riray.trace.patches import PatchTracer, project_nets

N_RAYS = 4000
# Near-grazing rays: incidence cosines drawn log-uniform in this range (89.97 to 88.3 degrees).
GRAZING_COS = (5e-4, 3e-2)
# Tolerances, metres and radians. A root is within the tracer's Newton tolerance (~5e-12 m
# here) of the ray, so along it within that over cos (<= 1e-8 m at the smallest cosine); the
# exit instead of the entry is off by a chord 2 R cos >= 7e-5 m.
T_TOL = 2e-8
POINT_TOL = 2e-8
# A normal next to a pole is good to ~3e-7 rad (the patch's own normal evaluation there);
# elsewhere to ~1e-10.
NORMAL_TOL = 1e-6
# f's output direction, times the entry's incidence cosine: after a grazing entry the inner ray
# meets the far side at the critical angle and leaves grazing, where the output direction's
# sensitivity to the normals grows as 1 / cos.
DIR_TOL = 1e-5


def _angle(a, b):
    return 2.0 * np.arctan2(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))


def _frame(n):
    """Two unit tangents orthogonal to unit normals n (N, 3)."""
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    return e1, np.cross(n, e1)


def _unit_targets(rng, n):
    """Unit vectors: half within 1e-9 ... 1e-3 rad of a pole (either), half next to the seam
    (azimuth 0), the quarter boundaries (azimuth k pi/2) or the equator (1e-12 ... 1e-3 rad
    away, either side)."""
    k = n // 2
    delta = 10.0 ** rng.uniform(-9, -3, k)
    az = rng.uniform(0, 2 * np.pi, k)
    z = np.where(rng.random(k) < 0.5, -1.0, 1.0)
    pole = np.stack([np.sin(delta) * np.cos(az), np.sin(delta) * np.sin(az),
                     z * np.cos(delta)], 1)
    m = n - k
    off = rng.choice([-1.0, 1.0], m) * 10.0 ** rng.uniform(-12, -3, m)
    lat = rng.uniform(-1.5, 1.5, m)
    az = rng.integers(0, 4, m) * (np.pi / 2) + off
    eq = rng.random(m) < 0.3
    lat[eq], az[eq] = off[eq], rng.uniform(0, 2 * np.pi, eq.sum())
    edge = np.stack([np.cos(lat) * np.cos(az), np.cos(lat) * np.sin(az), np.sin(lat)], 1)
    return np.concatenate([pole, edge])


def _rays_into(points, normals, rng):
    """Rays from outside aimed at ``points`` (N, 3) with outward unit ``normals``: incidence
    cosines uniform in [0.03, 1], a third log-uniform in GRAZING_COS, from 0.05 ... 2 m."""
    n = len(points)
    cos = rng.uniform(0.03, 1.0, n)
    g = rng.random(n) < 1 / 3
    cos[g] = 10.0 ** rng.uniform(*np.log10(GRAZING_COS), g.sum())
    phi = rng.uniform(0, 2 * np.pi, n)
    e1, e2 = _frame(normals)
    d = -cos[:, None] * normals + np.sqrt(1 - cos ** 2)[:, None] * (
        np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    d /= np.linalg.norm(d, axis=1)[:, None]
    return points - rng.uniform(0.05, 2.0, n)[:, None] * d, d


def _entry(o, d, center, radius):
    """Nearest t of the ray-sphere quadratic (rays that hit), in the stable form."""
    oc = o - center
    b = np.einsum("ij,ij->i", oc, d)
    c = np.einsum("ij,ij->i", oc, oc) - radius * radius
    return c / (-b + np.sqrt(b * b - c))


def _check_hits(h, o, d, t_true, n_true):
    p_true = o + t_true[:, None] * d
    nrm = h.normal * np.sign(np.einsum("ij,ij->i", h.normal, n_true))[:, None]
    wrong = ~h.hit | ~(np.abs(h.t - t_true) <= T_TOL) \
        | ~(np.linalg.norm(h.point - p_true, axis=1) <= POINT_TOL) \
        | ~(_angle(nrm, n_true) <= NORMAL_TOL)
    assert np.count_nonzero(wrong) == 0, (np.flatnonzero(wrong)[:5], h.t[wrong][:5],
                                          t_true[wrong][:5])


@pytest.fixture(scope="module")
def glass_ball():
    obj = build("glass_sphere").object
    surf = obj.patches[0].surface
    center = 0.5 * (surf.points.reshape(-1, 3).min(0) + surf.points.reshape(-1, 3).max(0))
    radius = 0.5 * float(np.ptp(surf.points[..., 2]))
    return obj, PatchTracer(obj), center, radius


def test_sphere_pole_and_seam_first_hits(glass_ball):
    """4,000 rays at the poles, seam and patch boundaries: every first hit is the entry, with
    its point and normal, and f leaves the ball after two refractions in the closed-form
    direction."""
    obj, tracer, center, radius = glass_ball
    rng = np.random.default_rng(2027)
    normals = _unit_targets(rng, N_RAYS)
    o, d = _rays_into(center + radius * normals, normals, rng)
    t_true = _entry(o, d, center, radius)
    n_true = (o + t_true[:, None] * d - center) / radius
    _check_hits(tracer.intersect(o, d), o, d, t_true, n_true)

    eta = 1.0 / obj.material.ior
    inner, _ = refract(d, n_true, np.full(N_RAYS, eta))
    p_in = o + t_true[:, None] * d
    t_out = -2.0 * np.einsum("ij,ij->i", p_in - center, inner)    # chord of the inner ray
    n_out = (p_in + t_out[:, None] * inner - center) / radius
    out, tir = refract(inner, -n_out, np.full(N_RAYS, 1.0 / eta))
    assert not tir.any()
    f = trace_object(tracer, obj.material, o, d)
    assert np.all(f.hit & ~f.null & (f.events == 2))
    cos = -np.einsum("ij,ij->i", d, n_true)
    assert np.all(_angle(f.out_dir, out) * cos <= DIR_TOL)


def test_ellipsoid_pole_first_hits():
    """The sphere scaled (1, 0.6, 1.7) and turned, so its poles lie off the axes: rays next to
    them (1e-9 ... 1e-3 rad on the unit sphere) and across its seam and boundaries hit the
    entry, with the quadric's normal."""
    rng = np.random.default_rng(11)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    lin = q @ np.diag([0.1, 0.06, 0.17])
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = lin, (0.3, -0.2, 0.5)
    obj = SpecularObject("e", [Patch("ellipsoid", 0, surface=transform(sphere(), m))])
    tracer = PatchTracer(obj)
    inv = np.linalg.inv(lin)
    unit = _unit_targets(rng, 2000)
    points = unit @ lin.T + m[:3, 3]
    normals = unit @ inv                       # the quadric's gradient: inv^T inv (x - c)
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    o, d = _rays_into(points, normals, rng)
    # in the unit sphere's coordinates the ray is o' + t d' (d' not unit): same t
    ou, du = (o - m[:3, 3]) @ inv.T, d @ inv.T
    a = np.einsum("ij,ij->i", du, du)
    b = np.einsum("ij,ij->i", ou, du)
    c = np.einsum("ij,ij->i", ou, ou) - 1.0
    t_true = c / (-b + np.sqrt(b * b - a * c))
    x = ou + t_true[:, None] * du
    n_true = x @ inv
    n_true /= np.linalg.norm(n_true, axis=1)[:, None]
    _check_hits(tracer.intersect(o, d), o, d, t_true, n_true)


def test_newton_starts_on_a_collapsed_edge(glass_ball):
    """Newton seeded on a polar sub-patch's collapsed edge (S_s = 0 there: a singular
    Jacobian), at its nearer end (a corner seed), steps off the edge and converges (but for a
    few runs, which the search retries) on the hit, 1e-6 ... 1e-3 (net parameter) from the
    pole, at incidence cosines 0.3 ... 1 (now and then on its mirror root across the edge,
    t < 0, the same point)."""
    _, tracer, center, radius = glass_ball
    rng = np.random.default_rng(5)
    n = 400
    grp = tracer.groups[0]
    south = np.flatnonzero(grp.v0 == 0.0)               # flat sub-patches at the south pole
    nets = grp.ctrl[south[rng.integers(0, len(south), n)]]
    s_root, t_root = rng.uniform(0.05, 0.95, n), 10.0 ** rng.uniform(-6, -3, n)
    target = bezier_eval(nets, s_root, t_root, 0)[0]
    normals = (target - center) / radius
    e1, _ = _frame(normals)
    cos = rng.uniform(0.3, 1.0, n)[:, None]
    d = -cos * normals + np.sqrt(1.0 - cos * cos) * e1
    s, t = np.round(s_root), np.zeros(n)
    ok = tracer.solve_newton(project_nets(nets, target - d, d), 2, 2, s, t)
    assert np.count_nonzero(ok) >= 0.98 * n
    P = bezier_eval(nets[ok], s[ok], t[ok], 0)[0]
    # the hit is 1.5e-8 m or more from the pole; Newton's tolerance is 5e-12 m / cos
    assert np.all(np.linalg.norm(P - target[ok], axis=1) <= 1e-9)
