"""Parallelograms (pairs of mesh triangles that form one) tested against packets of rays: the
closest hit and any-hit of many rays against a few hundred planar quads, without a hierarchy
walk.

A parallelogram q0 + u eu + v ev (u, v in [0, 1]) is kept as three linear functionals of space:
its unit normal and its dual basis (u = a.(p - q0), v = b.(p - q0)), each a scale times one of
the set's distinct unit *directions*. Rooms and furniture built along the axes share three, so
per ray each direction's dot products with its origin and direction are found once, and a
(quad, ray) test is about 20 array operations.

Rays are cut into packets of LANES consecutive rays (callers pass coherent rays in order:
camera rays row by row, the rays spawned from them in the same order). Per axis, a packet's
origins, directions and t ranges bound where its rays can be; only the quads whose padded boxes
meet those bounds are tested, densely over the packet's lanes: for the closest hit first the
quad each packet may reach first, then those it may reach before its farthest hit so far.
Shadow rays toward a point light (segments ending at an *apex*) are bounded from the apex, and
quads whose plane has the packet's origins and the apex on one side are skipped. Incoherent
packets are as exact, they only test more quads. A hit's t and barycentrics come from the
plane and the parallelogram coordinates (Moller-Trumbore's on its triangle to rounding).
"""

from __future__ import annotations

import numpy as np

BARY_EPS = 1e-10        # barycentric units: closes rounding gaps along shared edges/vertices
PARALLEL_EPS = 1e-12    # |cos(ray, plane normal)| below which a ray counts as parallel: no hit
LANES = 32              # rays per packet: wider packets cull less, narrower ones cost more tests
TOWARD_LANES = 64       # rays per packet bounded from an apex: converging segments stay close
QUAD_TOL = 1e-12        # |x + y - s1 - s2| / |s2 - s1| of two triangles (s1, x, s2), (s1, s2, y)
                        # below which they form a parallelogram (rounding of exact corners)
PAIR_ROUNDS = 3         # rounds of the pairing of triangles into parallelograms (a triangle can
                        # pair with up to 3 neighbours; leftovers stay triangles)
NO_TRI = np.iinfo(np.int64).max     # 'no triangle yet' in minimum reductions of indices


def parallelograms(vertices, faces, candidates):
    """Pairs of ``candidates`` (triangle indices) that share an edge (by vertex index) and form
    a parallelogram, each triangle in at most one pair. Returns (ta, tb, q0, eu, ev): the
    parallelogram is q0 + [0,1] eu + [0,1] ev, ta covers its part with u >= v, tb the rest."""
    cand = np.asarray(candidates, dtype=np.int64)
    f = faces[cand]
    a, b = f, np.roll(f, -1, axis=1)                 # edge k: corners k, k+1; opposite k+2
    lo, hi = np.minimum(a, b).ravel(), np.maximum(a, b).ravel()
    key = lo * len(vertices) + hi
    order = np.argsort(key, kind="stable")
    ks = key[order]
    same = np.flatnonzero(ks[1:] == ks[:-1])
    # edges shared by exactly two candidates (not three or more)
    single = ((same == 0) | (ks[same - 1] != ks[same])) & \
             ((same + 2 >= len(ks)) | (ks[np.minimum(same + 2, len(ks) - 1)] != ks[same]))
    same = same[single]
    e1, e2 = order[same], order[same + 1]            # (candidate * 3 + edge slot)
    i, j = e1 // 3, e2 // 3
    s1, s2 = vertices[lo[e1]], vertices[hi[e1]]
    x = vertices[f[i, (e1 % 3 + 2) % 3]]
    y = vertices[f[j, (e2 % 3 + 2) % 3]]
    span = np.linalg.norm(s2 - s1, axis=1)
    ok = (i != j) & (np.linalg.norm(np.cross(x - s1, y - s1), axis=1) > 0) & \
        (np.linalg.norm(x + y - s1 - s2, axis=1) <= QUAD_TOL * span)
    i, j, s1, x, y = i[ok], j[ok], s1[ok], x[ok], y[ok]
    keep = np.zeros(len(i), bool)
    free = np.ones(len(i), bool)
    for _ in range(PAIR_ROUNDS):                     # the first free pair of both triangles
        first = np.full(len(cand), len(i))
        idx = np.flatnonzero(free)
        np.minimum.at(first, i[idx], idx)
        np.minimum.at(first, j[idx], idx)
        take = free & (first[i] == np.arange(len(i))) & (first[j] == np.arange(len(i)))
        keep |= take
        used = np.zeros(len(cand), bool)
        used[i[take]] = used[j[take]] = True
        free &= ~used[i] & ~used[j]
    i, j, s1, x, y = i[keep], j[keep], s1[keep], x[keep], y[keep]
    return cand[i], cand[j], s1, x - s1, y - s1


