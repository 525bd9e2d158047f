"""The numpy floor of the environment pass: CPU seconds of the least vectorized arithmetic that
does the pass's work for a set of rays whose answers are already known, with no search.

Per ray: one ray-triangle test against the triangle it hits (plane crossing and barycentric
coordinates, the triangle's coefficients gathered per ray), one shading evaluation (surface
point, normal turned to the ray, each material's colour as the renderer evaluates it, every
light's irradiance and the final combination) and, per light with shadows, one ray-triangle
test of the shadow segment (against the same triangle: a search that found its one candidate
at once). Rays that miss see the world. The environment pass's CPU per ray over this floor is
what its searches (packets, grids, hierarchies) and bookkeeping cost.
"""

from __future__ import annotations

import time

import numpy as np

from ..trace.shading import Environment
from ..trace.textures import eval_texture, eval_world

CHUNK = 8192            # rays at once, as the environment pass takes them


def _plane_test(nrm, c, a, b, o, d):
    """(point, u, v, inside) where rays o + t d (columns (3, k)) cross planes nrm.x = c, with
    barycentrics u = a.x - a0, v = b.x - b0 (a, b: (4, k), xyz and constant)."""
    t = (c - (nrm[0] * o[0] + nrm[1] * o[1] + nrm[2] * o[2])) / \
        (nrm[0] * d[0] + nrm[1] * d[1] + nrm[2] * d[2])
    p = o + t * d
    u = a[0] * p[0] + a[1] * p[1] + a[2] * p[2] - a[3]
    v = b[0] * p[0] + b[1] * p[1] + b[2] * p[2] - b[3]
    return p, u, v, (t >= 0) & (u >= 0) & (v >= 0) & (u + v <= 1)


def _coefficients(env: Environment):
    """Per triangle (columns): unit normal, plane constant, barycentric rows (xyz, constant)."""
    ms = env.meshes
    v0 = ms.vertices[ms.faces[:, 0]]
    e1 = ms.vertices[ms.faces[:, 1]] - v0
    e2 = ms.vertices[ms.faces[:, 2]] - v0
    g11, g12, g22 = (np.einsum("ij,ij->i", x, y) for x, y in ((e1, e1), (e1, e2), (e2, e2)))
    det = (g11 * g22 - g12 * g12)[:, None]
    a = (g22[:, None] * e1 - g12[:, None] * e2) / det
    b = (g11[:, None] * e2 - g12[:, None] * e1) / det
    row = lambda w: np.concatenate([w.T, np.einsum("ij,ij->i", w, v0)[None]])
    return (np.ascontiguousarray(ms.geo_normal.T), np.einsum("ij,ij->i", ms.geo_normal, v0),
            row(a), row(b))


def floor_cpu_s(env: Environment, origins, dirs, tri) -> float:
    """CPU seconds (this process) of the floor's arithmetic for rays ``origins``, ``dirs``
    (n, 3) whose closest environment triangles are ``tri`` (n,; -1: a miss)."""
    nrm, c, a, b = _coefficients(env)
    mat = env._tri_material
    c0 = time.process_time()
    for s in range(0, len(origins), CHUNK):
        o, d = origins[s:s + CHUNK].T, dirs[s:s + CHUNK].T
        k = tri[s:s + CHUNK]
        hit = np.flatnonzero(k >= 0)
        out = np.empty((3, len(k)))
        out[:, k < 0] = eval_world(env.world, d[:, k < 0].T).T
        p_tri, o, d = k[hit], o[:, hit], d[:, hit]
        g, cp = nrm.take(p_tri, axis=1), c[p_tri]
        ap, bp = a.take(p_tri, axis=1), b.take(p_tri, axis=1)
        p, u, v, _ = _plane_test(g, cp, ap, bp, o, d)
        g = g * np.where(g[0] * d[0] + g[1] * d[1] + g[2] * d[2] > 0, -1.0, 1.0)
        albedo = np.empty((3, len(hit)))
        group = mat[p_tri]
        for m in np.unique(group):
            sel = np.flatnonzero(group == m)
            tex = env._materials[m].color
            albedo[:, sel] = (np.asarray(tex.color, dtype=np.float64)[:, None]
                              if tex.kind == "constant" else eval_texture(
                                  tex, p[:, sel].T,
                                  env.meshes.uv_at(p_tri[sel], u[sel], v[sel]).T).T)
        irr = np.zeros((3, len(hit)))
        for light in env.lights:
            if light.kind == "point":
                to = np.asarray(light.position, dtype=np.float64)[:, None] - p
                r2 = to[0] * to[0] + to[1] * to[1] + to[2] * to[2]
                l, scale = to / np.sqrt(r2), light.power / (4.0 * np.pi * r2)
            else:
                w = -np.asarray(light.direction, dtype=np.float64)
                l, scale = np.broadcast_to((w / np.linalg.norm(w))[:, None], p.shape), \
                    light.strength
            cos = np.maximum(g[0] * l[0] + g[1] * l[1] + g[2] * l[2], 0.0)
            if light.shadows:
                _plane_test(g, cp, ap, bp, p + env.offset * g, l)
            irr += cos * scale * np.asarray(light.color, dtype=np.float64)[:, None]
        out[:, hit] = albedo * (env.world.ambient + irr) / np.pi
    return time.process_time() - c0
