"""Exact ray intersection with the specular object's patches, vectorized over ray batches.

Method (after Martin et al.'s practical NURBS ray tracing, adapted to numpy):
1. Build (``subpatches``): every NURBS patch is cut into rational Bezier pieces and subdivided
   into flat sub-patches with conservative boxes (``geometry.bezier``); one BVH over all
   sub-patches.
2. Query (``newton``, ``roots``): the BVH yields candidate (ray, sub-patch) pairs. Each pair
   is seeded from the ray's hit on the two triangles of the sub-patch's corners (sub-patch
   midpoint if the plane hit is far outside), then Newton iterates on (s, t) in the
   sub-patch's local coordinates with the ray written as the intersection of two planes (a
   2x2 system, well conditioned away from exact tangency). The net is projected onto the
   planes once per pair (``project_nets``: two scalar nets and the weights), which also serves
   the end-on hull test; each iteration then evaluates three scalar polynomials. Converged
   roots inside the sub-patch are hits; the nearest wins.
3. Fallback (``roots``): a pair whose Newton run found no root in its net, or a grazing root
   whose twin (the ray's other nearby crossing) the twin search did not find, is split into
   four children, retried from their midpoints (a few levels deep).
4. Pairs are processed nearest box first; once a ray has a hit, candidates whose boxes start
   beyond it are dropped (in small batches, where few far pairs exist, all pairs go at once).
Mesh patches (triangles) go through the triangle tracer and compete on t.

Units: t is the distance along unit directions, in scene units (metres).
"""

from __future__ import annotations

from functools import cached_property

import numpy as np

from ..scene.model import Mesh, SpecularObject
from .hits import PatchHit
from .meshes import MeshSet
from .meshwalk import edge_neighbours
from .newton import (MAX_STEP, NEWTON_BLOCK, NEWTON_ITERS, NEWTON_TOL_REL, hull_meets, project_nets,
                     ray_planes, newton, second_derivative_bounds)
from .proxy import Proxy
from .roots import DEGENERATE_REL, PARAM_MARGIN, RootSearch
from .subpatches import bezier_pieces, flat_subpatches

# the tracer, and what importers take from here of the modules it is built from
__all__ = ["DEGENERATE_REL", "MAX_STEP", "NEWTON_BLOCK", "NEWTON_ITERS", "NEWTON_TOL_REL",
           "PARAM_MARGIN", "T_MIN_REL", "PatchHit", "PatchTracer", "hull_meets", "project_nets",
           "ray_planes"]

# Self-intersection guard: hits closer than this (relative to the object diagonal) are ignored.
T_MIN_REL = 1e-9
# A batch with at most this many far candidates (a ray's third box or later) solves them with
# the near ones in one stage: a stage's fixed cost (a whole Newton-and-fallback pipeline; an
# intersect call cost ~7 ms beyond its pairs' work before the projected-net Newton) outweighs
# the Newton work saved.
STAGE_MIN_PAIRS = 4096
# Pairs solved per batch: bounds memory (a degree-5 pair gathers 36 x 4 float64 control values)
# and keeps a batch's arrays small (exact renders ran ~5 % faster than with 1 << 16).
PAIR_CHUNK = 1 << 14



