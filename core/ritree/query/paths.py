"""Exact answers along a sample's path, for rays the tree would otherwise trace.

A ray that the baked-error tolerance refuses (or path identity, or too few usable samples)
usually takes the path of one of its samples: the same patches, in the same order, with the
same reflections, refractions and total internal reflections. The tree stores each hit
sample's path seeds (tree layout 6: the first hit's normalized patch parameters and those of
the next RECORDED_EVENTS events), so the ray is solved event by event along the path of its
nearest sample of its class (then of the nearest with another path, CANDIDATE_PATHS in all):
Newton on the patch the path visits from that sample's parameters there (``trace.polish``;
on a mesh patch a walk from the triangle the sample met there, ``meshpaths``), each event's
kind decided by the law at the solved point, as the tracer decides it (``surface_event``). The answer is kept only where

- every event converged near its seed (``CHAIN_MAX_MOVE_REL``, ``CHAIN_MOVE_PER_OFFSET``,
  ``CHAIN_MAX_TURN_DEG``),
- the ray-tree hash of the solved chain equals the sample's: the same patches and event kinds
  (a total internal reflection gained or lost changes it), and the path no longer than the
  recorded events,
- no segment of the chain, from the ray's origin to its first hit and between consecutive hits,
  meets the object in between (the fine triangle proxy, ``trace.proxy``: the solver found *a*
  crossing of each patch, this says it is the nearest),
- and the last ray leaves the object (the proxy again; the exact tracer where that ray leaves
  near the tangent plane); a trapped sample's path is the ray's only with all max_events
  events solved, and the ray is then trapped too.

On a mirror, a ray still refused whose exact first hit the query found (the full search, e.g.
a hit on a patch none of its samples hit) is then answered by its one reflection there where
that reflection leaves the object (the proxy, and the exact tracer over the stretch next to the
hit that the proxy does not look at). The others are traced.

On a dielectric (``QueryOptions.fresnel_tree``), the rays the tree interpolated are solved
along their samples' paths too: the tree holds one output ray per ray, but at each crossing
after the first the glass also reflects (the Fresnel tree, trace.objectfn), which a solved
chain carries; where the chain is not solved the interpolated answer stays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...trace.eventnormal import event_normal, oriented
from ...trace.objectfn import (SECONDARY_T_MIN_REL, TREE_HASH_SEED, FresnelBranches,
                               fresnel_dielectric, one_reflection_hash, reflect, surface_event,
                               tree_hash_step)
from ...trace.patches import PatchHit
from ...trace.polish import Seeds, polish_hits
from ...trace.proxy import GRAZING_SINE
from ..answers import (COL, SOLVED, TRACED, WHY_PATH, WHY_TOLERANCE, WHY_UNSAMPLED, WHY_USABLE,
                       is_interpolated)
from .meshpaths import mesh_event_hits
from .sets import N_CORNERS, corner_weights

# Each event's Newton root is kept only within this distance of its seed's surface point
# (relative to the box diagonal), plus CHAIN_MOVE_PER_OFFSET times the distance between the
# ray's and the sample's viewpoints (the sample's hit is that much farther from the ray's), and
# with a normal within this angle of the seed's: the seed is the hit of a nearby sample on the
# same patch, after as many events as the query ray; farther roots are another crossing of the
# patch. Wider than the first hit's limits in fill.py: later events drift apart as the chain
# bends.
CHAIN_MAX_MOVE_REL = 5e-2
CHAIN_MOVE_PER_OFFSET = 4.0
CHAIN_MAX_TURN_DEG = 30.0
# Distinct sample paths tried per ray (the heaviest sample's first).
CANDIDATE_PATHS = 2
# Newton starts each event from the weighted blend of the parameters of the ray's samples on
# the candidate path, where they lie within this of each other (normalized units, each axis);
# farther apart they straddle a closed patch's seam (a blend lands far from both sides) or the
# path bends sharply between them, and the heaviest sample's parameters are the seed.
SEED_BLEND_SPREAD = 0.1
# Rays refused for these reasons are solved along a sample's path before they are traced:
# past the tolerance, samples on different paths, or too few usable samples of the class
# (null ones among them: a null sample's path is a candidate too).
SOLVABLE = (WHY_TOLERANCE, WHY_PATH, WHY_USABLE)


def solve_paths(q, b) -> None:
    """Answer (SOLVED) the rays refused for SOLVABLE reasons whose exact path is one of their
    samples' of their class: tried in turn along the paths of the heaviest such sample (bilinear
    weights at both levels) and of the heaviest one with another path, up to CANDIDATE_PATHS;
    on a mirror, then the rays still refused whose exact first hit the query found, along
    their own one-reflection path (``one_reflection``); on a dielectric, then the rays the
    tree interpolated, along their samples' paths (module docstring)."""
    _sample_paths(q, b, np.flatnonzero((b.ans == TRACED) & np.isin(b.why, SOLVABLE)))
    if q.material.kind == "mirror":
        with b.clock("paths"):
            one_reflection(q, b)
    elif q.material.kind == "dielectric" and q.opt.fresnel_tree:
        _sample_paths(q, b, np.flatnonzero(is_interpolated(b.ans)))


