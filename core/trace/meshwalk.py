"""The hit of a ray on a mesh near a known triangle, by walking across the mesh's edges.

Solving a ray along a sample's path on a mesh patch (ritree.query.paths) knows the triangle
the sample's ray met at that event; the query ray, a little apart, meets the same smooth
surface a few triangles away. From the known triangle, each step intersects the ray with the
triangle's plane (Moller-Trumbore's barycentrics, as the tracer's) and, where the crossing lies
outside the triangle, steps across the edge facing the most negative barycentric to the
neighbour sharing it, until the crossing lies inside (the hit) or a step leaves the mesh (an
open edge, or an edge of more than two triangles), the ray runs parallel to a plane, or
WALK_STEPS steps pass. Each step is a few dozen flops for every ray at once: no BVH, no search
of the whole mesh. Like Newton on a NURBS patch it finds *a* crossing of the surface near the
seed; whether it is the ray's nearest the caller decides (the occlusion proxy).
"""

from __future__ import annotations

import numpy as np

from .hits import PatchHit
from .meshes import MeshSet, RayHits
from .planar import BARY_EPS

# Most edges a walk crosses: the query ray's hit lies a few triangles from its sample's.
WALK_STEPS = 24


def edge_neighbours(faces: np.ndarray) -> np.ndarray:
    """(T, 3) int64: for each triangle of ``faces`` (T, 3) vertex ids and each corner k, the
    triangle across the edge opposite corner k; -1 where no other triangle or more than one
    shares that edge."""
    t = len(faces)
    a = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    b = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])
    key = np.minimum(a, b) * (int(faces.max(initial=0)) + 1) + np.maximum(a, b)
    slot = np.arange(3 * t)                      # slot s: triangle s % t, corner s // t
    order = np.argsort(key, kind="stable")
    k = key[order]
    start = np.r_[True, k[1:] != k[:-1]]
    run = np.cumsum(start) - 1
    size = np.bincount(run)
    pair = np.flatnonzero(size[run] == 2)        # sorted slots of edges shared by exactly two
    first, second = order[pair[::2]], order[pair[1::2]]
    out = np.full(3 * t, -1, np.int64)
    out[first], out[second] = second % t, first % t
    return out.reshape(3, t).T.copy()


def walk(mesh: MeshSet, neighbours: np.ndarray, o, d, tri, tmin, tmax) -> RayHits:
    """Hits of rays ``o``, ``d`` (N, 3; unit d) walked from triangles ``tri`` (N,) of
    ``mesh`` across ``neighbours`` (``edge_neighbours`` of its faces): t in (tmin, tmax)
    (N,) where found, else a miss (module docstring)."""
    n = len(o)
    out = RayHits(np.full(n, np.inf), np.full(n, -1, np.int64), np.zeros(n), np.zeros(n))
    cols = lambda x: (x[:, 0], x[:, 1], x[:, 2])
    live, cur = np.arange(n), np.asarray(tri, np.int64).copy()
    for _ in range(WALK_STEPS):
        if len(live) == 0:
            break
        ok, t, b1, b2 = mesh._solve(cols(o[live]), cols(d[live]), None, cur)
        bary = np.stack([1.0 - b1 - b2, b1, b2], axis=1)
        worst = np.argmin(bary, axis=1)
        inside = ok & (bary[np.arange(len(live)), worst] >= -BARY_EPS)
        good = inside & (t > tmin[live]) & (t < tmax[live])
        g = live[good]
        out.t[g], out.tri[g], out.b1[g], out.b2[g] = t[good], cur[good], b1[good], b2[good]
        nxt = neighbours[cur, worst]
        step = ok & ~inside & (nxt >= 0)
        live, cur = live[step], nxt[step]
    return out


def mesh_hits(tracer, o, d, tri, tmin, tmax) -> PatchHit:
    """``walk`` on a PatchTracer's mesh patches from triangles ``tri`` (N,; indices into
    ``tracer.meshes``), as the tracer records hits: patch, point, shading and geometric
    normals as the surface is oriented, barycentric (u, v), the triangle."""
    ms = tracer.meshes
    rh = walk(ms, tracer.mesh_neighbours, np.asarray(o, np.float64),
              np.asarray(d, np.float64), tri, tmin, tmax)
    mh = ms.record(rh)
    res = PatchHit.misses(len(rh.t))
    k = np.flatnonzero(mh.hit)
    res.hit[k], res.t[k], res.tri[k] = True, mh.t[k], mh.tri[k]
    res.point[k], res.normal[k], res.geo_normal[k] = mh.point[k], mh.normal[k], mh.geo_normal[k]
    res.u[k], res.v[k] = mh.b1[k], mh.b2[k]
    res.patch[k] = tracer.mesh_patch[mh.mesh[k]]
    res.cls[k] = tracer.class_of[res.patch[k]]
    return res