class PatchTracer:
    """Exact nearest-hit queries against the specular object's patches."""

    def __init__(self, obj: SpecularObject):
        self.object = obj
        pts = [p.surface.points.reshape(-1, 3) if p.surface is not None else p.vertices
               for p in obj.patches]
        allp = np.concatenate(pts)
        self.lo = allp.min(axis=0)
        self.hi = allp.max(axis=0)
        self.diag = float(np.linalg.norm(self.hi - self.lo)) or 1.0
        self.class_of = np.array([p.class_id for p in obj.patches], dtype=np.int64)
        # each NURBS patch's Bezier pieces; every patch's parameter domain (u0, u1, v0, v1:
        # PatchHit (u, v) divided by it is the normalized parameter); whether it is closed in u / v
        self.pieces, self.uv_domain, self.closed = bezier_pieces(obj, self.diag)
        # BVH primitive k: sub-patch sub_local[k] of groups[sub_group[k]]
        self.groups, self.sub_group, self.sub_local, self.bvh = flat_subpatches(self.pieces,
                                                                                self.diag)
        self.n_subpatches = int(sum(len(g.patch) for g in self.groups))
        self._stack_pieces()
        self._build_meshes(obj)
        self.stats = {"pairs": 0, "newton_iters": 0, "fallback_pairs": 0}

    # ------------------------------------------------------------------ build
    def _stack_pieces(self):
        """All patches' Bezier pieces in one index space (``piece_base[patch]`` + the patch's
        own piece index): their parameter rectangles and patches, and their nets stacked per degree
        (``piece_nets[piece_group[k]][piece_local[k]]``) with their ``second_derivative_bounds``
        (``piece_bounds``, the same layout), for Newton runs on known pieces; and each patch's
        piece breakpoints for finding the piece of a parameter: patch p's distinct piece starts
        in u (column 0) and in v (column 1), ascending, are ``piece_breaks[piece_break_start[p,
        c]:][:piece_break_count[p, c]]`` (no breakpoints for a mesh patch)."""
        self.piece_base = np.full(len(self.object.patches), -1, np.int64)
        self.piece_break_start = np.zeros((len(self.object.patches), 2), np.int64)
        self.piece_break_count = np.zeros((len(self.object.patches), 2), np.int64)
        breaks = []
        rect, group, local, owner, nets, degrees = [], [], [], [], [], {}
        base = 0
        for pid, pcs in self.pieces.items():
            g = degrees.setdefault((pcs.degree_u, pcs.degree_v), len(degrees))
            if g == len(nets):
                nets.append([])
            start = sum(len(x) for x in nets[g])
            nets[g].append(pcs.ctrl)
            self.piece_base[pid] = base
            base += len(pcs.ctrl)
            rect.append(np.stack([pcs.u0, pcs.u1, pcs.v0, pcs.v1], axis=1))
            group.append(np.full(len(pcs.ctrl), g))
            local.append(start + np.arange(len(pcs.ctrl)))
            owner.append(np.full(len(pcs.ctrl), pid))
            for c, starts in enumerate((np.unique(pcs.u0), np.unique(pcs.v0))):
                self.piece_break_start[pid, c] = sum(len(x) for x in breaks)
                self.piece_break_count[pid, c] = len(starts)
                breaks.append(starts)
        self.piece_rect = np.concatenate(rect) if rect else np.zeros((0, 4))
        self.piece_group = np.concatenate(group) if group else np.zeros(0, np.int64)
        self.piece_local = np.concatenate(local) if local else np.zeros(0, np.int64)
        self.piece_patch = np.concatenate(owner) if owner else np.zeros(0, np.int64)
        self.piece_breaks = np.concatenate(breaks) if breaks else np.zeros(0)
        self.piece_nets = [np.concatenate(x) for x in nets]
        self.piece_bounds = [second_derivative_bounds(x) for x in self.piece_nets]

    def _build_meshes(self, obj):
        """The mesh patches as one MeshSet (smooth where they carry corner normals):
        ``mesh_patch[k]`` is the patch id of its mesh k, ``is_mesh[p]`` whether patch p is a
        mesh."""
        meshes, normals, ids = [], [], []
        for pid, patch in enumerate(obj.patches):
            if patch.surface is None:
                meshes.append(Mesh(name=patch.name, vertices=patch.vertices,
                                   triangles=patch.triangles, material=""))
                normals.append(patch.normals)
                ids.append(pid)
        self.mesh_patch = np.array(ids, dtype=np.int64)
        self.is_mesh = np.zeros(len(obj.patches), bool)
        self.is_mesh[self.mesh_patch] = True
        self.meshes = MeshSet(meshes, normals) if meshes else None

    @cached_property
    def occlusion_proxy(self):
        """The object's occlusion proxy (trace.proxy.Proxy), built on first use and kept: every
        query over this tracer shares it."""
        return Proxy.of(self)

    @cached_property
    def mesh_neighbours(self) -> np.ndarray:
        """(T, 3) the triangle across each edge of the mesh patches' triangles
        (``meshwalk.edge_neighbours``), built on first use: walks on the meshes start here."""
        return edge_neighbours(self.meshes.faces)

    def normalized_uv(self, patch, u, v) -> np.ndarray:
        """(N, 2) hit parameters (u, v) of patches ``patch`` (-1: a miss, 0 there) divided into
        [0, 1]^2 by each patch's domain."""
        dom = self.uv_domain[np.maximum(patch, 0)]
        out = np.stack([(u - dom[:, 0]) / np.maximum(dom[:, 1] - dom[:, 0], 1e-300),
                        (v - dom[:, 2]) / np.maximum(dom[:, 3] - dom[:, 2], 1e-300)], axis=1)
        out[patch < 0] = 0.0
        return out

    # ------------------------------------------------------------------ query
    def intersect(self, origins, dirs, tmin=None, tmax=None, patches=None) -> PatchHit:
        """Nearest hit with t in (max(tmin, T_MIN), tmax) for each ray.

        ``patches``: optional (N, K) int array of patch ids each ray may hit (-1 = unused slot),
        the RI-Tree's exact first hit against only the candidate patches; None = all patches.
        """
        n = len(origins)
        origins = np.asarray(origins, dtype=np.float64)
        dirs = np.asarray(dirs, dtype=np.float64)
        t_floor = T_MIN_REL * self.diag
        tmin = np.full(n, t_floor) if tmin is None else np.maximum(tmin, t_floor)
        tmax = np.full(n, np.inf) if tmax is None else np.asarray(tmax, dtype=np.float64)
        best_t = tmax.copy()
        res = PatchHit.misses(n)
        if n == 0:
            return res
        if self.meshes is not None:
            self._intersect_meshes(origins, dirs, tmin, best_t, res, patches)
        if self.bvh is not None:
            self._intersect_nurbs(origins, dirs, tmin, best_t, res, patches)
        res.hit = np.isfinite(res.t)
        res.cls[res.hit] = self.class_of[res.patch[res.hit]]
        return res

    def _intersect_meshes(self, o, d, tmin, best_t, res, patches):
        mh = self.meshes.closest_hit(o, d, tmin, best_t)
        pid = np.where(mh.hit, self.mesh_patch[np.maximum(mh.mesh, 0)], -1)
        # a candidate restriction drops disallowed mesh hits (an allowed mesh hidden behind a
        # disallowed one is not searched for: mesh patches are a minor case of the RI-Tree)
        ok = mh.hit & _allowed(pid, patches)
        res.t[ok] = mh.t[ok]
        best_t[ok] = mh.t[ok]
        res.point[ok] = mh.point[ok]
        res.normal[ok] = mh.normal[ok]
        res.geo_normal[ok] = mh.geo_normal[ok]
        res.tri[ok] = mh.tri[ok]
        res.patch[ok] = pid[ok]
        res.u[ok] = mh.b1[ok]
        res.v[ok] = mh.b2[ok]

    def _intersect_nurbs(self, o, d, tmin, best_t, res, patches):
        ray, prim, tent = self.bvh.candidates(o, d, tmin, best_t)
        if patches is not None:
            g, loc = self.sub_group[prim], self.sub_local[prim]
            pid = np.empty(len(prim), np.int64)
            for gi, grp in enumerate(self.groups):
                sel = g == gi
                pid[sel] = grp.patch[loc[sel]]
            keep = _allowed_pairs(pid, ray, patches)
            ray, prim, tent = ray[keep], prim[keep], tent[keep]
        # nearest boxes first: rank of each candidate within its ray (pairs come sorted by ray, t)
        rank = _rank_within(ray)
        todo = np.ones(len(ray), bool)
        # a second stage pays for its fixed cost only where it can drop many far pairs
        stages = (2, None) if np.count_nonzero(rank >= 2) > STAGE_MIN_PAIRS else (None,)
        search = RootSearch(self, o, d, tmin, best_t, res)
        for stage_max_rank in stages:
            sel = todo & (rank < stage_max_rank) if stage_max_rank is not None else todo.copy()
            sel &= tent <= best_t[ray]
            idx = np.flatnonzero(sel)
            todo[idx] = False
            for c in range(0, len(idx), PAIR_CHUNK):
                part = idx[c:c + PAIR_CHUNK]
                search.solve_pairs(ray[part], prim[part])

    def solve_newton(self, proj, p, q, s, t, bound=None):
        """``newton.newton`` at this object's tolerance (NEWTON_TOL_REL of its diagonal): in
        place on (s, t) for nets of degree (p, q) projected onto their rays' planes
        (``project_nets``), with the nets' second-derivative ``bound`` if given (runs then end
        without a confirming iteration); returns the converged mask."""
        return newton(proj, p, q, s, t, NEWTON_TOL_REL * self.diag, self.stats, bound)


def _allowed(pid, patches):
    if patches is None:
        return np.ones(len(pid), bool)
    return np.any(patches == pid[:, None], axis=1) & (pid >= 0)


def _allowed_pairs(pid, ray, patches):
    return np.any(patches[ray] == pid[:, None], axis=1)


def _rank_within(ray):
    """0, 1, 2, ... position of each pair within its ray's run (pairs are grouped by ray)."""
    if len(ray) == 0:
        return np.zeros(0, np.int64)
    start = np.r_[True, ray[1:] != ray[:-1]]
    idx = np.arange(len(ray))
    return idx - np.maximum.accumulate(np.where(start, idx, 0))
