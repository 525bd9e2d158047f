"""Exact ray intersection with the specular object's patches, vectorized over ray batches.

Method (after Martin et al.'s practical NURBS ray tracing, adapted to numpy):
1. Build: every NURBS patch is cut into rational Bezier pieces and subdivided into flat
   sub-patches with conservative boxes (``geometry.bezier``); one BVH over all sub-patches.
2. Query: the BVH yields candidate (ray, sub-patch) pairs. Each pair is seeded from the ray's
   hit on the two triangles of the sub-patch's corners (sub-patch midpoint if the plane hit is
   far outside), then Newton iterates on (s, t) in the sub-patch's local coordinates with the
   ray written as the intersection of two planes (a 2x2 system, well conditioned away from
   exact tangency). The net is projected onto the planes once per pair (``_project``: two
   scalar nets and the weights), which also serves the end-on hull test; each iteration then
   evaluates three scalar polynomials. Converged roots inside the sub-patch are hits; the
   nearest wins.
3. Fallback: a pair whose Newton run found no root in its net, or a grazing root whose twin
   (the ray's other nearby crossing) the twin search did not find, is split into four
   children, retried from their midpoints (a few levels deep).
4. Pairs are processed nearest box first; once a ray has a hit, candidates whose boxes start
   beyond it are dropped (in small batches, where few far pairs exist, all pairs go at once).
Mesh patches (triangles) go through the triangle tracer and compete on t.

Units: t is the distance along unit directions, in scene units (metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import bezier as bz
from ..geometry.nurbs import evaluate as nurbs_evaluate
from ..geometry.nurbs import normals as nurbs_normals
from ..scene.model import Mesh, SpecularObject
from .boxes import slab_intervals
from .bvh import BVH
from .meshes import MeshSet

# Flatness of sub-patches, relative to the object's bounding-box diagonal: the control net
# deviates from its bilinear corner interpolation by at most this much (a good Newton seed).
FLAT_TOL_REL = 2e-3
# Newton convergence: residual distance from the ray, relative to the object diagonal.
# Double precision evaluation of a degree <= 5 patch is good to ~1e-15 relative.
NEWTON_TOL_REL = 1e-11
NEWTON_ITERS = 12
# Newton may step outside the sub-patch while converging; a root is accepted when its local
# coordinates lie within this margin of [0, 1] (neighbouring sub-patches overlap on edges).
PARAM_MARGIN = 1e-9
# Largest Newton step in local parameter units, per component: clipping keeps wild steps inside
# the patch. Each component is clipped on its own: next to a collapsed edge (a pole) the step
# along the edge is huge and meaningless (S_s ~ 0 there), while the step away from it is small
# and right; scaling both by one factor stalled the runs on the edge for many iterations.
MAX_STEP = 0.5
# Seeds: a plane hit outside the extended corner triangles (barycentric margin) seeds at the
# sub-patch midpoint instead.
SEED_MARGIN = 0.25
# De Casteljau retry depth for pairs whose Newton run found no root in the net, or a grazing
# one (its net may hold a twin): each level halves the net in both directions; the ray is kept
# only where it meets a child's box and its control hull. Two levels: with the end-on hull
# test few pairs get here, and one level left the twin of a grazing root unfound.
FALLBACK_LEVELS = 2
# A root whose ray makes an angle below the sub-patch's normal-cone half-angle with the tangent
# plane may have a twin root in the same sub-patch (two roots in one net need the normal to turn
# by at least twice that angle). The cone of a rational net is an estimate: it is widened by
# this factor and margin before use.
TWIN_CONE_SAFETY = 1.5
TWIN_CONE_MARGIN_DEG = 1.0
# A twin run that converged at least this far (net-local parameter units) from the first root
# found a second root, not the first one again.
TWIN_DISTINCT = 1e-6
# A converged root lies within tol of the ray, so along the ray only within tol / |cos| of
# the crossing (cos: ray against normal); the piece test allows that much past the piece's edge,
# capped at this fraction of the object diagonal (about the length over which a tangent ray
# stays within tol of a surface curved on the object's scale).
ROOT_REACH_REL = 1e-6
# Child boxes in the retry are padded by this fraction of the object diagonal (rounding).
BOX_PAD_REL = 1e-12
# Self-intersection guard: hits closer than this (relative to the object diagonal) are ignored.
T_MIN_REL = 1e-9
# |Ss x St| below this (relative to (|Ss| + |St|)^2) marks a point at or next to a degenerate one
# (pole, collapsed edge): the normal comes from the patch's own normal evaluation (nurbs.normals:
# the limit normal at the point itself) instead. Near a collapsed edge S_s shrinks to rounding
# noise of the subdivided net's coordinates (each de Casteljau split adds some), and the cross
# product's direction errs by up to ~1e-13 / (this ratio) rad (1e-4 rad at 1e-9 rad from the
# glass_sphere's pole); the patch's own evaluation errs by <= ~3e-7 rad there.
DEGENERATE_REL = 1e-6
# A batch with at most this many far candidates (a ray's third box or later) solves them with
# the near ones in one stage: a stage's fixed cost (a whole Newton-and-fallback pipeline; an
# intersect call cost ~7 ms beyond its pairs' work before the projected-net Newton) outweighs
# the Newton work saved.
STAGE_MIN_PAIRS = 4096
# Newton runs iterated together: their working arrays (~1 kB a run) stay in a core's cache.
NEWTON_BLOCK = 4096
# Pairs solved per batch: bounds memory (a degree-5 pair gathers 36 x 4 float64 control values)
# and keeps a batch's arrays small (exact renders ran ~5 % faster than with 1 << 16).
PAIR_CHUNK = 1 << 14
# A patch is closed in u (v) where its two u (v) edges coincide within this distance, relative to
# the object's diagonal, at CLOSED_PROBES points along them.
CLOSED_TOL_REL = 1e-9
CLOSED_PROBES = 9
# Angular slack (rad) of the end-on hull test: a line within rounding of the hull's boundary
# (or through a control point, angle of a zero vector) counts as meeting it.
HULL_GAP_SLACK = 1e-9
# A control point this close to the line (relative to the farthest) is on it: meeting.
HULL_POINT_REL = 1e-12


@dataclass
class PatchHit:
    """Nearest hits of a batch of rays. Arrays are (N,) or (N,3); misses have t = inf,
    patch = -1, cls = -1 and zero point/normal/uv. ``normal`` is the unit geometric normal as the
    surface is oriented (not flipped toward the ray); (u, v) are the patch's own parameters
    (barycentric (b1, b2) for mesh patches)."""

    hit: np.ndarray
    t: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    patch: np.ndarray
    cls: np.ndarray
    u: np.ndarray
    v: np.ndarray

    @classmethod
    def misses(cls, n: int) -> "PatchHit":
        """``n`` rays that hit nothing (yet)."""
        return cls(hit=np.zeros(n, bool), t=np.full(n, np.inf), point=np.zeros((n, 3)),
                   normal=np.zeros((n, 3)), patch=np.full(n, -1, np.int64),
                   cls=np.full(n, -1, np.int64), u=np.zeros(n), v=np.zeros(n))

    def take(self, idx) -> "PatchHit":
        """The rows ``idx`` of every array."""
        return PatchHit(**{k: v[idx] for k, v in self.__dict__.items()})

    def put(self, rows, other: "PatchHit") -> None:
        """Overwrite rows ``rows`` with ``other`` (len(rows) hits), in place."""
        for k, v in self.__dict__.items():
            v[rows] = getattr(other, k)


@dataclass
class _Nets:
    """The nets of a batch of (ray, net) pairs: sub-patch nets or their de Casteljau children.
    ``box`` = (s0, s1, t0, t1) is the rectangle a net covers in its sub-patch ``sp``'s local
    coordinates."""

    ctrl: np.ndarray      # (n, p+1, q+1, 4) homogeneous
    sp: np.ndarray        # (n,) sub-patch index within the group
    box: np.ndarray       # (n, 4)

    def take(self, idx) -> "_Nets":
        return _Nets(self.ctrl[idx], self.sp[idx], self.box[idx])


@dataclass
class _Group:
    """Sub-patches of one (degree_u, degree_v), from all NURBS patches of the object."""

    ctrl: np.ndarray      # (M, p+1, q+1, 4) homogeneous
    patch: np.ndarray     # (M,) patch id
    cone_sin: np.ndarray  # (M,) sine of the (widened) normal-cone half-angle: grazing limit
    u0: np.ndarray        # (M,) NURBS parameter rectangle of the sub-patch
    u1: np.ndarray
    v0: np.ndarray
    v1: np.ndarray
    ps0: np.ndarray       # (M,) the sub-patch's rectangle in its Bezier piece's [0,1]^2
    ps1: np.ndarray
    pt0: np.ndarray
    pt1: np.ndarray


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
        # each patch's parameter domain (u0, u1, v0, v1): NURBS knot range, [0, 1]^2 for a
        # mesh patch (barycentric); PatchHit (u, v) divided by it is the normalized parameter
        self.uv_domain = np.tile(np.array([0.0, 1.0, 0.0, 1.0]), (len(obj.patches), 1))
        self.pieces: dict[int, bz.BezierPieces] = {}    # each NURBS patch's Bezier pieces
        # (P, 2): the patch is closed in u / in v (its two edges coincide: a surface of
        # revolution's seam), so parameters wrap around
        self.closed = np.zeros((len(obj.patches), 2), bool)
        self._build_nurbs(obj)
        self._stack_pieces()
        self._build_meshes(obj)
        self.stats = {"pairs": 0, "newton_iters": 0, "fallback_pairs": 0}

    # ------------------------------------------------------------------ build
    def _build_nurbs(self, obj):
        flat_tol = FLAT_TOL_REL * self.diag
        groups: dict[tuple[int, int], list] = {}
        for pid, patch in enumerate(obj.patches):
            if patch.surface is None:
                continue
            pieces = bz.extract_bezier(patch.surface)
            self.pieces[pid] = pieces
            self.uv_domain[pid] = (pieces.u0.min(), pieces.u1.max(), pieces.v0.min(),
                                   pieces.v1.max())
            self.closed[pid] = _closed(patch.surface, self.uv_domain[pid], CLOSED_TOL_REL * self.diag)
            sub = bz.subdivide_flat(pieces, flat_tol)
            pi = sub.piece
            du = pieces.u1[pi] - pieces.u0[pi]
            dv = pieces.v1[pi] - pieces.v0[pi]
            cone = TWIN_CONE_SAFETY * bz.normal_cone_half_angle(sub.ctrl) \
                + np.radians(TWIN_CONE_MARGIN_DEG)
            rec = (sub.ctrl, np.full(len(pi), pid), np.sin(np.minimum(cone, np.pi / 2)),
                   pieces.u0[pi] + du * sub.s0, pieces.u0[pi] + du * sub.s1,
                   pieces.v0[pi] + dv * sub.t0, pieces.v0[pi] + dv * sub.t1,
                   sub.s0, sub.s1, sub.t0, sub.t1, sub.lo, sub.hi)
            groups.setdefault(sub.ctrl.shape[1:3], []).append(rec)
        self.groups: list[_Group] = []
        los, his, gid = [], [], []
        for g, recs in enumerate(groups.values()):
            cat = [np.concatenate([r[k] for r in recs]) for k in range(13)]
            self.groups.append(_Group(*cat[:11]))
            los.append(cat[11])
            his.append(cat[12])
            gid.append(np.full(len(cat[0]), g))
        if los:
            self.sub_group = np.concatenate(gid)
            counts = [len(g.patch) for g in self.groups]
            self.sub_local = np.concatenate([np.arange(c) for c in counts])
            self.bvh = BVH.build(np.concatenate(los), np.concatenate(his))
        else:
            self.bvh = None
        self.n_subpatches = int(sum(len(g.patch) for g in self.groups))

    def _stack_pieces(self):
        """All patches' Bezier pieces in one index space (``piece_base[patch]`` + the patch's
        own piece index): their parameter rectangles and patches, and their nets stacked per degree
        (``piece_nets[piece_group[k]][piece_local[k]]``), for Newton runs on known pieces."""
        self.piece_base = np.full(len(self.object.patches), -1, np.int64)
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
        self.piece_rect = np.concatenate(rect) if rect else np.zeros((0, 4))
        self.piece_group = np.concatenate(group) if group else np.zeros(0, np.int64)
        self.piece_local = np.concatenate(local) if local else np.zeros(0, np.int64)
        self.piece_patch = np.concatenate(owner) if owner else np.zeros(0, np.int64)
        self.piece_nets = [np.concatenate(x) for x in nets]

    def _build_meshes(self, obj):
        meshes, ids = [], []
        for pid, patch in enumerate(obj.patches):
            if patch.surface is None:
                meshes.append(Mesh(name=patch.name, vertices=patch.vertices,
                                   triangles=patch.triangles, material=""))
                ids.append(pid)
        self.mesh_patch = np.array(ids, dtype=np.int64)
        self.meshes = MeshSet(meshes) if meshes else None

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
        for stage_max_rank in stages:
            sel = todo & (rank < stage_max_rank) if stage_max_rank is not None else todo.copy()
            sel &= tent <= best_t[ray]
            idx = np.flatnonzero(sel)
            todo[idx] = False
            for c in range(0, len(idx), PAIR_CHUNK):
                part = idx[c:c + PAIR_CHUNK]
                self._solve_pairs(o, d, tmin, best_t, res, ray[part], prim[part])

    def _solve_pairs(self, o, d, tmin, best_t, res, ray, prim):
        g_of = self.sub_group[prim]
        loc = self.sub_local[prim]
        for gi, grp in enumerate(self.groups):
            sel = np.flatnonzero(g_of == gi)
            if len(sel) == 0:
                continue
            sp = loc[sel]
            nets = _Nets(grp.ctrl[sp], sp, np.tile(np.array([0.0, 1.0, 0.0, 1.0]), (len(sp), 1)))
            self._newton_batch(o, d, tmin, best_t, res, ray[sel], nets, grp, FALLBACK_LEVELS)

    def _newton_batch(self, o, d, tmin, best_t, res, r, nets: _Nets, grp, levels):
        """Newton on ``nets`` for rays ``r``; records hits nearer than best_t.

        Pairs without a root, with a root outside the net, or with a grazing root (its net may
        hold a twin) are split by de Casteljau into four children, kept where the ray still
        meets their boxes."""
        if len(r) == 0:
            return
        ro, rd = o[r], d[r]
        proj = _project(nets.ctrl, ro, rd)
        meet = _hull_meets(proj)
        if not meet.all():
            r, ro, rd, proj = (x[meet] for x in (r, ro, rd, proj))
            nets = nets.take(meet)
            if len(r) == 0:
                return
        self.stats["pairs"] += len(r)
        ctrl = nets.ctrl
        if levels == FALLBACK_LEVELS:
            s, t = _seed(ctrl, ro, rd)
        else:
            # a retried net's corner seed led Newton astray once (a grazing ray's corner-triangle
        # hit can lie nearer the ray's other crossing, outside the net): start from the middle
            s, t = np.full(len(r), 0.5), np.full(len(r), 0.5)
        ok = self._newton(proj, ctrl.shape[1] - 1, ctrl.shape[2] - 1, s, t)
        in_net = (s >= -PARAM_MARGIN) & (s <= 1 + PARAM_MARGIN) & (t >= -PARAM_MARGIN) \
            & (t <= 1 + PARAM_MARGIN)
        # no root at all, or a root outside the net (another root may hide in it: a grazing
        # ray, or a seed from outside the corner triangles)
        retry = ~ok | ~in_net
        grazing = self._accept(o, d, tmin, best_t, res, r, nets, proj, grp, ok, s, t, twin=True)
        # a grazing root may have a twin in the net that the twin search missed
        retry |= grazing
        if levels > 0:
            self._subdivide(o, d, tmin, best_t, res, r, nets, grp, levels, np.flatnonzero(retry))

    def _newton(self, proj, p, q, s, t):
        """Newton iterations in place on (s, t) for nets of degree (p, q) projected onto their
        rays' planes (``_project``: proj (n, (p+1)(q+1), 3)); returns the converged mask. Each
        step component is clipped to MAX_STEP; at a singular Jacobian the step is the least-squares
        one; runs that leave [-1, 2]^2 or meet a zero Jacobian stop unconverged. The live runs are kept packed (no per-iteration gathers).

        With A, B, W the projected nets' values, the ray planes' residuals are f1 = A / W,
        f2 = B / W (distances of the surface point from the planes) and their partials
        (A_s - W_s f1) / W etc.: the rational surface's, without forming its points."""
        ok = np.zeros(len(s), bool)
        for lo in range(0, len(s), NEWTON_BLOCK):         # blocks stay in cache
            hi = min(lo + NEWTON_BLOCK, len(s))
            ok[lo:hi] = self._newton_block(proj[lo:hi], p, q, s[lo:hi], t[lo:hi])
        return ok

    def _newton_block(self, proj, p, q, s, t):
        """_newton on one block (s, t: views, updated in place)."""
        tol = NEWTON_TOL_REL * self.diag
        ok = np.zeros(len(s), bool)
        act = np.arange(len(s))
        fa, ss, tt = proj, s.copy(), t.copy()
        for _ in range(NEWTON_ITERS):
            if len(act) == 0:
                break
            self.stats["newton_iters"] += len(act)
            H = bz.tensor_weights(ss, tt, p, q, 1) @ fa         # (k, partial S/Ss/St, A/B/W)
            w = H[:, 0, 2]
            f1 = H[:, 0, 0] / w
            f2 = H[:, 0, 1] / w
            conv = np.hypot(f1, f2) <= tol
            a = (H[:, 1, 0] - H[:, 1, 2] * f1) / w
            b = (H[:, 2, 0] - H[:, 2, 2] * f1) / w
            c = (H[:, 1, 1] - H[:, 1, 2] * f2) / w
            e = (H[:, 2, 1] - H[:, 2, 2] * f2) / w
            det = a * e - b * c
            sing = ~(np.abs(det) > 1e-300 + 1e-14 * (np.abs(a * e) + np.abs(b * c)))
            # a rank-one Jacobian (on a collapsed edge S_s = 0): the least-squares step J^T f /
            # |J|^2 moves off the edge; only a zero Jacobian ends the run
            frob = a * a + b * b + c * c + e * e
            dead = sing & ~(frob > 1e-300)
            safe = np.where(sing, np.where(dead, 1.0, frob), det)
            ds = np.where(sing, a * f1 + c * f2, e * f1 - b * f2) / safe
            dt = np.where(sing, b * f1 + e * f2, a * f2 - c * f1) / safe
            ss -= np.where(conv, 0.0, np.clip(ds, -MAX_STEP, MAX_STEP))
            tt -= np.where(conv, 0.0, np.clip(dt, -MAX_STEP, MAX_STEP))
            done = conv | dead | (ss < -1.0) | (ss > 2.0) | (tt < -1.0) | (tt > 2.0)
            if done.any():
                ok[act[conv]] = True
                s[act[done]] = ss[done]
                t[act[done]] = tt[done]
                keep = ~done
                act, fa, ss, tt = act[keep], fa[keep], ss[keep], tt[keep]
        s[act] = ss
        t[act] = tt
        return ok

    def _accept(self, o, d, tmin, best_t, res, r, nets: _Nets, proj, grp, ok, s, t, twin):
        """Record converged roots that lie inside their Bezier piece and beat best_t.

        With ``twin``, grazing roots get a second Newton run for their twin: two roots of one
        ray in one flat net need a grazing ray (the net's normal cone bounds how far the surface
        turns), and the twin lies about one chord length 2 |cos| / curvature along the ray:
        behind a found root (a nearer hit), ahead of a root at the ray's own start (t <= tmin:
        the next hit of a ray leaving the surface). A root counts as the ray's start, not a hit,
        when the surface crossing it stands for lies at or before tmin (``_crossing_behind``).
        A root past the piece's edge (on the net's polynomial continued across a piece
        boundary: a seam, a knot line) is no hit, but its twin may lie in the net, just inside
        the boundary, where Newton from inside the net went past it: it gets the twin run too.
        ``proj``: the nets projected onto their rays' planes (``_project``), for the twin runs.
        Returns the mask of pairs whose root is grazing (their net may hold a second root) and
        whose twin run, if any, did not find a second root."""
        ctrl, sp, box = nets.ctrl, nets.sp, nets.box
        s_sub = box[:, 0] + (box[:, 1] - box[:, 0]) * s
        t_sub = box[:, 2] + (box[:, 3] - box[:, 2]) * t
        ps = grp.ps0[sp] + (grp.ps1[sp] - grp.ps0[sp]) * s_sub
        pt = grp.pt0[sp] + (grp.pt1[sp] - grp.pt0[sp]) * t_sub
        good = np.flatnonzero(ok)
        grazing = np.zeros(len(r), bool)
        if len(good) == 0:
            return grazing
        P, Ps, Pt, Pss, Pst, Ptt = bz.bezier_eval(ctrl, s[good], t[good], derivatives=2,
                                                  index=good)
        rr = r[good]
        dd = d[rr]
        tt = np.einsum("ij,ij->i", P - o[rr], dd)
        nrm = np.cross(Ps, Pt)
        ln = np.linalg.norm(nrm, axis=1)
        un = nrm / np.maximum(ln, 1e-300)[:, None]
        cos = np.einsum("ij,ij->i", un, dd)
        # the ray direction within the tangent plane, in parameter units per unit length
        w = dd - cos[:, None] * un
        w /= np.maximum(np.linalg.norm(w, axis=1), 1e-300)[:, None]
        a, b = _tangent_coords(Ps, Pt, w)
        # Newton's residual is a distance from the ray, so a root is placed along the ray only
        # to within tol / |cos| (a grazing root next to a piece boundary may land just across
        # it from either side): the piece test allows that far, in parameter units
        tol = NEWTON_TOL_REL * self.diag
        reach = np.minimum(tol / np.maximum(np.abs(cos), 1e-300), ROOT_REACH_REL * self.diag)
        gs, gg = sp[good], good
        slack_s = PARAM_MARGIN + reach * np.abs(a) * (grp.ps1[gs] - grp.ps0[gs]) \
            * (box[gg, 1] - box[gg, 0])
        slack_t = PARAM_MARGIN + reach * np.abs(b) * (grp.pt1[gs] - grp.pt0[gs]) \
            * (box[gg, 3] - box[gg, 2])
        in_piece = (ps[gg] >= -slack_s) & (ps[gg] <= 1 + slack_s) & (pt[gg] >= -slack_t) \
            & (pt[gg] <= 1 + slack_t)
        start = tt <= tmin[rr]
        # |g| <= tol for a converged root, so only these may stand for a crossing behind tmin
        near = np.flatnonzero(~start & (2.0 * NEWTON_TOL_REL * self.diag
                                        >= (tt - tmin[rr]) * np.abs(cos)))
        if len(near):
            start[near] = _crossing_behind(o[rr[near]], dd[near], tt[near], tmin[rr[near]],
                                           P[near], Ps[near], Pt[near], Pss[near], Pst[near],
                                           Ptt[near], un[near], cos[near])
        cand = np.flatnonzero(in_piece & ~start & (tt < best_t[rr]))
        order = cand[np.lexsort((tt[cand], rr[cand]))]
        first = order[np.r_[True, rr[order][1:] != rr[order][:-1]]] if len(order) else order
        self._record(res, best_t, grp, sp[good[first]], rr[first], tt[first], P[first],
                     Ps[first], Pt[first], nrm[first], ln[first], s_sub[good[first]],
                     t_sub[good[first]])
        g = np.flatnonzero(np.abs(cos) < grp.cone_sin[sp[good]])
        grazing[good[g]] = True
        if not twin or len(g) == 0:
            return grazing
        a, b = a[g], b[g]
        curv = np.abs(np.einsum("ij,ij->i", un[g], a[:, None] ** 2 * Pss[g]
                                + 2 * (a * b)[:, None] * Pst[g] + b[:, None] ** 2 * Ptt[g]))
        chord = 2.0 * np.abs(cos[g]) / np.maximum(curv, 1e-300)
        chord *= np.where(start[g], 1.0, -1.0)
        # a seed far outside the net means the twin is elsewhere (another net finds it)
        s2 = s[good[g]] + chord * a
        t2 = t[good[g]] + chord * b
        near = (s2 >= -1.0) & (s2 <= 2.0) & (t2 >= -1.0) & (t2 <= 2.0)
        gi, s2, t2 = good[g][near], s2[near], t2[near]
        if len(gi) == 0:
            return grazing
        ok2 = self._newton(proj[gi], ctrl.shape[1] - 1, ctrl.shape[2] - 1, s2, t2)
        self._accept(o, d, tmin, best_t, res, r[gi], nets.take(gi), proj[gi], grp, ok2, s2, t2,
                     twin=False)
        # a twin run that converged away from the first root found the twin (in this net or a
        # neighbour's); one that failed or came back to the first root settles nothing
        grazing[gi[ok2 & (np.hypot(s2 - s[gi], t2 - t[gi]) > TWIN_DISTINCT)]] = False
        return grazing

    def _record(self, res, best_t, grp, spf, rr, tt, P, Ps, Pt, nrm, ln, s_sub, t_sub):
        """Store hits (one per ray) that beat the running best; (s_sub, t_sub) are sub-patch
        local coordinates."""
        better = tt < best_t[rr]
        spf, rr, tt, P, Ps, Pt, nrm, ln, s_sub, t_sub = (
            x[better] for x in (spf, rr, tt, P, Ps, Pt, nrm, ln, s_sub, t_sub))
        u = grp.u0[spf] + (grp.u1[spf] - grp.u0[spf]) * s_sub
        v = grp.v0[spf] + (grp.v1[spf] - grp.v0[spf]) * t_sub
        deg = ln <= DEGENERATE_REL * (np.linalg.norm(Ps, axis=1)
                                      + np.linalg.norm(Pt, axis=1)) ** 2 + 1e-300
        nrm = nrm / np.where(deg, 1.0, ln)[:, None]
        pid = grp.patch[spf]
        for p in np.unique(pid[deg]):
            m = deg & (pid == p)
            nrm[m] = nurbs_normals(self.object.patches[p].surface, u[m], v[m])
        best_t[rr] = tt
        res.t[rr] = tt
        res.point[rr] = P
        res.normal[rr] = nrm
        res.patch[rr] = pid
        res.u[rr] = u
        res.v[rr] = v

    def _subdivide(self, o, d, tmin, best_t, res, r, nets: _Nets, grp, levels, idx):
        """Split nets ``idx`` into four children and retry those whose boxes the ray meets.
        The children start Newton from their midpoints (``_newton_batch``)."""
        if len(idx) == 0:
            return
        self.stats["fallback_pairs"] += len(idx)
        left, right = bz.split(nets.ctrl[idx], 1)
        kids = []
        for half, (a0, a1) in ((left, (0.0, 0.5)), (right, (0.5, 1.0))):
            lo_v, hi_v = bz.split(half, 2)
            for net, (b0, b1) in ((lo_v, (0.0, 0.5)), (hi_v, (0.5, 1.0))):
                kids.append((net, a0, a1, b0, b1))
        bx = nets.box[idx]
        ctrl = np.concatenate([k[0] for k in kids])
        rep = np.tile(idx, 4)
        ws = bx[:, 1] - bx[:, 0]
        wt = bx[:, 3] - bx[:, 2]
        kbox = np.concatenate([np.stack([bx[:, 0] + k[1] * ws, bx[:, 0] + k[2] * ws,
                                         bx[:, 2] + k[3] * wt, bx[:, 2] + k[4] * wt], 1)
                               for k in kids])
        pts = ctrl[..., :3] / ctrl[..., 3:]
        lo = pts.min(axis=(1, 2)) - BOX_PAD_REL * self.diag
        hi = pts.max(axis=(1, 2)) + BOX_PAD_REL * self.diag
        rr = r[rep]
        meet = np.flatnonzero(_ray_box(o[rr], d[rr], lo, hi, tmin[rr], best_t[rr]))
        kids = _Nets(ctrl[meet], nets.sp[rep[meet]], kbox[meet])
        self._newton_batch(o, d, tmin, best_t, res, rr[meet], kids, grp, levels - 1)


