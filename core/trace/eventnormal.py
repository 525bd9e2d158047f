"""The normal a surface event reflects or refracts about, on smooth meshes.

A smooth mesh's shading normal (the blend of its triangle's corner normals) differs from the
triangle's own (geometric) normal. Used as is, it can send a reflected ray below the triangle
(into the surface it just left) or a refracted ray back to the side it came from, and a ray
can arrive from behind it although in front of the triangle: the black speckles and leaks of
naive smooth shading. Here every event first orients both normals by the side of the triangle
the ray meets (so which side a ray is on never depends on the shading normal), then uses the
shading normal where its event is sound, and elsewhere tilts it toward the geometric normal
(along the great circle between them) just far enough that the event is: the incoming ray
meets its front, a reflected ray (mirror, total internal reflection) leaves above the triangle
by at least ``min(REFLECT_MARGIN, half its incidence cosine)``, a refracted ray leaves below
it. The geometric normal itself always makes a sound event, so the tilt is found by
bisection on [0, 1] (the smallest sound tilt, to TILT_STEPS halvings) and is continuous
where the shading normal turns unsound. On NURBS patches both normals are one and nothing
changes.
"""

from __future__ import annotations

import numpy as np

# A reflected ray leaves the triangle's plane at a cosine of at least this (or half the
# incoming ray's, at grazing incidence): clear of the surface it leaves.
REFLECT_MARGIN = 1e-2
# Halvings of the tilt interval: the tilt is found to 2^-TILT_STEPS of the angle between the
# shading and the geometric normal.
TILT_STEPS = 16


def oriented(d, normal, geo):
    """(shading, geometric, back) for rays ``d`` (N, 3) meeting surfaces with unit shading
    ``normal`` and geometric ``geo`` normals (N, 3) as oriented: both normals flipped so the
    geometric one faces the ray, and whether the ray meets the back of the surface (the side
    its geometric normal points away from). A shading normal on the other side of the surface
    than the geometric one (a corrupt custom normal) is replaced by the geometric one."""
    back = np.einsum("ij,ij->i", d, geo) > 0.0
    sign = np.where(back, -1.0, 1.0)[:, None]
    ns, ng = normal * sign, geo * sign
    ns = np.where((np.einsum("ij,ij->i", ns, ng) > 0.0)[:, None], ns, ng)
    return ns, ng, back


def reflect(d, n):
    """Mirror directions d about unit normals n (either orientation)."""
    return d - 2.0 * np.einsum("ij,ij->i", d, n)[:, None] * n


def refract(d, n, eta):
    """Snell refraction of unit d through unit n facing against d, eta = n_from / n_to.
    Returns (directions, tir) where tir marks total internal reflection (direction reflected)."""
    cos_i = -np.einsum("ij,ij->i", d, n)
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    tir = k < 0.0
    cos_t = np.sqrt(np.maximum(k, 0.0))
    t = eta[:, None] * d + (eta * cos_i - cos_t)[:, None] * n
    out = np.where(tir[:, None], reflect(d, n), t)
    return out / np.linalg.norm(out, axis=1)[:, None], tir


def event_normal(d, ns, ng, eta=None):
    """The unit normal (N, 3) rays ``d`` reflect (``eta`` None) or refract (``eta`` (N,) =
    n_from / n_to) about, from ``oriented`` shading ``ns`` and geometric ``ng`` normals: ``ns``
    where its event is sound, else tilted toward ``ng`` (module docstring)."""
    smooth = np.flatnonzero(np.any(ns != ng, axis=1))      # NURBS and flat: sound
    e_s = None if eta is None else np.asarray(eta, np.float64)[smooth]
    bad = smooth[~_sound(d[smooth], ns[smooth], ng[smooth], e_s)]
    if len(bad) == 0:
        return ns
    db, sb, gb = d[bad], ns[bad], ng[bad]
    eb = None if eta is None else np.asarray(eta, np.float64)[bad]
    lo, hi = np.zeros(len(bad)), np.ones(len(bad))
    for _ in range(TILT_STEPS):
        mid = 0.5 * (lo + hi)
        ok = _sound(db, _tilt(sb, gb, mid), gb, eb)
        hi = np.where(ok, mid, hi)
        lo = np.where(ok, lo, mid)
    out = ns.copy()
    out[bad] = np.where((hi >= 1.0)[:, None], gb, _tilt(sb, gb, hi))
    return out


def _tilt(ns, ng, a):
    """Unit normals a of the way (0..1, by angle) from ``ns`` to ``ng`` along their great
    circle (the two are less than 90 degrees apart)."""
    ang = np.arccos(np.clip(np.einsum("ij,ij->i", ns, ng), -1.0, 1.0))
    s = np.sin(ang)
    safe = s > 1e-12
    w0 = np.where(safe, np.sin((1.0 - a) * ang) / np.where(safe, s, 1.0), 1.0 - a)
    w1 = np.where(safe, np.sin(a * ang) / np.where(safe, s, 1.0), a)
    n = w0[:, None] * ns + w1[:, None] * ng
    return n / np.linalg.norm(n, axis=1)[:, None]


def _sound(d, n, ng, eta):
    """(N,) whether reflecting (``eta`` None) or refracting rays ``d`` about ``n`` is a sound
    event on a surface of geometric normal ``ng`` facing the rays."""
    cos_i = -np.einsum("ij,ij->i", d, n)
    margin = np.minimum(REFLECT_MARGIN, -0.5 * np.einsum("ij,ij->i", d, ng))
    if eta is None:
        return (cos_i > 0.0) & (np.einsum("ij,ij->i", reflect(d, n), ng) >= margin)
    out, tir = refract(d, n, eta)
    side = np.einsum("ij,ij->i", out, ng)
    return (cos_i > 0.0) & np.where(tir, side >= margin, side < 0.0)