def _canonical(vecs):
    """(unit vectors with their first nonzero component positive, the signs applied)."""
    first = np.argmax(vecs != 0, axis=1)
    s = np.where(vecs[np.arange(len(vecs)), first] < 0, -1.0, 1.0)
    return vecs * s[:, None] + 0.0, s              # + 0.0 turns -0.0 into 0.0


def _bary_map(a, b, q0, tri):
    """(2, 3, P): a triangle's barycentrics (b1, b2) = m[i, 0] + m[i, 1] u + m[i, 2] v at
    quad coordinates (u, v), for triangles ``tri`` (P, 3 corners, 3) whose corners are quad
    corners (u, v in {0, 1}: the map's coefficients are small integers, exact)."""
    rel = tri - q0[:, None]
    cu = np.rint(np.einsum("pj,pcj->pc", a, rel))
    cv = np.rint(np.einsum("pj,pcj->pc", b, rel))
    du1, du2, dv1, dv2 = cu[:, 1] - cu[:, 0], cu[:, 2] - cu[:, 0], cv[:, 1] - cv[:, 0], \
        cv[:, 2] - cv[:, 0]
    det = du1 * dv2 - du2 * dv1                         # +-1
    return np.stack([np.stack([cv[:, 0] * du2 - cu[:, 0] * dv2, dv2, -du2]) / det,
                     np.stack([cu[:, 0] * dv1 - cv[:, 0] * du1, -dv1, du1]) / det])


