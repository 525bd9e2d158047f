"""Solving (ray, net) pairs for the nearest hits: Newton runs on the nets seen end-on along
their rays (``newton``), the roots accepted where they lie inside their Bezier piece, beyond the
ray's start and nearer than the ray's best hit; twin runs for grazing roots; and the de
Casteljau fallback, which splits a net whose run found no root or a grazing one into four
children and retries them. Distances are in scene units (metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import bezier as bz
from ..geometry.nurbs import normals as nurbs_normals
from .boxes import slab_intervals
from .newton import NEWTON_TOL_REL, hull_meets, project_nets, newton_seed
from .hits import PatchHit
from .subpatches import SubPatchGroup

# Newton may step outside the sub-patch while converging; a root is accepted when its local
# coordinates lie within this margin of [0, 1] (neighbouring sub-patches overlap on edges).
PARAM_MARGIN = 1e-9
# De Casteljau retry depth for pairs whose Newton run found no root in the net, or a grazing
# one (its net may hold a twin): each level halves the net in both directions; the ray is kept
# only where it meets a child's box and its control hull. Two levels: with the end-on hull
# test few pairs get here, and one level left the twin of a grazing root unfound.
FALLBACK_LEVELS = 2
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
# |Ss x St| below this (relative to (|Ss| + |St|)^2) marks a point at or next to a degenerate one
# (pole, collapsed edge): the normal comes from the patch's own normal evaluation (nurbs.normals:
# the limit normal at the point itself) instead. Near a collapsed edge S_s shrinks to rounding
# noise of the subdivided net's coordinates (each de Casteljau split adds some), and the cross
# product's direction errs by up to ~1e-13 / (this ratio) rad (1e-4 rad at 1e-9 rad from the
# glass_sphere's pole); the patch's own evaluation errs by <= ~3e-7 rad there.
DEGENERATE_REL = 1e-6


@dataclass
class NetPairs:
    """(ray, net) pairs of one sub-patch group: sub-patch nets or their de Casteljau children.
    ``box`` = (s0, s1, t0, t1) is the rectangle a net covers in its sub-patch ``sp``'s local
    coordinates."""

    grp: SubPatchGroup
    r: np.ndarray         # (n,) ray index
    ctrl: np.ndarray      # (n, p+1, q+1, 4) homogeneous
    sp: np.ndarray        # (n,) sub-patch index within the group
    box: np.ndarray       # (n, 4)

    def take(self, idx) -> "NetPairs":
        """The pairs ``idx``."""
        return NetPairs(self.grp, self.r[idx], self.ctrl[idx], self.sp[idx], self.box[idx])


@dataclass
class _Roots:
    """Converged roots of (ray, net) pairs and the surface there."""

    r: np.ndarray         # (k,) ray index
    sp: np.ndarray        # (k,) sub-patch index within the group
    dist: np.ndarray      # (k,) distance of the root's point along the ray (m)
    s: np.ndarray         # (k,) net-local parameters
    t: np.ndarray
    s_sub: np.ndarray     # (k,) sub-patch local parameters
    t_sub: np.ndarray
    P: np.ndarray         # (k, 3) the point, and its partials in net-local (s, t)
    Ps: np.ndarray
    Pt: np.ndarray
    Pss: np.ndarray
    Pst: np.ndarray
    Ptt: np.ndarray
    nrm: np.ndarray       # (k, 3) Ps x Pt
    ln: np.ndarray        # (k,) |Ps x Pt|
    un: np.ndarray        # (k, 3) unit normal
    cos: np.ndarray       # (k,) un . ray direction
    a: np.ndarray         # (k,) the ray's direction in the tangent plane, a Ps + b Pt
    b: np.ndarray

    def take(self, idx) -> "_Roots":
        """The roots ``idx``."""
        return _Roots(**{k: v[idx] for k, v in self.__dict__.items()})


class RootSearch:
    """One intersect call's search of (ray, net) pairs of ``tracer`` (a PatchTracer): rays
    (o, d) (N, 3) with unit d, their segment starts ``tmin`` (N,) (m); ``best_t`` (N,) (m, the
    segment ends before any hit) and ``res`` are updated in place with each nearer hit found."""

    def __init__(self, tracer, o, d, tmin, best_t, res: PatchHit):
        self.tracer, self.diag = tracer, tracer.diag
        self.o, self.d, self.tmin, self.best_t, self.res = o, d, tmin, best_t, res

    def solve_pairs(self, ray, prim):
        """Solve the pairs (ray, sub-patch ``prim``: the tracer's BVH primitive)."""
        tracer = self.tracer
        g_of = tracer.sub_group[prim]
        loc = tracer.sub_local[prim]
        for gi, grp in enumerate(tracer.groups):
            sel = np.flatnonzero(g_of == gi)
            if len(sel) == 0:
                continue
            sp = loc[sel]
            pairs = NetPairs(grp, ray[sel], grp.ctrl[sp], sp,
                             np.tile(np.array([0.0, 1.0, 0.0, 1.0]), (len(sp), 1)))
            self.newton_batch(pairs, FALLBACK_LEVELS)

    def newton_batch(self, pairs: NetPairs, levels: int):
        """Newton on ``pairs``; records hits nearer than best_t.

        Pairs without a root, with a root outside the net, or with a grazing root (its net may
        hold a twin) are split by de Casteljau into four children, kept where the ray still
        meets their boxes, down to ``levels`` more levels."""
        if len(pairs.r) == 0:
            return
        ro, rd = self.o[pairs.r], self.d[pairs.r]
        proj = project_nets(pairs.ctrl, ro, rd)
        meet = hull_meets(proj)
        if not meet.all():
            ro, rd, proj = (x[meet] for x in (ro, rd, proj))
            pairs = pairs.take(meet)
            if len(pairs.r) == 0:
                return
        self.tracer.stats["pairs"] += len(pairs.r)
        ctrl = pairs.ctrl
        if levels == FALLBACK_LEVELS:
            s, t = newton_seed(ctrl, ro, rd)
        else:
            # a retried net's corner seed led Newton astray once (a grazing ray's corner-triangle
            # hit can lie nearer the ray's other crossing, outside the net): start from the middle
            s, t = np.full(len(pairs.r), 0.5), np.full(len(pairs.r), 0.5)
        ok = self.tracer.solve_newton(proj, ctrl.shape[1] - 1, ctrl.shape[2] - 1, s, t)
        in_net = (s >= -PARAM_MARGIN) & (s <= 1 + PARAM_MARGIN) & (t >= -PARAM_MARGIN) \
            & (t <= 1 + PARAM_MARGIN)
        # no root at all, or a root outside the net (another root may hide in it: a grazing
        # ray, or a seed from outside the corner triangles)
        retry = ~ok | ~in_net
        grazing = self.accept(pairs, proj, ok, s, t, twin=True)
        # a grazing root may have a twin in the net that the twin search missed
        retry |= grazing
        if levels > 0:
            self.subdivide(pairs, levels, np.flatnonzero(retry))

    def accept(self, pairs: NetPairs, proj, ok, s, t, twin: bool):
        """Record converged roots (``ok``, at net-local (s, t)) that lie inside their Bezier
        piece and beat best_t.

        With ``twin``, grazing roots get a second Newton run for their twin: two roots of one
        ray in one flat net need a grazing ray (the net's normal cone bounds how far the surface
        turns), and the twin lies about one chord length 2 |cos| / curvature along the ray:
        behind a found root (a nearer hit), ahead of a root at the ray's own start (t <= tmin:
        the next hit of a ray leaving the surface). A root counts as the ray's start, not a hit,
        when the surface crossing it stands for lies at or before tmin (``_crossing_behind``).
        A root past the piece's edge (on the net's polynomial continued across a piece
        boundary: a seam, a knot line) is no hit, but its twin may lie in the net, just inside
        the boundary, where Newton from inside the net went past it: it gets the twin run too.
        ``proj``: the nets projected onto their rays' planes (``project_nets``), for the twin runs.
        Returns the mask of pairs whose root is grazing (their net may hold a second root) and
        whose twin run, if any, did not find a second root."""
        good = np.flatnonzero(ok)
        grazing = np.zeros(len(pairs.r), bool)
        if len(good) == 0:
            return grazing
        roots = self._roots(pairs, s, t, good)
        in_piece = self._in_piece(pairs, good, roots)
        start = self._at_start(roots)
        rr, tt = roots.r, roots.dist
        cand = np.flatnonzero(in_piece & ~start & (tt < self.best_t[rr]))
        order = cand[np.lexsort((tt[cand], rr[cand]))]
        first = order[np.r_[True, rr[order][1:] != rr[order][:-1]]] if len(order) else order
        self._record(pairs.grp, roots, first)
        g = np.flatnonzero(np.abs(roots.cos) < pairs.grp.cone_sin[roots.sp])
        grazing[good[g]] = True
        if twin and len(g):
            found = self._twin(pairs.take(good[g]), proj[good[g]], roots.take(g), start[g])
            grazing[good[g][found]] = False
        return grazing

    def _roots(self, pairs: NetPairs, s, t, good) -> _Roots:
        """The roots (s, t) of pairs ``good`` and the surface there."""
        box, sp = pairs.box, pairs.sp
        s_sub = box[:, 0] + (box[:, 1] - box[:, 0]) * s
        t_sub = box[:, 2] + (box[:, 3] - box[:, 2]) * t
        P, Ps, Pt, Pss, Pst, Ptt = bz.bezier_eval(pairs.ctrl, s[good], t[good], derivatives=2,
                                                  index=good)
        rr = pairs.r[good]
        dd = self.d[rr]
        tt = np.einsum("ij,ij->i", P - self.o[rr], dd)
        nrm = np.cross(Ps, Pt)
        ln = np.linalg.norm(nrm, axis=1)
        un = nrm / np.maximum(ln, 1e-300)[:, None]
        cos = np.einsum("ij,ij->i", un, dd)
        # the ray direction within the tangent plane, in parameter units per unit length
        w = dd - cos[:, None] * un
        w /= np.maximum(np.linalg.norm(w, axis=1), 1e-300)[:, None]
        a, b = _tangent_coords(Ps, Pt, w)
        return _Roots(r=rr, sp=sp[good], dist=tt, s=s[good], t=t[good], s_sub=s_sub[good],
                      t_sub=t_sub[good], P=P, Ps=Ps, Pt=Pt, Pss=Pss, Pst=Pst, Ptt=Ptt, nrm=nrm,
                      ln=ln, un=un, cos=cos, a=a, b=b)

    def _in_piece(self, pairs: NetPairs, good, roots: _Roots):
        """Whether roots (of pairs ``good``) lie inside their Bezier piece, to within how far
        along the ray Newton placed them."""
        grp, box, gs, gg = pairs.grp, pairs.box, roots.sp, good
        ps = grp.ps0[gs] + (grp.ps1[gs] - grp.ps0[gs]) * roots.s_sub
        pt = grp.pt0[gs] + (grp.pt1[gs] - grp.pt0[gs]) * roots.t_sub
        # Newton's residual is a distance from the ray, so a root is placed along the ray only
        # to within tol / |cos| (a grazing root next to a piece boundary may land just across
        # it from either side): the piece test allows that far, in parameter units
        tol = NEWTON_TOL_REL * self.diag
        reach = np.minimum(tol / np.maximum(np.abs(roots.cos), 1e-300), ROOT_REACH_REL * self.diag)
        slack_s = PARAM_MARGIN + reach * np.abs(roots.a) * (grp.ps1[gs] - grp.ps0[gs]) \
            * (box[gg, 1] - box[gg, 0])
        slack_t = PARAM_MARGIN + reach * np.abs(roots.b) * (grp.pt1[gs] - grp.pt0[gs]) \
            * (box[gg, 3] - box[gg, 2])
        return (ps >= -slack_s) & (ps <= 1 + slack_s) & (pt >= -slack_t) & (pt <= 1 + slack_t)

    def _at_start(self, roots: _Roots):
        """Whether roots stand for the ray's own start (a crossing at or before tmin)."""
        rr, tt = roots.r, roots.dist
        start = tt <= self.tmin[rr]
        # |g| <= tol for a converged root, so only these may stand for a crossing behind tmin
        near = np.flatnonzero(~start & (2.0 * NEWTON_TOL_REL * self.diag
                                        >= (tt - self.tmin[rr]) * np.abs(roots.cos)))
        if len(near):
            rn = rr[near]
            start[near] = _crossing_behind(self.o[rn], self.d[rn], self.tmin[rn], roots.take(near))
        return start

    def _twin(self, pairs: NetPairs, proj, roots: _Roots, start):
        """Twin runs of grazing roots (``accept``), seeded one chord length along the ray
        (ahead where the root is the ray's ``start``, behind otherwise); returns the mask of
        roots whose twin run found a second root."""
        a, b = roots.a, roots.b
        curv = np.abs(np.einsum("ij,ij->i", roots.un, a[:, None] ** 2 * roots.Pss
                                + 2 * (a * b)[:, None] * roots.Pst + b[:, None] ** 2 * roots.Ptt))
        chord = 2.0 * np.abs(roots.cos) / np.maximum(curv, 1e-300)
        chord *= np.where(start, 1.0, -1.0)
        # a seed far outside the net means the twin is elsewhere (another net finds it)
        s2 = roots.s + chord * a
        t2 = roots.t + chord * b
        near = np.flatnonzero((s2 >= -1.0) & (s2 <= 2.0) & (t2 >= -1.0) & (t2 <= 2.0))
        found = np.zeros(len(start), bool)
        if len(near) == 0:
            return found
        s2, t2, pairs, proj = s2[near], t2[near], pairs.take(near), proj[near]
        p, q = pairs.ctrl.shape[1] - 1, pairs.ctrl.shape[2] - 1
        ok2 = self.tracer.solve_newton(proj, p, q, s2, t2)
        self.accept(pairs, proj, ok2, s2, t2, twin=False)
        # a twin run that converged away from the first root found the twin (in this net or a
        # neighbour's); one that failed or came back to the first root settles nothing
        found[near] = ok2 & (np.hypot(s2 - roots.s[near], t2 - roots.t[near]) > TWIN_DISTINCT)
        return found

    def _record(self, grp: SubPatchGroup, roots: _Roots, idx):
        """Store the hits of roots ``idx`` (one per ray) that beat the running best."""
        roots = roots.take(idx[roots.dist[idx] < self.best_t[roots.r[idx]]])
        spf, rr, tt, Ps, Pt, ln = roots.sp, roots.r, roots.dist, roots.Ps, roots.Pt, roots.ln
        u = grp.u0[spf] + (grp.u1[spf] - grp.u0[spf]) * roots.s_sub
        v = grp.v0[spf] + (grp.v1[spf] - grp.v0[spf]) * roots.t_sub
        deg = ln <= DEGENERATE_REL * (np.linalg.norm(Ps, axis=1)
                                      + np.linalg.norm(Pt, axis=1)) ** 2 + 1e-300
        nrm = roots.nrm / np.where(deg, 1.0, ln)[:, None]
        pid = grp.patch[spf]
        for p in np.unique(pid[deg]):
            m = deg & (pid == p)
            nrm[m] = nurbs_normals(self.tracer.object.patches[p].surface, u[m], v[m])
        res = self.res
        self.best_t[rr] = tt
        res.t[rr] = tt
        res.point[rr] = roots.P
        res.normal[rr] = nrm
        res.geo_normal[rr] = nrm
        res.tri[rr] = -1
        res.patch[rr] = pid
        res.u[rr] = u
        res.v[rr] = v

    def subdivide(self, pairs: NetPairs, levels: int, idx):
        """Split nets ``idx`` into four children and retry those whose boxes the ray meets.
        The children start Newton from their midpoints (``newton_batch``)."""
        if len(idx) == 0:
            return
        self.tracer.stats["fallback_pairs"] += len(idx)
        left, right = bz.split(pairs.ctrl[idx], 1)
        kids = []
        for half, (a0, a1) in ((left, (0.0, 0.5)), (right, (0.5, 1.0))):
            lo_v, hi_v = bz.split(half, 2)
            for net, (b0, b1) in ((lo_v, (0.0, 0.5)), (hi_v, (0.5, 1.0))):
                kids.append((net, a0, a1, b0, b1))
        bx = pairs.box[idx]
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
        rr = pairs.r[rep]
        meet = np.flatnonzero(_ray_box(self.o[rr], self.d[rr], lo, hi, self.tmin[rr],
                                       self.best_t[rr]))
        kids = NetPairs(pairs.grp, rr[meet], ctrl[meet], pairs.sp[rep[meet]], kbox[meet])
        self.newton_batch(kids, levels - 1)


def _crossing_behind(o, d, tmin, roots: _Roots):
    """Whether each root P (at distance tt > tmin along its ray (o, d)) stands for a surface
    crossing at or before tmin: the ray's own start re-found, not a new hit.

    Newton accepts any point within tolerance of the ray, and a ray leaving the surface at a
    small angle a stays that close to it for about tol / a. The crossing a root stands for is
    the zero nearest P of the ray's height above the surface, to second order in the distance
    tau from P along the ray: h(tau) = g + c tau - k (1 - c^2) tau^2 / 2 (g the height at P
    along the unit normal n, c = d . n, k = n . S'' the normal curvature along the ray's
    tangent-plane direction); where h has no zero, its minimum. A departure root's model
    passes through the departure point, a genuine hit's through P. Since |tau| <= 2|g| / |c|
    and |g| <= tol, callers pass only roots with 2 tol >= (tt - tmin)|c|."""
    tt, P, Ps, Pt, Pss, Pst, Ptt = (roots.dist, roots.P, roots.Ps, roots.Pt, roots.Pss,
                                   roots.Pst, roots.Ptt)
    un, c = roots.un, roots.cos
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
    return (np.where(ok, (g22 * r1 - g12 * r2) / safe, 0.0),
            np.where(ok, (g11 * r2 - g12 * r1) / safe, 0.0))


def _ray_box(o, d, lo, hi, tmin, tmax):
    """Whether segments [tmin, tmax] of rays meet boxes [lo, hi] (closed slabs, zero-safe)."""
    tnear, tfar = slab_intervals(o, d, lo, hi)
    return np.maximum(tnear.max(axis=1), tmin) <= np.minimum(tfar.min(axis=1), tmax)