def _sample_paths(q, b, rays) -> None:
    """Query rays ``rays`` solved along their samples' paths (``solve_paths``); those not
    solved keep their answer."""
    if len(rays) == 0 or b.loc is None or b.loc_pc is None:
        return
    with b.clock("paths"):
        row = np.full(len(b.o), -1)
        row[b.loc.ray] = np.arange(len(b.loc))
        rays = rays[row[rays] >= 0]
        loc = b.loc.take(row[rays])
        pc = b.loc_pc[row[rays]]
        keep = pc >= 0
        rays, loc, pc = rays[keep], loc.take(keep), pc[keep]
        ids, w = sample_weights(q, loc, pc)
        entry = b.o[rays] + q.st.box_entry(b.o[rays], b.d[rays])[:, None] * b.d[rays]
        for _ in range(CANDIDATE_PATHS):
            best = np.argmax(w, axis=1)
            k = np.flatnonzero(w[np.arange(len(w)), best] >= 0)
            if len(k) == 0:
                break
            sid = ids[k, best[k]]
            vp = q.tree.vp_forest.corner[loc.vnode[k], best[k] // N_CORNERS]
            offset = np.linalg.norm(entry[k] - q.tree.vp_pos[vp], axis=1)
            chain(q, b, rays[k], sid, seed_uvs(q.table, ids[k], w[k], sid),
                  CHAIN_MAX_MOVE_REL * q.tree.diag + CHAIN_MOVE_PER_OFFSET * offset)
            # the next candidate: another path, for the rays not solved yet
            tried = np.full(len(w), -1, np.int64)
            tried[k] = q.table.tree[sid]
            w[q.table.tree[ids] == tried[:, None]] = -1.0
            w[b.ans[rays] == SOLVED] = -1.0


def one_reflection(q, b) -> None:
    """Answer (SOLVED) the mirror rays still refused (SOLVABLE reasons, or a first hit on a
    patch none of their samples hit: WHY_UNSAMPLED) whose exact first hit the query found (the
    full search: the nearest) and whose reflection there leaves the object (``_hits_again``):
    their path is that one reflection, whatever their samples' paths."""
    rays = np.flatnonzero((b.ans == TRACED) & np.isin(b.why, SOLVABLE + (WHY_UNSAMPLED,)))
    got = b.known.of(rays) if len(rays) else None
    if got is None:
        return
    k, first = got
    k, first = k[first.hit], first.take(np.flatnonzero(first.hit))
    rays = rays[k]
    d = b.d[rays]
    nrm = np.where((np.einsum("ij,ij->i", first.normal, d) > 0)[:, None], -first.normal,
                   first.normal)
    out = reflect(d, nrm)
    again = _hits_again(q, first.point, out, nrm)
    # The proxy does not look at the stretch next to the surface point (proxy.end_stretch),
    # where a patch meeting this one at a crease may be met: the exact tracer looks there (on a
    # sample's path the samples vouch for it). Grazing rays were traced all the way already.
    r = np.flatnonzero(~again & (np.abs(np.einsum("ij,ij->i", out, nrm)) >= GRAZING_SINE))
    floor = np.full(len(r), SECONDARY_T_MIN_REL * q.st.tracer.diag)
    again[r] = q.st.tracer.intersect(first.point[r], out[r], tmin=floor,
                                     tmax=q.proxy.end_stretch(out[r], nrm[r])).hit
    keep = np.flatnonzero(~again)
    n = len(keep)
    _answer(q, b, rays[keep], first.take(keep),
            Chains(oo=first.point[keep], od=out[keep], null=np.zeros(n, bool),
                   events=np.ones(n, np.int64),
                   tree=one_reflection_hash(first.patch[keep]),
                   fresnel=np.zeros(n), refl_dir=np.zeros((n, 3)), out_weight=np.ones(n),
                   branch_color=np.zeros((n, 3))))


def sample_weights(q, loc, pc):
    """(ids (n, 16), weights (n, 16)) of the located rays' ``loc`` samples: the bilinear weight
    of each at the viewpoint and direction levels, -1 where its class is not ``pc``."""
    ids, w = corner_weights(q.tree, loc)
    return ids, np.where(q.table.cls[ids] == pc[:, None], w, -1.0)


def seed_uvs(tab, ids, w, sid) -> np.ndarray:
    """(n, E, 2) normalized parameters to start each event of sample ``sid``'s path from, for
    rays whose samples are ``ids`` (n, 16) with weights ``w`` (-1: not of the ray's class):
    the weighted blend of those on that path (same ray-tree hash), per event where their
    parameters lie within SEED_BLEND_SPREAD of each other, else ``sid``'s own."""
    own = _path_uvs(tab, sid)                                               # (n, E, 2)
    uv = _path_uvs(tab, ids)                                                # (n, 16, E, 2)
    same = (tab.tree[ids] == tab.tree[sid][:, None]) & (w >= 0)
    ws = np.where(same, w, 0.0)
    total = ws.sum(axis=1)
    blend = np.einsum("nk,nkec->nec", ws / np.where(total > 0, total, 1.0)[:, None], uv)
    on = same[:, :, None, None]
    spread = np.where(on, uv, -np.inf).max(axis=1) - np.where(on, uv, np.inf).min(axis=1)
    far = np.any(spread > SEED_BLEND_SPREAD, axis=2) | (total <= 0)[:, None]
    return np.where(far[..., None], own, blend)


def _path_uvs(tab, sid) -> np.ndarray:
    """(..., E, 2) the normalized parameters of samples ``sid``'s first hit and later events."""
    return np.concatenate([tab.vals[sid][..., None, COL.UV], tab.ev_uv[sid]], axis=-2)


def chain(q, b, rays, sid, uvs, max_move) -> None:
    """Solve query rays ``rays`` along the paths of samples ``sid`` from the events' seed
    parameters ``uvs`` (n, E, 2) and answer those kept; ``max_move`` (n,): how far from its
    seed an event's root may lie (scene units)."""
    tab, tracer, mat = q.table, q.st.tracer, q.material
    patches = np.concatenate([tab.patch[sid, None].astype(np.int64),
                              tab.ev_patch[sid].astype(np.int64)], axis=1)     # (n, E)
    own = _path_uvs(tab, sid)            # on a mesh patch: the sample's triangle
    n_ev = np.sum(patches >= 0, axis=1)
    n = len(rays)
    alive = np.ones(n, bool)
    h = np.full(n, TREE_HASH_SEED, np.uint64)
    cur_o, cur_d = b.o[rays].copy(), b.d[rays].copy()
    inside = np.zeros(n, bool)
    first = PatchHit.misses(n)
    floor = np.full(n, SECONDARY_T_MIN_REL * tracer.diag)
    min_cos = np.cos(np.radians(CHAIN_MAX_TURN_DEG))
    fresnel, refl_dir = np.zeros(n), np.zeros((n, 3))
    out_weight, branches = np.ones(n), FresnelBranches()    # a dielectric's Fresnel tree
    split = mat.kind == "dielectric" and q.opt.fresnel_tree
    n_max = patches.shape[1]
    pts, nrms, dirs = (np.zeros((n, n_max, 3)) for _ in range(3))
    for e in range(n_max):
        act = np.flatnonzero(alive & (e < n_ev))
        if len(act) == 0:
            break
        seeds = Seeds(patches[act, e], uvs[act, e].astype(np.float64), None, None)
        tmax = b.tmax[rays[act]] if e == 0 else np.full(len(act), np.inf)
        hit = polish_hits(tracer, cur_o[act], cur_d[act], seeds, max_move[act], min_cos,
                          floor[act], tmax)
        mesh_event_hits(tracer, patches[act, e], own[act, e].astype(np.float64), cur_o[act],
                        cur_d[act], floor[act], tmax, max_move[act], min_cos, hit)
        if e == 0:
            _known_first_hits(b, rays[act], patches[act, 0], hit)
        ok = hit.hit
        alive[act[~ok]] = False
        act, hit = act[ok], hit.take(np.flatnonzero(ok))
        if e == 0:
            first.put(act, hit)
        d_in = cur_d[act]
        nrm, geo, back = oriented(d_in, hit.normal, hit.geo_normal)
        ev = surface_event(tracer, mat, d_in, nrm, geo, back, hit.patch, inside[act])
        new_d = ev.out_dir
        if e == 0 and mat.kind == "dielectric":
            fresnel[act] = fresnel_dielectric(-np.einsum("ij,ij->i", d_in, nrm), ev.eta)
            refl_dir[act] = reflect(d_in, event_normal(d_in, nrm, geo))
        if e > 0 and split:
            branches.split(act, hit.point, d_in, nrm, geo, ev.n_t, ev.eta, ev.tir, ev.inside,
                           e + 1, out_weight)
        inside[act] = ev.inside_after
        h[act] = tree_hash_step(h[act], hit.patch, ev.kind)
        cur_o[act], cur_d[act] = hit.point, new_d
        pts[act, e], nrms[act, e], dirs[act, e] = hit.point, geo, new_d
    good = np.flatnonzero(alive & (h.astype(np.uint32) == tab.tree[sid]))
    searched = b.known.pos[rays[good]] >= 0     # first hit from the full search: the nearest
    good = good[~_crossed(q, b.o[rays[good]], b.d[rays[good]], pts[good], nrms[good],
                          dirs[good], n_ev[good], searched)]
    # a trapped path is the ray's where all its max_events events are; any other must leave
    null = tab.null[sid[good]]
    good = good[~null | (n_ev[good] == q.st.scene.render.max_events)]
    null = tab.null[sid[good]]
    out = good[~null]
    if len(out):
        last = nrms[out, n_ev[out] - 1]
        good = np.concatenate([good[null], out[~_hits_again(q, cur_o[out], cur_d[out], last)]])
    null = tab.null[sid[good]]
    cur_d[good[null]] = 0.0
    kept = np.zeros(n, bool)
    kept[good] = True
    color = branches.trace(tracer, mat, q.st.env.shade_rays, n, q.st.scene.render.max_events,
                           kept)
    _answer(q, b, rays[good], first.take(good),
            Chains(oo=cur_o[good], od=cur_d[good], null=null, events=n_ev[good],
                   tree=h[good].astype(np.uint32), fresnel=fresnel[good],
                   refl_dir=refl_dir[good], out_weight=out_weight[good],
                   branch_color=color[good]))


def _hits_again(q, o, d, n) -> np.ndarray:
    """(n,) bool: whether the rays leaving surface points ``o`` along ``d`` (normals ``n``)
    meet the object again: the proxy decides, except for rays leaving within GRAZING_SINE of
    the tangent plane (the proxy's untested stretch would be long), which the exact tracer
    decides."""
    sine = np.abs(np.einsum("ij,ij->i", d, n))
    grazing = sine < GRAZING_SINE
    again = np.zeros(len(o), bool)
    g = np.flatnonzero(grazing)
    if len(g):
        floor = np.full(len(g), SECONDARY_T_MIN_REL * q.st.tracer.diag)
        again[g] = q.st.tracer.intersect(o[g], d[g], tmin=floor).hit
    r = np.flatnonzero(~grazing)
    if len(r):
        again[r] = q.proxy.crossed(o[r], d[r], np.full(len(r), np.inf), n[r])
    return again


def _crossed(q, o, d, pts, nrms, dirs, n_ev, searched) -> np.ndarray:
    """(n,) bool: whether the proxy (trace.proxy) finds the object between the ray's origin
    ``o`` (direction ``d``) and its first solved hit, or between two consecutive solved hits
    (``pts``, ``nrms``: (n, E, 3) points and normals facing the incoming ray, ``dirs`` the
    directions leaving them; ``n_ev`` events each); the first stretch is not looked at where
    ``searched`` (n,): that first hit is the full search's, the nearest."""
    bad = np.zeros(len(o), bool)
    if len(o) == 0:
        return bad
    k = np.flatnonzero(~searched)
    first = np.linalg.norm(pts[k, 0] - o[k], axis=1)
    bad[k] = q.proxy.crossed(o[k], d[k], first, d[k], nrms[k, 0])
    for e in range(pts.shape[1] - 1):
        k = np.flatnonzero(~bad & (n_ev > e + 1))
        if len(k) == 0:
            break
        seg = pts[k, e + 1] - pts[k, e]
        bad[k] = q.proxy.crossed(pts[k, e], dirs[k, e], np.linalg.norm(seg, axis=1),
                                 nrms[k, e], nrms[k, e + 1])
    return bad


def _known_first_hits(b, rows, patch, hit: PatchHit) -> None:
    """Where the query found the exact first hit of rays ``rows`` already, it replaces
    Newton's: kept if on the path's first patch ``patch``, else none."""
    got = b.known.of(rows)
    if got is not None:
        k, kh = got
        hit.hit[k] = False
        same = np.flatnonzero(kh.hit & (kh.patch == patch[k]))
        hit.put(k[same], kh.take(same))


@dataclass
class Chains:
    """What the solved chains of n rays leave: output origin and direction (n, 3; a trapped
    ray's origin its last hit, its direction zero, as the tracer answers it), trapped or not,
    events, ray-tree hash, a dielectric's Fresnel weight and reflected direction, and its
    Fresnel tree's share on the output ray and other branches' colour (ObjectRays)."""

    oo: np.ndarray
    od: np.ndarray
    null: np.ndarray
    events: np.ndarray
    tree: np.ndarray
    fresnel: np.ndarray
    refl_dir: np.ndarray
    out_weight: np.ndarray
    branch_color: np.ndarray


def _answer(q, b, rows, first: PatchHit, ch: Chains) -> None:
    """Write the solved answers of query rays ``rows`` (SOLVED): their exact first hits
    ``first`` and chains ``ch``."""
    d = b.d[rows]
    nrm = np.where((np.einsum("ij,ij->i", first.normal, d) > 0)[:, None], -first.normal,
                   first.normal)
    res = b.res
    res.hit[rows], res.null[rows] = True, ch.null
    res.out_origin[rows], res.out_dir[rows] = ch.oo, ch.od
    res.t_first[rows], res.point[rows], res.normal[rows] = first.t, first.point, nrm
    res.patch[rows], res.cls[rows] = first.patch, q.st.tracer.class_of[first.patch]
    res.events[rows], res.tree[rows] = ch.events, ch.tree
    res.fresnel[rows], res.refl_dir[rows] = ch.fresnel, ch.refl_dir
    res.out_weight[rows], res.branch_color[rows] = ch.out_weight, ch.branch_color
    res.uv[rows] = q.st.tracer.normalized_uv(first.patch, first.u, first.v)
    b.ans[rows] = SOLVED
    b.why[rows] = 0
    b.solved += len(rows)
