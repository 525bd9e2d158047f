"""Triangle meshes of the environment: closest hit and any-hit (shadow rays) for ray arrays.

All meshes are concatenated into one triangle set. The ray-triangle test is Moller-Trumbore in
float64, with triangles grown by BARY_EPS in barycentric units so that a ray through an edge or
vertex shared by neighbouring triangles hits at least one of them, and triangle boxes padded so
that slab-test rounding never drops a candidate.

Two tiers: *planes*, the few large parallelograms that two triangles of a mesh form (a room's
walls and floor), are tested against every ray at once as one matrix product and a rectangle
check (BIG_FRACTION, MAX_PLANES); the other triangles sit in a BVH that each ray walks only up
to its nearest plane hit. Every reported hit (t, barycentrics) is Moller-Trumbore's on the
triangle found, so the tiers change which work is done, not the arithmetic of a hit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scene.model import Mesh
from .boxes import slab_intervals
from .bvh import BVH

BARY_EPS = 1e-10        # barycentric units: closes rounding gaps along shared edges/vertices
PARALLEL_EPS = 1e-12    # |cos(ray, plane normal)| below which a ray counts as parallel: no hit
BOX_PAD = 1e-9          # fraction of the scene's bounding-box diagonal added around each
                        # triangle box, so the BVH slab test is conservative under rounding
RAY_CHUNK = 16384       # rays per traversal chunk: bounds the (ray, triangle) pair arrays
LEAF_SIZE = 4           # triangles per BVH leaf
# A parallelogram whose box diagonal is at least this fraction of the set's diagonal is tested
# as a plane against every ray (one array op per chunk): such faces are met by a large share of
# all rays, where the BVH would walk several nodes to reach them.
BIG_FRACTION = 0.25
MAX_PLANES = 16         # most parallelograms tested as planes (the largest): each costs about
                        # 20 array ops per ray, a BVH walk of a room about 25 (ray, node) pairs
QUAD_TOL = 1e-12        # |x + y - s1 - s2| / |s2 - s1| of two triangles (s1, x, s2), (s1, s2, y)
                        # below which they form a parallelogram (rounding of exact corners)
PAIR_ROUNDS = 3         # rounds of the pairing of triangles into parallelograms (a triangle can
                        # pair with up to 3 neighbours; leftovers stay triangles in the BVH)


@dataclass
class RayHits:
    """Closest hits of N rays: which triangle and where on it (t inf, tri -1 on a miss)."""

    t: np.ndarray            # (N,) distance along the ray (unit dirs: metres)
    tri: np.ndarray          # (N,) int64, index into the concatenated triangles
    b1: np.ndarray           # (N,) barycentric weight of vertex 1 (0 on a miss)
    b2: np.ndarray           # (N,) barycentric weight of vertex 2 (0 on a miss)

    @property
    def hit(self) -> np.ndarray:
        return self.tri >= 0

    def take(self, idx) -> "RayHits":
        """The hits of rays ``idx`` (an index array or a mask)."""
        return RayHits(self.t[idx], self.tri[idx], self.b1[idx], self.b2[idx])


@dataclass
class MeshHit:
    """Closest hits of N rays; fields of missed rays are 0 (t is inf, tri and mesh are -1).
    geo_normal is the unit winding normal (v1-v0)x(v2-v0); normal the shading normal (smooth
    meshes: interpolated vertex normals); neither is flipped towards the ray."""

    hit: np.ndarray          # (N,) bool
    t: np.ndarray            # (N,)
    tri: np.ndarray          # (N,) int64, index into the concatenated triangles
    mesh: np.ndarray         # (N,) int64, index into the MeshSet's mesh list
    b1: np.ndarray           # (N,) barycentric weight of vertex 1
    b2: np.ndarray           # (N,) barycentric weight of vertex 2
    point: np.ndarray        # (N, 3)
    geo_normal: np.ndarray   # (N, 3)
    normal: np.ndarray       # (N, 3)
    uv: np.ndarray           # (N, 2), zeros for meshes without UVs


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


class MeshSet:
    """The union of a list of ``Mesh`` with a BVH over its triangles."""

    def __init__(self, meshes: list[Mesh]):
        self.meshes = list(meshes)
        verts, faces, uvs, tri_mesh, smooth = [], [], [], [], []
        base = 0
        for k, m in enumerate(self.meshes):
            v = np.asarray(m.vertices, dtype=np.float64)
            f = np.asarray(m.triangles)
            if v.ndim != 2 or v.shape[1] != 3 or not np.isfinite(v).all():
                raise ValueError(f"mesh {m.name!r}: vertices must be a finite (n, 3) array")
            if f.ndim != 2 or f.shape[1] != 3 or (f.size and (f.min() < 0 or f.max() >= len(v))):
                raise ValueError(f"mesh {m.name!r}: triangles must be (m, 3) vertex indices "
                                 f"in [0, {len(v)})")
            if m.uvs is not None:
                uv = np.asarray(m.uvs, dtype=np.float64)
                if uv.shape != (len(v), 2):
                    raise ValueError(f"mesh {m.name!r}: uvs must be ({len(v)}, 2), "
                                     f"got {uv.shape}")
            else:
                uv = np.zeros((len(v), 2))
            verts.append(v)
            faces.append(f.astype(np.int64) + base)
            uvs.append(uv)
            tri_mesh.append(np.full(len(f), k, dtype=np.int64))
            smooth.append(np.full(len(f), bool(m.smooth)))
            base += len(v)
        cat = lambda parts, shape, dt: (np.concatenate(parts).astype(dt) if parts
                                        else np.zeros(shape, dtype=dt))
        self.vertices = cat(verts, (0, 3), np.float64)
        self.faces = cat(faces, (0, 3), np.int64)
        self.uvs = cat(uvs, (0, 2), np.float64)
        self.tri_mesh = cat(tri_mesh, (0,), np.int64)
        v0, v1, v2 = (self.vertices[self.faces[:, i]] for i in range(3))
        e1, e2 = v1 - v0, v2 - v0
        n = np.cross(e1, e2)
        self.area2 = np.linalg.norm(n, axis=1)                     # |e1 x e2|
        self.geo_normal = n / np.where(self.area2 > 0, self.area2, 1.0)[:, None]
        # per-vertex normals (smooth meshes): unit face normals weighted by the corner angle,
        # as Blender computes them
        corners = (v0, v1, v2)
        vn = np.zeros((len(self.vertices), 3))
        for i in range(3):
            a = corners[(i + 1) % 3] - corners[i]
            b = corners[(i + 2) % 3] - corners[i]
            ang = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))
            w = self.geo_normal * ang[:, None]
            for ax in range(3):
                vn[:, ax] += np.bincount(self.faces[:, i], w[:, ax], minlength=len(vn))
        vn_len = np.linalg.norm(vn, axis=1)
        self.vertex_normals = vn / np.where(vn_len > 0, vn_len, 1.0)[:, None]
        self.tri_smooth = cat(smooth, (0,), bool)
        self._v0 = np.ascontiguousarray(v0.T)
        self._e1 = np.ascontiguousarray(e1.T)
        self._e2 = np.ascontiguousarray(e2.T)
        lo = np.minimum(np.minimum(v0, v1), v2)
        hi = np.maximum(np.maximum(v0, v1), v2)
        diag = float(np.linalg.norm(hi.max(0) - lo.min(0))) if len(lo) else 0.0
        pad = BOX_PAD * max(diag, 1.0)
        self.bvh = BVH.build(lo - pad, hi + pad, LEAF_SIZE)
        self._build_planes(lo, hi, pad, diag)

    def _build_planes(self, lo, hi, pad, diag):
        """The plane tier (see the module docstring) and the BVH over the other triangles."""
        size = np.linalg.norm(hi - lo, axis=1)
        # a parallelogram's triangle spans at least half its box diagonal
        big = np.flatnonzero(size >= 0.5 * BIG_FRACTION * diag) if diag > 0 else np.zeros(0, int)
        ta, tb, q0, eu, ev = parallelograms(self.vertices, self.faces, big)
        qsize = np.linalg.norm(np.abs(eu) + np.abs(ev), axis=1)     # box diagonal
        sel = np.flatnonzero(qsize >= BIG_FRACTION * diag)
        sel = sel[np.argsort(-qsize[sel], kind="stable")[:MAX_PLANES]]
        ta, tb, q0, eu, ev = ta[sel], tb[sel], q0[sel], eu[sel], ev[sel]
        n = np.cross(eu, ev)
        n /= np.linalg.norm(n, axis=1)[:, None]
        g11, g12, g22 = (np.einsum("ij,ij->i", p, q) for p, q in ((eu, eu), (eu, ev), (ev, ev)))
        det = (g11 * g22 - g12 * g12)[:, None]
        a = (g22[:, None] * eu - g12[:, None] * ev) / det          # dual basis: u = a.(p - q0)
        b = (g11[:, None] * ev - g12[:, None] * eu) / det          # v = b.(p - q0)
        w = np.concatenate([n, a, b])                               # (3P, 3)
        self._plane_wd = w
        self._plane_wo = np.concatenate([-n, a, b])
        half = np.repeat([0.0, 0.5, 0.5], len(n))
        self._plane_c = np.einsum("ij,ij->i", self._plane_wo, np.concatenate([q0, q0, q0])) + half
        self._plane_tri = np.stack([ta, tb])                        # (2, P): u >= v, u < v
        rest = np.ones(self.num_triangles, bool)
        rest[ta] = rest[tb] = False
        self._rest = np.flatnonzero(rest)                           # BVH tier triangle ids
        self._rest_bvh = (self.bvh if rest.all() else
                          BVH.build(lo[rest] - pad, hi[rest] + pad, LEAF_SIZE))
        r_lo, r_hi = lo[rest] - pad, hi[rest] + pad
        self._rest_box = ((r_lo.min(0), r_hi.max(0)) if len(r_lo) else None)

    @property
    def num_triangles(self) -> int:
        return int(self.faces.shape[0])

    @property
    def num_planes(self) -> int:
        """Parallelograms tested as planes."""
        return int(self._plane_tri.shape[1])

    def _solve(self, o, d, r, p):
        """Moller-Trumbore on pairs (ray r, triangle p); o, d (3, N). Returns (det_ok, t, b1,
        b2), whatever the barycentrics and t."""
        dx, dy, dz = d[0][r], d[1][r], d[2][r]
        ax, ay, az = self._e1[0][p], self._e1[1][p], self._e1[2][p]
        bx, by, bz = self._e2[0][p], self._e2[1][p], self._e2[2][p]
        px = dy * bz - dz * by
        py = dz * bx - dx * bz
        pz = dx * by - dy * bx
        det = ax * px + ay * py + az * pz
        ok = np.abs(det) > PARALLEL_EPS * self.area2[p]
        inv = 1.0 / np.where(ok, det, 1.0)
        sx = o[0][r] - self._v0[0][p]
        sy = o[1][r] - self._v0[1][p]
        sz = o[2][r] - self._v0[2][p]
        b1 = (sx * px + sy * py + sz * pz) * inv
        qx = sy * az - sz * ay
        qy = sz * ax - sx * az
        qz = sx * ay - sy * ax
        b2 = (dx * qx + dy * qy + dz * qz) * inv
        t = (bx * qx + by * qy + bz * qz) * inv
        return ok, t, b1, b2

    def _intersect(self, o, d, tmin, tmax, r, p):
        """Moller-Trumbore on pairs (ray r, triangle p); o, d (3, N). Returns (t, b1, b2) with
        t = inf where the pair misses or the hit lies outside [tmin, tmax]."""
        ok, t, b1, b2 = self._solve(o, d, r, p)
        ok &= (b1 >= -BARY_EPS) & (b2 >= -BARY_EPS) & (b1 + b2 <= 1.0 + BARY_EPS)
        ok &= (t >= tmin[r]) & (t <= tmax[r])
        return np.where(ok, t, np.inf), b1, b2

    @staticmethod
    def _prep(origins, dirs, tmin, tmax):
        origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        n = len(origins)
        tmin = np.broadcast_to(np.asarray(0.0 if tmin is None else tmin, np.float64), (n,))
        tmax = np.broadcast_to(np.asarray(np.inf if tmax is None else tmax, np.float64), (n,))
        return origins, dirs, tmin, tmax, n

    def closest_hit(self, origins, dirs, tmin=None, tmax=None) -> MeshHit:
        """Closest hit with t in [tmin (default 0), tmax (default inf)] of each ray."""
        return self.record(self.closest(origins, dirs, tmin, tmax))

    def closest(self, origins, dirs, tmin=None, tmax=None) -> RayHits:
        """Closest hit with t in [tmin (default 0), tmax (default inf)] of each ray: triangle,
        t and barycentrics, Moller-Trumbore's on that triangle."""
        origins, dirs, tmin, tmax, n = self._prep(origins, dirs, tmin, tmax)
        t = np.full(n, np.inf)
        tri = np.full(n, -1, dtype=np.int64)
        b1, b2 = np.zeros(n), np.zeros(n)
        for c0 in range(0, n, RAY_CHUNK):
            sl = slice(c0, min(n, c0 + RAY_CHUNK))
            o, d, t0, t1 = origins[sl], dirs[sl], tmin[sl], tmax[sl]
            pt, ptri = self._planes_closest(o, d, t0, t1)
            bt, btri = self._rest_closest(o, d, t0, np.minimum(t1, pt))
            near = btri >= 0                       # a BVH hit lies at or before the plane hit
            ptri[near] = btri[near]
            idx = np.flatnonzero(ptri >= 0)
            _, th, b1h, b2h = self._solve(np.ascontiguousarray(o[idx].T),
                                          np.ascontiguousarray(d[idx].T),
                                          np.arange(len(idx)), ptri[idx])
            t[c0 + idx], tri[c0 + idx], b1[c0 + idx], b2[c0 + idx] = th, ptri[idx], b1h, b2h
        return RayHits(t, tri, b1, b2)

    def _plane_test(self, o, d, tmin, tmax):
        """(t, u, v), each (P, n): where rays o + t d cross the planes and the parallelogram
        coordinates there, less 1/2; t = inf where the crossing is outside [tmin, tmax] or the
        parallelogram (grown by BARY_EPS) or the ray runs parallel. Rows are planes, so every
        array op runs over contiguous memory."""
        p = self.num_planes
        od = self._plane_wo @ o.T
        od -= self._plane_c[:, None]                # n.(q0 - o), a.(o - q0) - 1/2, b.(...)
        dd = self._plane_wd @ d.T                   # n.d, a.d, b.d
        dn = dd[:p]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.divide(od[:p], dn, out=od[:p])
            u = np.multiply(t, dd[p:2 * p], out=dd[p:2 * p])
            u += od[p:2 * p]
            v = np.multiply(t, dd[2 * p:], out=dd[2 * p:])
            v += od[2 * p:]
            bad = np.abs(dn) <= PARALLEL_EPS        # a parallel ray's t, u, v may be NaN
            bad |= t < tmin
            bad |= t > tmax
            bad |= np.abs(u) > 0.5 + BARY_EPS
            bad |= np.abs(v) > 0.5 + BARY_EPS
        t[bad] = np.inf
        return t, u, v

    def _planes_closest(self, o, d, tmin, tmax):
        """(t, tri) of the nearest plane-tier hit per ray (inf / -1 where none)."""
        n = len(o)
        if self.num_planes == 0:
            return np.full(n, np.inf), np.full(n, -1, dtype=np.int64)
        t, u, v = self._plane_test(o, d, tmin, tmax)
        k = np.argmin(t, axis=0)
        cols = np.arange(n)
        tk = t[k, cols]
        tri = self._plane_tri[(u[k, cols] < v[k, cols]).astype(np.int64), k]
        return tk, np.where(tk < np.inf, tri, -1)

    def _rest_rays(self, o, d, tmin, tmax):
        """Indices of the rays whose segment meets the box of the BVH tier's triangles."""
        if self._rest_box is None:
            return np.zeros(0, dtype=np.int64)
        tn, tf = slab_intervals(o, d, *self._rest_box)
        return np.flatnonzero(np.maximum(tn.max(axis=1), tmin) <= np.minimum(tf.min(axis=1), tmax))

    def _rest_closest(self, o, d, tmin, tmax):
        """(t, tri) of the nearest BVH-tier hit per ray within [tmin, tmax]."""
        t = np.full(len(o), np.inf)
        tri = np.full(len(o), -1, dtype=np.int64)
        idx = self._rest_rays(o, d, tmin, tmax)
        if len(idx):
            oi, di, t0, t1 = o[idx], d[idx], tmin[idx], tmax[idx]
            ot, dt = np.ascontiguousarray(oi.T), np.ascontiguousarray(di.T)
            rest = self._rest
            t[idx], p = self._rest_bvh.closest_hit(
                oi, di, t0, t1, lambda r, q: self._intersect(ot, dt, t0, t1, r, rest[q])[0])
            tri[idx] = np.where(p >= 0, rest[np.maximum(p, 0)], -1)
        return t, tri

    def record(self, hits: RayHits) -> MeshHit:
        """The surface at each hit: point, normals, uv and mesh."""
        t, tri = hits.t, hits.tri
        n = len(t)
        hit = tri >= 0
        idx = np.flatnonzero(hit)
        p = tri[idx]
        b1h, b2h = hits.b1[idx], hits.b2[idx]
        b0h = 1.0 - b1h - b2h
        f = self.faces[p]
        w = (b0h[:, None], b1h[:, None], b2h[:, None])
        point = np.zeros((n, 3))
        point[idx] = sum(w[i] * self.vertices[f[:, i]] for i in range(3))
        geo = np.zeros((n, 3))
        geo[idx] = self.geo_normal[p]
        nrm = geo.copy()
        sm = self.tri_smooth[p]
        if sm.any():
            ns = sum(w[i][sm] * self.vertex_normals[f[sm, i]] for i in range(3))
            ln = np.linalg.norm(ns, axis=1)
            good = ln > 0
            sel = idx[sm][good]
            nrm[sel] = ns[good] / ln[good, None]
        uv = np.zeros((n, 2))
        uv[idx] = sum(w[i] * self.uvs[f[:, i]] for i in range(3))
        mesh = np.full(n, -1, dtype=np.int64)
        mesh[idx] = self.tri_mesh[p]
        return MeshHit(hit=hit, t=t, tri=tri, mesh=mesh, b1=hits.b1, b2=hits.b2, point=point,
                       geo_normal=geo, normal=nrm, uv=uv)

    def any_hit(self, origins, dirs, tmin=None, tmax=None) -> np.ndarray:
        """(N,) bool: does the segment [tmin (default 0), tmax (default inf)] hit a triangle.
        A ray leaves the BVH walk at its first hit; rays a plane blocks do not walk it."""
        origins, dirs, tmin, tmax, n = self._prep(origins, dirs, tmin, tmax)
        out = np.zeros(n, dtype=bool)
        for c0 in range(0, n, RAY_CHUNK):
            sl = slice(c0, min(n, c0 + RAY_CHUNK))
            o, d, t0, t1 = origins[sl], dirs[sl], tmin[sl], tmax[sl]
            blocked = self._planes_any(o, d, t0, t1)
            free = np.flatnonzero(~blocked)
            idx = free[self._rest_rays(o[free], d[free], t0[free], t1[free])]
            if len(idx):
                oi, di, a, b = o[idx], d[idx], t0[idx], t1[idx]
                ot, dt = np.ascontiguousarray(oi.T), np.ascontiguousarray(di.T)
                rest = self._rest
                blocked[idx] = self._rest_bvh.any_hit(
                    oi, di, a, b, lambda r, q: self._intersect(ot, dt, a, b, r, rest[q])[0])
            out[sl] = blocked
        return out

    def _planes_any(self, o, d, tmin, tmax):
        """(n,) bool: does some plane-tier parallelogram cross each segment. Only rays with a
        plane whose sides hold both segment ends differently (or one on it) are tested in
        full."""
        n = len(o)
        if self.num_planes == 0:
            return np.zeros(n, bool)
        p = self.num_planes
        with np.errstate(invalid="ignore"):
            dn = self._plane_wd[:p] @ d.T
            side = self._plane_wo[:p] @ o.T - self._plane_c[:p, None]    # n.(q0 - o)
            s0 = tmin * dn - side                   # signed plane distance at both ends
            s1 = tmax * dn - side                   # (inf for an endless segment)
            same = (s0 > 0) & (s1 > 0) | (s0 < 0) & (s1 < 0)
        rows = np.flatnonzero(~same.all(axis=0))
        out = np.zeros(n, bool)
        if len(rows):
            t, _, _ = self._plane_test(o[rows], d[rows], tmin[rows], tmax[rows])
            out[rows] = (t < np.inf).any(axis=0)
        return out