class Packets:
    """Rays (columns ot, dt (3, n)) cut into packets of LANES or TOWARD_LANES (the last one
    padded with lanes that never hit), with each packet's per-axis bounds: origins in [o0, o1]
    + t [d0, d1], t in [t0, t1], each (3, packets) / (packets,). ``apex``: a point every
    segment ends at, within ``apex_pad``, with tmin >= 0 (shadow rays toward a point light); a
    packet is then bounded from the apex instead (``toward``): each point of a segment lies at
    apex' + s (origin - apex'), s in [0, 1], for an apex' within ``apex_pad`` of the apex, far
    tighter than its origins' and directions' spreads. Where every ray starts at one point
    (camera rays), ``point`` is it (pad 0)."""

    def __init__(self, ot, dt, tmin, tmax, apex=None, apex_pad: float = 0.0):
        n = ot.shape[1]                             # ot, dt: origins, directions (3, n)
        self.lanes = lanes = LANES if apex is None else TOWARD_LANES
        self.n, self.npk = n, -(-n // lanes)
        m = self.npk * lanes
        if m > n:
            ot, dt = (np.concatenate([a, np.repeat(a[:, -1:], m - n, axis=1)], axis=1)
                      for a in (ot, dt))
            tmin = np.concatenate([tmin, np.full(m - n, np.inf)])
            tmax = np.concatenate([tmax, np.full(m - n, -np.inf)])
        shape = (3, self.npk, lanes)
        self.ot = np.ascontiguousarray(ot).reshape(shape)
        self.dt = np.ascontiguousarray(dt).reshape(shape)
        self.tmin, self.tmax = tmin.reshape(self.npk, lanes), tmax.reshape(self.npk, lanes)
        self.o0, self.o1 = self.ot.min(axis=2), self.ot.max(axis=2)
        self.toward = apex is not None
        if self.toward:
            self.point, self.pad = np.asarray(apex, dtype=np.float64), float(apex_pad)
            self.d0 = self.o0 - self.point[:, None] - apex_pad
            self.d1 = self.o1 - self.point[:, None] + apex_pad
            self.t0, self.t1 = np.zeros(self.npk), np.ones(self.npk)
            return
        self.d0, self.d1 = self.dt.min(axis=2), self.dt.max(axis=2)
        self.t0, self.t1 = self.tmin.min(axis=1), self.tmax.max(axis=1)
        one = np.array_equal(self.o0, self.o1) and np.all(self.o0 == self.o0[:, :1])
        self.point, self.pad = (self.o0[:, 0].copy(), 0.0) if one else (None, 0.0)

    def dots(self, dirs, axis, k, pkt, which):
        """(K, lanes) dot products of unit directions ``dirs[k]`` with the lanes' origins
        (``which`` "o") or directions ("d") of packets ``pkt``; ``axis``: the coordinate axis
        of each direction, or None."""
        src = self.ot if which == "o" else self.dt
        if axis is not None:
            return src[axis[k], pkt]
        e = dirs[k]
        return (e[:, 0, None] * src[0, pkt] + e[:, 1, None] * src[1, pkt]
                + e[:, 2, None] * src[2, pkt])

    def meets(self, lo, hi):
        """(boxes, packets) bool: may a ray of the packet meet the box [lo, hi] (B, 3)? For
        t >= 0 the packet's points along an axis lie in [o0 + t d0, o1 + t d1]; that must meet
        [lo, hi] on every axis at one common t within the packet's t range. Also returns the
        lower bound of that t (boxes, packets): no ray of the packet meets the box before."""
        with np.errstate(divide="ignore", invalid="ignore"):
            inv0, inv1 = 1.0 / self.d0, 1.0 / self.d1
            # r * w gives a bound, or +-inf where a zero speed decides by the sign of r alone,
            # or NaN (skipped by fmin/fmax) where the side does not bound t
            up0 = np.where(self.d0 > 0, inv0, np.where(self.d0 == 0, np.inf, np.nan))
            lo0 = np.where(self.d0 < 0, inv0, np.nan)
            lo1 = np.where(self.d1 > 0, inv1, np.nan)
            up1 = np.where(self.d1 < 0, inv1, np.where(self.d1 == 0, -np.inf, np.nan))
            a = np.broadcast_to(np.maximum(self.t0, 0.0), (len(lo), self.npk))
            b = np.broadcast_to(self.t1, (len(lo), self.npk))
            if self.point is not None:              # one origin: per box, not per pair
                h1, l0 = hi - (self.point - self.pad), lo - (self.point + self.pad)
            for ax in range(3):
                if self.point is not None:
                    r1, r0 = h1[:, ax, None], l0[:, ax, None]
                else:
                    r1 = hi[:, ax, None] - self.o0[ax]        # (boxes, packets)
                    r0 = lo[:, ax, None] - self.o1[ax]
                b = np.fmin(b, r1 * up0[ax])
                a = np.fmax(a, r1 * lo0[ax])
                a = np.fmax(a, r0 * lo1[ax])
                b = np.fmin(b, r0 * up1[ax])
        out = a <= b
        neg = self.t0 < 0                           # negative t: bounds above do not hold
        if neg.any():
            out[:, neg] = True
            a = np.where(neg, -np.inf, a)
        return out, a


class QuadSet:
    """Parallelograms q0 + [0,1] eu + [0,1] ev (P, 3 each), each covering two mesh triangles:
    ``ta`` its part with u >= v, ``tb`` the rest, with corners ``corners_a``, ``corners_b``
    (P, 3, 3) in their faces' vertex order. Boxes are padded by ``pad``."""

    def __init__(self, ta, tb, q0, eu, ev, corners_a, corners_b, pad: float):
        self.ta, self.tb = np.asarray(ta, np.int64), np.asarray(tb, np.int64)
        self.pad = float(pad)
        p = len(self.ta)
        nrm = np.cross(eu, ev)
        nrm /= np.linalg.norm(nrm, axis=1)[:, None]
        g11, g12, g22 = (np.einsum("ij,ij->i", x, y) for x, y in ((eu, eu), (eu, ev), (ev, ev)))
        det = (g11 * g22 - g12 * g12)[:, None]
        a = (g22[:, None] * eu - g12[:, None] * ev) / det          # u = a.(p - q0)
        b = (g11[:, None] * ev - g12[:, None] * eu) / det          # v = b.(p - q0)
        la, lb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
        units, sign = _canonical(np.concatenate([nrm, a / la[:, None], b / lb[:, None]]))
        self.dirs, inv = np.unique(units.reshape(-1, 3), axis=0, return_inverse=True)
        self.kn, self.ka, self.kb = np.asarray(inv).reshape(3, p)
        sn, sa, sb = sign.reshape(3, p)
        eye = np.abs(self.dirs) == 1.0
        self.axis = np.argmax(eye, axis=1) if eye.any(axis=1).all() else None
        # plane dir_n.x = cn; u - 1/2 = lam_a (dir_a.x - ma), inside when |dir_a.x - ma| <= ha
        self.nrm, self.c = nrm, np.einsum("ij,ij->i", nrm, q0)     # plane nrm.x = c
        self.cn = sn * self.c
        self.lam_a, self.lam_b = sa * la, sb * lb
        self.ma = (np.einsum("ij,ij->i", a, q0) + 0.5) / self.lam_a
        self.mb = (np.einsum("ij,ij->i", b, q0) + 0.5) / self.lam_b
        self.ha = (0.5 + BARY_EPS) / la
        self.hb = (0.5 + BARY_EPS) / lb
        corners = np.stack([q0, q0 + eu, q0 + ev, q0 + eu + ev])
        self.lo, self.hi = corners.min(axis=0) - pad, corners.max(axis=0) + pad
        # rows 2 q + half (0: ta, 1: tb): b1, b2 = row[0:3], row[3:6] . (1, u, v)
        maps = np.stack([_bary_map(a, b, q0, c) for c in (corners_a, corners_b)])
        self.bary = np.ascontiguousarray(maps.transpose(3, 0, 1, 2).reshape(2 * p, 6))

    def __len__(self) -> int:
        return len(self.ta)

    def _apart(self, pk: Packets, q, pkt) -> np.ndarray:
        """(K,) bool for pairs (quad q, packet pkt) of a packet bounded from an apex: every
        origin of the packet lies more than ``pad`` off the quad's plane, on the side of the
        apex, which lies more than apex pad + ``pad`` off it, so that no segment of the packet
        crosses the plane (the plane test's rounding is far below ``pad``)."""
        mid, half = 0.5 * (pk.o0 + pk.o1), 0.5 * (pk.o1 - pk.o0)
        nq = self.nrm[q]
        dc = (nq[:, 0] * mid[0, pkt] + nq[:, 1] * mid[1, pkt] + nq[:, 2] * mid[2, pkt]
              - self.c[q])
        rad = (np.abs(nq[:, 0]) * half[0, pkt] + np.abs(nq[:, 1]) * half[1, pkt]
               + np.abs(nq[:, 2]) * half[2, pkt])
        side = (self.nrm * pk.point).sum(axis=1)[q] - self.c[q]    # no BLAS call
        far = pk.pad + self.pad
        return ((side > far) & (dc - rad > self.pad)) | ((side < -far) & (dc + rad < -self.pad))

    def _candidates(self, pk: Packets):
        """Pairs (packet, quad) whose rays may cross, grouped by packet, with the lower bound
        of their crossing t."""
        cand, entry = pk.meets(self.lo, self.hi)
        pkt, q = np.nonzero(cand.T)
        if pk.toward:
            keep = ~self._apart(pk, q, pkt)
            pkt, q = pkt[keep], q[keep]
        return pkt, q, entry[q, pkt]

    def _test(self, pk: Packets, pkt, q):
        """Lanes' crossing t of pairs (packet pkt, quad q) (inf for a miss), u - 1/2 and
        v - 1/2 over lam_a, lam_b, each (K, lanes)."""
        kn, ka, kb = self.kn[q], self.ka[q], self.kb[q]
        dots = lambda k, which: pk.dots(self.dirs, self.axis, k, pkt, which)
        dn = dots(kn, "d")
        with np.errstate(divide="ignore", invalid="ignore"):
            t = self.cn[q, None] - dots(kn, "o")
            t /= dn
            u = dots(ka, "d")
            u *= t
            u += dots(ka, "o")
            u -= self.ma[q, None]
            v = dots(kb, "d")
            v *= t
            v += dots(kb, "o")
            v -= self.mb[q, None]
            bad = np.abs(dn) <= PARALLEL_EPS       # a parallel ray's t, u, v may be NaN
            bad |= t < pk.tmin[pkt]
            bad |= t > pk.tmax[pkt]
            bad |= np.abs(u) > self.ha[q, None]
            bad |= np.abs(v) > self.hb[q, None]
        t[bad] = np.inf
        return t, u, v

    def closest(self, pk: Packets):
        """(t, tri, b1, b2) per ray: the nearest quad hit in each ray's [tmin, tmax], its
        triangle and barycentrics there (inf / -1 / 0 where none); equal t goes to the lower
        triangle index. Each packet first tests the quad it may reach first, then only the
        quads it may reach before its farthest hit so far (what that quad hides is skipped)."""
        pkt, q, entry = self._candidates(pk)
        m, lanes = pk.npk * pk.lanes, pk.lanes
        best = np.full((pk.npk, lanes), np.inf)
        tri = np.full(m, NO_TRI)
        b1, b2 = np.zeros(m), np.zeros(m)
        if len(pkt) == 0:
            return best.reshape(-1)[:pk.n], np.full(pk.n, -1), b1[:pk.n], b2[:pk.n]
        order = np.lexsort((entry, pkt))                    # per packet, nearest entry first
        first = np.zeros(len(pkt), bool)
        first[order[np.r_[True, pkt[order][1:] != pkt[order][:-1]]]] = True
        one = np.flatnonzero(first)                         # one pair per packet
        t1, u1, v1 = self._test(pk, pkt[one], q[one])
        best[pkt[one]] = t1
        far = best.max(axis=1)
        two = np.flatnonzero(~first & (entry <= far[pkt]))
        pkt, q = np.concatenate([pkt[one], pkt[two]]), np.concatenate([q[one], q[two]])
        t, u, v = t1, u1, v1
        if len(two):
            t2, u2, v2 = self._test(pk, pkt[len(one):], q[len(one):])
            t, u, v = np.concatenate([t1, t2]), np.concatenate([u1, u2]), np.concatenate([v1, v2])
            pos2 = (pkt[len(one):] * lanes)[:, None] + np.arange(lanes)
            np.minimum.at(best.reshape(-1), pos2.reshape(-1), t2.reshape(-1))
        k, lane = np.nonzero((t == best[pkt]) & (t < np.inf))
        qk, at = q[k], pkt[k] * lanes + lane
        uu = self.lam_a[qk] * u[k, lane] + 0.5                 # quad coordinates
        vv = self.lam_b[qk] * v[k, lane] + 0.5
        half = np.where(uu > vv, 0, np.where(uu < vv, 1, (self.tb[qk] < self.ta[qk])))
        tk = np.where(half == 0, self.ta[qk], self.tb[qk])
        np.minimum.at(tri, at, tk)
        win = np.flatnonzero(tk == tri[at])     # one per ray: ties on one quad and half
        mp = self.bary.take(2 * qk[win] + half[win], axis=0).T   # (6, w)
        uw, vw = uu[win], vv[win]
        b1[at[win]] = mp[0] + mp[1] * uw + mp[2] * vw
        b2[at[win]] = mp[3] + mp[4] * uw + mp[5] * vw
        tri[tri == NO_TRI] = -1
        return best.reshape(-1)[:pk.n], tri[:pk.n], b1[:pk.n], b2[:pk.n]

    def any_hit(self, pk: Packets) -> np.ndarray:
        """(n,) bool: does some quad cross each ray within [tmin, tmax]."""
        pkt, q, _ = self._candidates(pk)
        t, _, _ = self._test(pk, pkt, q)
        k, lane = np.nonzero(t < np.inf)
        out = np.zeros(pk.npk * pk.lanes, bool)
        out[pkt[k] * pk.lanes + lane] = True
        return out[:pk.n]