# ---------------------------------------------------------------------- helpers
def _closed(surf, dom, tol) -> tuple[bool, bool]:
    """Whether NURBS ``surf`` (domain ``dom`` = u0, u1, v0, v1) is closed in u and in v."""
    x = np.linspace(0.0, 1.0, CLOSED_PROBES)
    out = []
    for edge in ((dom[0], dom[1], dom[2] + x * (dom[3] - dom[2]), True),
                 (dom[2], dom[3], dom[0] + x * (dom[1] - dom[0]), False)):
        lo, hi, along, is_u = edge
        a = np.full(CLOSED_PROBES, lo)
        b = np.full(CLOSED_PROBES, hi)
        p0 = nurbs_evaluate(surf, a, along, 0)[0] if is_u else nurbs_evaluate(surf, along, a, 0)[0]
        p1 = nurbs_evaluate(surf, b, along, 0)[0] if is_u else nurbs_evaluate(surf, along, b, 0)[0]
        out.append(bool(np.linalg.norm(p0 - p1, axis=1).max() <= tol))
    return out[0], out[1]


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


def _ray_planes(d):
    """Two unit normals orthogonal to each direction and to each other (Duff et al.'s basis)."""
    sign = np.where(d[:, 2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + d[:, 2])
    b = d[:, 0] * d[:, 1] * a
    n1 = np.stack([1.0 + sign * d[:, 0] ** 2 * a, sign * b, -sign * d[:, 0]], 1)
    n2 = np.stack([b, sign + d[:, 1] ** 2 * a, -d[:, 1]], 1)
    return n1, n2


def _seed(ctrl, ro, rd):
    """Newton seeds (s, t) from the ray's hit on the two triangles spanned by the net's corner
    points (its surface corners); the net's midpoint where the plane hit lies far outside."""
    corners = ctrl[:, [0, -1, 0, -1], [0, 0, -1, -1]]
    cP = corners[..., :3] / corners[..., 3:]
    n = len(ro)
    s = np.full(n, 0.5)
    t = np.full(n, 0.5)
    found = np.zeros(n, bool)
    # triangle A: (00, 10, 11) -> s = b1 + b2, t = b2 ; triangle B: (00, 11, 01) -> s = b1, t = b1 + b2
    for (i1, i2), a_is_s in (((1, 3), True), ((3, 2), False)):
        p0, e1, e2 = cP[:, 0], cP[:, i1] - cP[:, 0], cP[:, i2] - cP[:, 0]
        pv = np.cross(rd, e2)
        det = np.einsum("ij,ij->i", e1, pv)
        usable = np.abs(det) > 1e-300
        safe = np.where(usable, det, 1.0)
        tv = ro - p0
        b1 = np.einsum("ij,ij->i", tv, pv) / safe
        b2 = np.einsum("ij,ij->i", rd, np.cross(tv, e1)) / safe
        hit = usable & (b1 >= -SEED_MARGIN) & (b2 >= -SEED_MARGIN) \
            & (b1 + b2 <= 1.0 + SEED_MARGIN) & ~found
        ls, lt = (b1 + b2, b2) if a_is_s else (b1, b1 + b2)
        s = np.where(hit, np.clip(ls, 0.0, 1.0), s)
        t = np.where(hit, np.clip(lt, 0.0, 1.0), t)
        found |= hit
    return s, t


def _crossing_behind(o, d, tt, tmin, P, Ps, Pt, Pss, Pst, Ptt, un, cos):
    """Whether each root P (at distance tt > tmin along its ray) stands for a surface crossing
    at or before tmin: the ray's own start re-found, not a new hit.

    Newton accepts any point within tolerance of the ray, and a ray leaving the surface at a
    small angle a stays that close to it for about tol / a. The crossing a root stands for is
    the zero nearest P of the ray's height above the surface, to second order in the distance
    tau from P along the ray: h(tau) = g + c tau - k (1 - c^2) tau^2 / 2 (g the height at P
    along the unit normal n, c = d . n, k = n . S'' the normal curvature along the ray's
    tangent-plane direction); where h has no zero, its minimum. A departure root's model
    passes through the departure point, a genuine hit's through P. Since |tau| <= 2|g| / |c|
    and |g| <= tol, callers pass only roots with 2 tol >= (tt - tmin)|c|."""
    c = cos
    g = np.einsum("ij,ij->i", o + tt[:, None] * d - P, un)
    w = d - c[:, None] * un
    w /= np.maximum(np.linalg.norm(w, axis=1), 1e-300)[:, None]
    a, b = _tangent_coords(Ps, Pt, w)
    k = np.einsum("ij,ij->i", un, a[:, None] ** 2 * Pss + 2 * (a * b)[:, None] * Pst
                  + b[:, None] ** 2 * Ptt)
    q = -k * (1.0 - c * c)                       # h''
    disc = c * c - 2.0 * q * g
    den = c + np.copysign(np.sqrt(np.maximum(disc, 0.0)), c)
    with np.errstate(divide="ignore", invalid="ignore"):
        tau = np.where(disc >= 0.0, -2.0 * g / den, -c / q)
    tau = np.where(np.isfinite(tau), tau, 0.0)   # c = 0 with g = 0 or h'' = 0: P itself
    return tt + tau <= tmin


def _tangent_coords(Ps, Pt, w):
    """(a, b) with a Ps + b Pt = w for tangent vectors w (least squares, 2x2 normal equations)."""
    g11 = np.einsum("ij,ij->i", Ps, Ps)
    g12 = np.einsum("ij,ij->i", Ps, Pt)
    g22 = np.einsum("ij,ij->i", Pt, Pt)
    r1 = np.einsum("ij,ij->i", Ps, w)
    r2 = np.einsum("ij,ij->i", Pt, w)
    det = g11 * g22 - g12 * g12
    safe = np.where(np.abs(det) > 1e-300, det, 1.0)
    ok = np.abs(det) > 1e-300
    return np.where(ok, (g22 * r1 - g12 * r2) / safe, 0.0), np.where(ok, (g11 * r2 - g12 * r1) / safe, 0.0)


def _project(ctrl, ro, rd):
    """Homogeneous nets ``ctrl`` (n, p+1, q+1, 4) projected onto their rays' two planes
    (``_ray_planes``: n_i . x = c_i through the origin ``ro``): (n, (p+1)(q+1), 3) holding per
    control point A = n1 . X - c1 w, B = n2 . X - c2 w and w. A / w and B / w are the point's
    coordinates in the plane seen end-on along the ray, which passes through (0, 0)."""
    n1, n2 = _ray_planes(rd)
    h = ctrl.reshape(len(ctrl), -1, 4)
    nrm = np.stack([n1, n2], axis=2)                                    # (n, 3, 2)
    proj = np.empty(h.shape[:2] + (3,))
    np.matmul(h[..., :3], nrm, out=proj[..., :2])
    proj[..., 0] -= np.einsum("ij,ij->i", n1, ro)[:, None] * h[..., 3]
    proj[..., 1] -= np.einsum("ij,ij->i", n2, ro)[:, None] * h[..., 3]
    proj[..., 2] = h[..., 3]
    return proj


def _hull_meets(proj):
    """False where the ray certainly misses the net's surface: the ray's line, seen end-on in
    the plane of (n1, n2), lies outside the 2D convex hull of the control points (convex hull
    property; w > 0 keeps the homogeneous points' angles). ``proj``: the projected nets
    (``_project``). First the hull's bounding box (all points on one side of one ray plane),
    then the hull itself: the line is outside it when the points' angles around it leave a
    gap wider than pi."""
    f1, f2 = proj[..., 0], proj[..., 1]
    meets = ~((f1.min(1) > 0) | (f1.max(1) < 0) | (f2.min(1) > 0) | (f2.max(1) < 0))
    idx = np.flatnonzero(meets)
    if len(idx):
        a, b = f1[idx], f2[idx]
        ang = np.sort(np.arctan2(b, a), axis=1)
        gap = np.maximum(np.diff(ang, axis=1).max(axis=1), ang[:, 0] + 2 * np.pi - ang[:, -1])
        r = np.hypot(a, b)
        on_point = r.min(axis=1) <= HULL_POINT_REL * r.max(axis=1)
        meets[idx] = (gap <= np.pi + HULL_GAP_SLACK) | on_point
    return meets


def _ray_box(o, d, lo, hi, tmin, tmax):
    """Whether segments [tmin, tmax] of rays meet boxes [lo, hi] (closed slabs, zero-safe)."""
    tnear, tfar = slab_intervals(o, d, lo, hi)
    return np.maximum(tnear.max(axis=1), tmin) <= np.minimum(tfar.min(axis=1), tmax)
