"""Solving a ray along a sample's path where the path crosses a mesh patch: the event's hit is
walked from the triangle the sample met there (trace.meshwalk), the mesh's counterpart of
Newton on a NURBS patch from the sample's parameters (trace.polish)."""

from __future__ import annotations

import numpy as np

from ...trace.meshwalk import mesh_hits
from ...trace.objectfn import params_tri
from ...trace.polish import Seeds, keep_near


def mesh_event_hits(tracer, patch, recorded, o, d, tmin, tmax, max_move, min_cos,
                    hit) -> None:
    """Where the event of rays ``o``, ``d`` (N, 3) lies on a mesh patch ``patch`` (N,), write
    into ``hit`` (PatchHit, in place) the hit walked from the triangle its sample's recorded
    parameters ``recorded`` (N, 2) name, kept (as polish keeps a Newton root) within
    ``max_move`` (N,) of that triangle's centroid and with a normal within ``min_cos`` of its
    own, t in (tmin, tmax) (N,); a triangle that is not the patch's (a tree recorded otherwise)
    starts no walk."""
    m = np.flatnonzero((patch >= 0) & tracer.is_mesh[np.maximum(patch, 0)])
    if len(m) == 0:
        return
    ms = tracer.meshes
    tri = params_tri(recorded[m])
    ok = tri < len(ms.faces)
    ok[ok] = tracer.mesh_patch[ms.tri_mesh[tri[ok]]] == patch[m[ok]]
    m, tri = m[ok], tri[ok]
    got = mesh_hits(tracer, o[m], d[m], tri, tmin[m], tmax[m])
    centre = ms.vertices[ms.faces[tri]].mean(axis=1)
    geo = ms.geo_normal[tri]
    facing = np.where((np.einsum("ij,ij->i", geo, d[m]) > 0)[:, None], -geo, geo)
    keep_near(got, d[m], Seeds(patch[m], recorded[m], centre, facing), max_move[m], min_cos)
    got.t[~got.hit] = np.inf
    got.patch[~got.hit] = -1
    hit.put(m, got)
