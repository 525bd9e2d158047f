"""The exact hit of a ray on a known NURBS patch, by Newton's method from a nearby seed.

The RI-Tree query knows, for a mirror ray whose interpolating samples all reflect once off one
patch, that patch and an interpolated parameter (u, v) close to the ray's hit on it. Newton's
method on the Bezier piece holding the seed (the tracer's two-plane form,
``PatchTracer.solve_newton``, with the pieces' second-derivative bounds: a run ends on the step
proven to land within tolerance) converges to that hit in about two iterations from the
interpolated seed: a small part of what the full search costs (BVH walk, candidate pairs,
seeds, fallback splits). It does not tell whether the ray meets something else first; that
the caller takes from the samples.

Units: t and distances in scene units; (u, v) normalized to the patch's domain [0, 1]^2.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..geometry import bezier as bz
from ..geometry.nurbs import normals as nurbs_normals
from .patches import DEGENERATE_REL, PARAM_MARGIN, PatchHit, PatchTracer, project_nets

# A root that converged outside its Bezier piece (the seed lay in a neighbouring piece) is
# looked for again from that root, in the piece that holds it: this many runs in all.
POLISH_RUNS = 2


@dataclass
class Seeds:
    """What the caller knows of each ray's hit: its patch (N,), normalized parameters (N, 2),
    an estimate of the hit point (N, 3) and of the unit normal facing the ray (N, 3) (both
    None: the surface's at the parameters); and optionally second parameters (N, 2) to start
    from where the first find no hit (a blend of parameters across a closed patch's seam lands
    far from both sides)."""

    patch: np.ndarray
    uvn: np.ndarray
    point: np.ndarray | None
    normal: np.ndarray | None
    alt_uvn: np.ndarray | None = None


def polish_hits(tracer: PatchTracer, o, d, seeds: Seeds, max_move: float, min_cos: float,
                tmin, tmax) -> PatchHit:
    """``_polish`` from the seeds' parameters, then from their second parameters for the rays
    still without a hit. Seeds without a point and normal take the surface's at the
    parameters each run starts from (as ``surface_at``, the normal turned to face the ray),
    from the piece lookup that starts Newton."""
    res = _polish(tracer, o, d, seeds, max_move, min_cos, tmin, tmax)
    if seeds.alt_uvn is not None:
        r = np.flatnonzero(~res.hit)
        if len(r):
            alt = Seeds(seeds.patch[r], seeds.alt_uvn[r],
                        *(None if x is None else x[r] for x in (seeds.point, seeds.normal)))
            move = np.broadcast_to(np.asarray(max_move, np.float64), res.hit.shape)[r]
            res.put(r, _polish(tracer, np.asarray(o)[r], np.asarray(d)[r], alt, move,
                               min_cos, tmin[r], tmax[r]))
    return res


def _polish(tracer: PatchTracer, o, d, seeds: Seeds, max_move: float, min_cos: float,
            tmin, tmax) -> PatchHit:
    """Hits of rays ``o``, ``d`` (N, 3; unit d) on their seeds' patches by Newton from the
    seeds' parameters. A hit is kept (``hit`` True) where Newton converged inside the patch at
    a distance t in (tmin, tmax) (N,), within ``max_move`` (scene units; one for all rays or
    (N,)) of the seed's point,
    and with its normal facing the ray at a cosine >= ``min_cos`` to the seed's normal (a
    grazing ray's second root, where it leaves the surface, faces the other way). Rays on
    mesh patches get no hit. ``normal``: the unit normal as the surface is oriented;
    (u, v): NURBS parameters."""
    o, d = np.asarray(o, np.float64), np.asarray(d, np.float64)
    n = len(o)
    res = PatchHit.misses(n)
    patch = np.asarray(seeds.patch, np.int64)
    live = np.flatnonzero(_on_nurbs(tracer, patch))
    u, v = _nurbs_uv(tracer, patch[live], np.asarray(seeds.uvn, np.float64)[live])
    k, s, t = _piece_of(tracer, patch[live], u, v)
    if seeds.point is None:
        P, nrm = np.zeros((n, 3)), np.zeros((n, 3))
        P[live], nrm[live] = _surface(tracer, k, s, t, u, v)
        nrm = np.where((np.einsum("ij,ij->i", nrm, d) > 0)[:, None], -nrm, nrm)
        seeds = replace(seeds, point=P, normal=nrm)
    for run in range(POLISH_RUNS):
        if len(live) == 0:
            break
        if run:
            k, s, t = _piece_of(tracer, patch[live], u, v)
        ok = _newton(tracer, o[live], d[live], k, s, t)
        inside = (s >= -PARAM_MARGIN) & (s <= 1 + PARAM_MARGIN) & (t >= -PARAM_MARGIN) \
            & (t <= 1 + PARAM_MARGIN)
        rect = np.take(tracer.piece_rect, k, axis=0)
        u = rect[:, 0] + s * (rect[:, 1] - rect[:, 0])
        v = rect[:, 2] + t * (rect[:, 3] - rect[:, 2])
        g = np.flatnonzero(ok & inside)
        _record(tracer, o, d, live[g], k[g], s[g], t[g], u[g], v[g], res)
        # a root outside its piece: once more from it, where it lies in the patch's domain
        # (across the seam of a closed patch: parameters wrapped around)
        dom = np.take(tracer.uv_domain, patch[live], axis=0)
        closed = np.take(tracer.closed, patch[live], axis=0)
        u = np.where(closed[:, 0], dom[:, 0] + np.mod(u - dom[:, 0], dom[:, 1] - dom[:, 0]), u)
        v = np.where(closed[:, 1], dom[:, 2] + np.mod(v - dom[:, 2], dom[:, 3] - dom[:, 2]), v)
        again = np.flatnonzero(ok & ~inside & (u >= dom[:, 0]) & (u <= dom[:, 1])
                               & (v >= dom[:, 2]) & (v <= dom[:, 3]))
        live, u, v = live[again], u[again], v[again]
    k = np.flatnonzero(res.hit)
    res.hit[k[(res.t[k] <= tmin[k]) | (res.t[k] >= tmax[k])]] = False
    keep_near(res, d, seeds, max_move, min_cos)
    res.t[~res.hit] = np.inf
    res.patch[~res.hit] = -1
    res.cls[res.hit] = tracer.class_of[res.patch[res.hit]]
    return res


def keep_near(h: PatchHit, d, seeds: Seeds, max_move: float, min_cos: float) -> None:
    """Drop (in place: ``hit`` False) the hits of ``h`` farther than ``max_move`` from the
    seeds' points or whose normal, turned to face the rays ``d``, makes a cosine below
    ``min_cos`` with the seeds' normals."""
    k = np.flatnonzero(h.hit)
    nk = h.normal[k]
    facing = np.einsum("ij,ij->i", np.where((np.einsum("ij,ij->i", nk, d[k]) > 0)[:, None],
                                            -nk, nk), seeds.normal[k])
    move = np.broadcast_to(np.asarray(max_move, np.float64), h.hit.shape)[k]
    far = (facing < min_cos) | (np.linalg.norm(h.point[k] - seeds.point[k], axis=1) > move)
    h.hit[k[far]] = False


def _piece_of(tracer, patch, u, v):
    """(global piece index, local s, local t) of NURBS parameters (u, v) (N,) on NURBS patches
    ``patch`` (N,), as ``bezier.nurbs_to_piece_param`` finds them on each patch's pieces: the
    last piece starting at or below the parameter in u and in v (the first where none does),
    (s, t) clamped to [0, 1]. One branch-free binary search of every ray's own patch's
    breakpoints (``PatchTracer.piece_breaks``) in u and v at once."""
    x = np.stack([u, v], axis=1)
    start = np.take(tracer.piece_break_start, patch, axis=0)
    count = np.take(tracer.piece_break_count, patch, axis=0)
    # how many of the ray's breakpoints are <= x, found in steps of descending powers of two
    below = np.zeros_like(count)
    n_max = int(count.max(initial=0))
    for p in range(n_max.bit_length() - 1, -1, -1):
        step = below + (1 << p)
        le = np.take(tracer.piece_breaks, start + np.minimum(step, count) - 1) <= x
        below += (le & (step <= count)) * np.int64(1 << p)
    i = below - (below > 0)
    k = np.take(tracer.piece_base, patch) + i[:, 0] * count[:, 1] + i[:, 1]
    rect = np.take(tracer.piece_rect, k, axis=0)
    s = np.clip((u - rect[:, 0]) / (rect[:, 1] - rect[:, 0]), 0.0, 1.0)
    t = np.clip((v - rect[:, 2]) / (rect[:, 3] - rect[:, 2]), 0.0, 1.0)
    return k, s, t


def _newton(tracer, o, d, k, s, t):
    """PatchTracer.solve_newton on pieces ``k`` (one batch per degree); (s, t) updated in place;
    returns the converged mask."""
    ok = np.zeros(len(k), bool)
    grp = tracer.piece_group[k]
    for g in np.unique(grp):
        m = np.flatnonzero(grp == g)
        loc = tracer.piece_local[k[m]]
        nets = tracer.piece_nets[g][loc]
        ss, tt = s[m], t[m]
        bound = np.take(tracer.piece_bounds[g], loc, axis=0)
        ok[m] = tracer.solve_newton(project_nets(nets, o[m], d[m]), nets.shape[1] - 1,
                                    nets.shape[2] - 1, ss, tt, bound)
        s[m], t[m] = ss, tt
    return ok


def _record(tracer, o, d, rows, k, s, t, u, v, res):
    """Write the roots (s, t) on pieces ``k`` of rays ``rows`` into ``res``."""
    P, nrm = _surface(tracer, k, s, t, u, v)
    res.hit[rows] = True
    res.t[rows] = np.einsum("ij,ij->i", P - o[rows], d[rows])
    res.point[rows] = P
    res.normal[rows] = nrm
    res.geo_normal[rows] = nrm
    res.patch[rows] = tracer.piece_patch[k]
    res.u[rows], res.v[rows] = u, v


def _surface(tracer, k, s, t, u, v):
    """(points (N, 3), unit normals (N, 3) as the surface is oriented) at local (s, t) of
    pieces ``k`` (clipped to the piece), which are NURBS parameters (u, v) of their patches;
    at poles and collapsed edges the limit normal."""
    P = np.empty((len(k), 3))
    nrm = np.empty((len(k), 3))
    grp = tracer.piece_group[k]
    for g in np.unique(grp):
        m = np.flatnonzero(grp == g)
        P[m], Ps, Pt = bz.bezier_eval(tracer.piece_nets[g], np.clip(s[m], 0.0, 1.0),
                                      np.clip(t[m], 0.0, 1.0), derivatives=1,
                                      index=tracer.piece_local[k[m]])
        n = np.cross(Ps, Pt)
        ln = np.linalg.norm(n, axis=1)
        deg = ln <= DEGENERATE_REL * (np.linalg.norm(Ps, axis=1)
                                      + np.linalg.norm(Pt, axis=1)) ** 2 + 1e-300
        nrm[m] = n / np.where(deg, 1.0, ln)[:, None]
        pid = tracer.piece_patch[k[m]]
        for p in np.unique(pid[deg]):            # poles, collapsed edges: the limit normal
            i = m[np.flatnonzero(deg & (pid == p))]
            nrm[i] = nurbs_normals(tracer.object.patches[int(p)].surface, u[i], v[i])
    return P, nrm


def surface_at(tracer: PatchTracer, patch, uvn):
    """The surface of NURBS patches ``patch`` (N,) at normalized parameters ``uvn`` (N, 2) in
    [0, 1]^2: (points (N, 3), unit normals (N, 3) as the surface is oriented, ok (N,)); ``ok``
    is False (and the values zero) on mesh patches."""
    patch = np.asarray(patch, np.int64)
    P, nrm = np.zeros((len(patch), 3)), np.zeros((len(patch), 3))
    ok = _on_nurbs(tracer, patch)
    live = np.flatnonzero(ok)
    if len(live):
        u, v = _nurbs_uv(tracer, patch[live], np.asarray(uvn, np.float64)[live])
        k, s, t = _piece_of(tracer, patch[live], u, v)
        P[live], nrm[live] = _surface(tracer, k, s, t, u, v)
    return P, nrm, ok


def _on_nurbs(tracer, patch) -> np.ndarray:
    """Whether each of ``patch`` (int64, -1: none) is a NURBS patch of ``tracer``."""
    return (patch >= 0) & (tracer.piece_base[np.maximum(patch, 0)] >= 0)


def _nurbs_uv(tracer, patch, uvn):
    """NURBS parameters (u, v) of normalized parameters ``uvn`` (N, 2) on NURBS ``patch``
    (the inverse of PatchTracer.normalized_uv)."""
    dom = np.take(tracer.uv_domain, patch, axis=0)
    return (dom[:, 0] + uvn[:, 0] * (dom[:, 1] - dom[:, 0]),
            dom[:, 2] + uvn[:, 1] * (dom[:, 3] - dom[:, 2]))
