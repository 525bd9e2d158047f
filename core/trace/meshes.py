"""Triangle meshes of the environment: closest hit and any-hit (shadow rays) for ray arrays.

All meshes are concatenated into one triangle set. The ray-triangle test is Moller-Trumbore in
float64, with triangles grown by BARY_EPS in barycentric units so that a ray through an edge or
vertex shared by neighbouring triangles hits at least one of them, and triangle boxes padded so
that culling by boxes never drops a candidate under rounding.

Tiers, chosen by the set's size:
- *quads* (trace/planar.py): parallelograms that two triangles form, tested against packets of
  consecutive rays; all of them in a small set (up to SMALL_SET triangles: a room and its
  furniture), else only the largest (BIG_FRACTION, MAX_PLANES: the walls around a big mesh);
- a BVH (trace/bvh.py) over the other triangles, which each ray walks only up to its quad hit;
- for segments that end at a given point (shadow rays toward a point light), an apex grid
  (trace/apexgrid.py) over those other triangles instead of the BVH.
A quad hit's t and barycentrics come from the quad's plane and parallelogram coordinates
(Moller-Trumbore's on its triangle to rounding: ~1e-16 relative), other hits are
Moller-Trumbore's; equal t goes to the lower triangle index in every tier.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scene.model import Mesh
from .apexgrid import ApexGrid, GridTooLarge
from .boxes import slab_intervals
from .bvh import BVH
from .planar import BARY_EPS, PARALLEL_EPS, Packets, QuadSet, parallelograms

BOX_PAD = 1e-9          # fraction of the scene's bounding-box diagonal added around each
                        # triangle box, so that culling by boxes is conservative under rounding
RAY_CHUNK = 16384        # rays per chunk: bounds the (ray, triangle) and packet arrays (~L2 size)
LEAF_SIZE = 4           # triangles per BVH leaf
SMALL_SET = 512         # a set of at most this many triangles tests all its parallelograms as
                        # quads: a few hundred quads cost less per packet than a BVH walk per ray
# In a larger set, a parallelogram whose box diagonal is at least this fraction of the set's
# diagonal is a quad: such faces are met by a large share of all rays, where the BVH would walk
# several nodes to reach them.
BIG_FRACTION = 0.25
MAX_PLANES = 16         # most parallelograms tested as quads in a larger set (the largest)


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


class MeshSet:
    """The union of a list of ``Mesh`` with a BVH over its triangles. ``corner_normals``:
    optionally, per mesh, its unit normal at every triangle corner (m, 3, 3) or None: a mesh
    with them is smooth, shaded by their blend (custom split normals), instead of by its
    smooth flag."""

    def __init__(self, meshes: list[Mesh], corner_normals: list | None = None):
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
        # per triangle and corner, as columns (corner, axis, triangle): gathered per hit
        corner = lambda a: np.ascontiguousarray(a[self.faces].transpose(1, 2, 0))
        self._corner_xyz = corner(self.vertices)
        self._corner_nrm = corner(self.vertex_normals)
        self._set_corner_normals(corner_normals)
        self._corner_uv = corner(self.uvs)
        self._geo_t = np.ascontiguousarray(self.geo_normal.T)
        self._v0 = np.ascontiguousarray(v0.T)
        self._e1 = np.ascontiguousarray(e1.T)
        self._e2 = np.ascontiguousarray(e2.T)
        lo = np.minimum(np.minimum(v0, v1), v2)
        hi = np.maximum(np.maximum(v0, v1), v2)
        diag = float(np.linalg.norm(hi.max(0) - lo.min(0))) if len(lo) else 0.0
        pad = BOX_PAD * max(diag, 1.0)
        self.pad = pad
        self.bvh = BVH.build(lo - pad, hi + pad, LEAF_SIZE)
        self._build_tiers(lo, hi, pad, diag)

    def _set_corner_normals(self, corner_normals):
        """Smooth the triangles of the meshes given corner normals, shaded by those."""
        if corner_normals is None:
            return
        if len(corner_normals) != len(self.meshes):
            raise ValueError(f"corner_normals: one entry per mesh ({len(self.meshes)}), got "
                             f"{len(corner_normals)}")
        for k, cn in enumerate(corner_normals):
            if cn is None:
                continue
            rows = np.flatnonzero(self.tri_mesh == k)
            cn = np.asarray(cn, dtype=np.float64)
            if cn.shape != (len(rows), 3, 3):
                raise ValueError(f"mesh {self.meshes[k].name!r}: corner normals must be "
                                 f"({len(rows)}, 3, 3), got {cn.shape}")
            self._corner_nrm[:, :, rows] = cn.transpose(1, 2, 0)
            self.tri_smooth[rows] = True

    def _build_tiers(self, lo, hi, pad, diag):
        """The quads (see the module docstring) and the BVH over the other triangles."""
        m = self.num_triangles
        if m <= SMALL_SET:
            cand = np.arange(m)
        else:   # a parallelogram's triangle spans at least half its box diagonal
            cand = np.flatnonzero(np.linalg.norm(hi - lo, axis=1) >= 0.5 * BIG_FRACTION * diag)
        ta, tb, q0, eu, ev = parallelograms(self.vertices, self.faces, cand)
        if m > SMALL_SET:
            qsize = np.linalg.norm(np.abs(eu) + np.abs(ev), axis=1)     # box diagonal
            sel = np.flatnonzero(qsize >= BIG_FRACTION * diag)
            sel = sel[np.argsort(-qsize[sel], kind="stable")[:MAX_PLANES]]
            ta, tb, q0, eu, ev = ta[sel], tb[sel], q0[sel], eu[sel], ev[sel]
        corners = lambda t: self.vertices[self.faces[t]]
        self.quads = QuadSet(ta, tb, q0, eu, ev, corners(ta), corners(tb), pad) if len(ta) \
            else None
        rest = np.ones(m, bool)
        rest[ta] = rest[tb] = False
        self._rest = np.flatnonzero(rest)                           # BVH tier triangle ids
        r_lo, r_hi = lo[rest] - pad, hi[rest] + pad
        self._rest_bvh = self.bvh if rest.all() else BVH.build(r_lo, r_hi, LEAF_SIZE)
        self._rest_box = (r_lo.min(0), r_hi.max(0)) if rest.any() else None
        self._grids = {}                                            # (apex, pad) -> ApexGrid

    @property
    def num_triangles(self) -> int:
        return int(self.faces.shape[0])

    @property
    def num_quads(self) -> int:
        """Parallelograms tested as quads against packets of rays."""
        return 0 if self.quads is None else len(self.quads)

    def _solve(self, o, d, r, p):
        """Moller-Trumbore on pairs (ray r, triangle p); o, d (3, N); r None: ray i is pair i.
        Returns (det_ok, t, b1, b2), whatever the barycentrics and t."""
        if r is not None:
            o, d = (o[0][r], o[1][r], o[2][r]), (d[0][r], d[1][r], d[2][r])
        dx, dy, dz = d
        ax, ay, az = self._e1[0][p], self._e1[1][p], self._e1[2][p]
        bx, by, bz = self._e2[0][p], self._e2[1][p], self._e2[2][p]
        px = dy * bz - dz * by
        py = dz * bx - dx * bz
        pz = dx * by - dy * bx
        det = ax * px + ay * py + az * pz
        ok = np.abs(det) > PARALLEL_EPS * self.area2[p]
        inv = 1.0 / np.where(ok, det, 1.0)
        sx = o[0] - self._v0[0][p]
        sy = o[1] - self._v0[1][p]
        sz = o[2] - self._v0[2][p]
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
        t and barycentrics, Moller-Trumbore's on that triangle; equal t goes to the lower
        triangle index. Rays in a coherent order (neighbours next to each other) are fastest."""
        origins, dirs, tmin, tmax, n = self._prep(origins, dirs, tmin, tmax)
        t = np.full(n, np.inf)
        tri = np.full(n, -1, dtype=np.int64)
        b1, b2 = np.zeros(n), np.zeros(n)
        for c0 in range(0, n, RAY_CHUNK):
            sl = slice(c0, min(n, c0 + RAY_CHUNK))
            o, d, t0, t1 = origins[sl], dirs[sl], tmin[sl], tmax[sl]
            if self.quads is not None:
                t[sl], tri[sl], b1[sl], b2[sl] = self.quads.closest(
                    Packets(np.ascontiguousarray(o.T), np.ascontiguousarray(d.T), t0, t1))
            if len(self._rest) == 0:
                continue
            qt, qtri = t[sl], tri[sl]
            bt, btri = self._rest_closest(o, d, t0, np.minimum(t1, qt))
            idx = np.flatnonzero((btri >= 0) & ((bt < qt) | (btri < qtri)))   # bt <= qt
            _, th, b1h, b2h = self._solve(np.ascontiguousarray(o[idx].T),
                                          np.ascontiguousarray(d[idx].T), None, btri[idx])
            t[c0 + idx], tri[c0 + idx], b1[c0 + idx], b2[c0 + idx] = th, btri[idx], b1h, b2h
        return RayHits(t, tri, b1, b2)

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

    def surface(self, tri, b1, b2):
        """(point, geo_normal, normal), each (3, k), at barycentrics (b1, b2) of triangles
        ``tri`` (k,) (all hit): columns, so per-point arithmetic runs over whole rows."""
        w = (1.0 - b1 - b2, b1, b2)
        tv = self._corner_xyz.take(tri, axis=2)                     # (corner, axis, k)
        point = w[0] * tv[0] + w[1] * tv[1] + w[2] * tv[2]
        geo = self._geo_t.take(tri, axis=1)
        nrm = geo
        sm = np.flatnonzero(self.tri_smooth[tri])
        if len(sm):
            vn = self._corner_nrm.take(tri[sm], axis=2)
            ns = w[0][sm] * vn[0] + w[1][sm] * vn[1] + w[2][sm] * vn[2]
            ln = np.sqrt(ns[0] * ns[0] + ns[1] * ns[1] + ns[2] * ns[2])
            good = ln > 0
            nrm = geo.copy()
            nrm[:, sm[good]] = ns[:, good] / ln[good]
        return point, geo, nrm

    def uv_at(self, tri, b1, b2) -> np.ndarray:
        """(2, k) interpolated UVs at barycentrics (b1, b2) of triangles ``tri`` (k,)."""
        t = self._corner_uv.take(tri, axis=2)
        return (1.0 - b1 - b2) * t[0] + b1 * t[1] + b2 * t[2]

    def record(self, hits: RayHits) -> MeshHit:
        """The surface at each hit: point, normals, uv and mesh."""
        t, tri = hits.t, hits.tri
        n = len(t)
        hit = tri >= 0
        idx = np.flatnonzero(hit)
        p, b1, b2 = tri[idx], hits.b1[idx], hits.b2[idx]
        point, geo, nrm, uv = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 2))
        point[idx], geo[idx], nrm[idx] = (a.T for a in self.surface(p, b1, b2))
        uv[idx] = self.uv_at(p, b1, b2).T
        mesh = np.full(n, -1, dtype=np.int64)
        mesh[idx] = self.tri_mesh[p]
        return MeshHit(hit=hit, t=t, tri=tri, mesh=mesh, b1=hits.b1, b2=hits.b2, point=point,
                       geo_normal=geo, normal=nrm, uv=uv)

    def any_hit(self, origins, dirs, tmin=None, tmax=None, apex=None,
                apex_pad: float = 0.0) -> np.ndarray:
        """(N,) bool: does the segment [tmin (default 0), tmax (default inf)] hit a triangle.
        ``apex`` (3,): a point the segments end at, within ``apex_pad`` (shadow rays toward a
        point light): packets are then bounded from it and the triangles off the quads found
        in an apex grid (built once per apex and pad, see ``prepare_apex``); segments that do
        not end there (or start before t = 0) are tested as without an apex."""
        origins, dirs, tmin, tmax, n = self._prep(origins, dirs, tmin, tmax)
        apex = None if apex is None else np.asarray(apex, dtype=np.float64)
        out = np.zeros(n, dtype=bool)
        for c0 in range(0, n, RAY_CHUNK):
            sl = slice(c0, min(n, c0 + RAY_CHUNK))
            ot, dt = np.ascontiguousarray(origins[sl].T), np.ascontiguousarray(dirs[sl].T)
            t0, t1 = tmin[sl], tmax[sl]
            if apex is None:
                out[sl] = self._any_cols(ot, dt, t0, t1, None, 0.0)
                continue
            with np.errstate(invalid="ignore"):      # inf * 0 for endless segments
                e = [ot[i] + t1 * dt[i] - apex[i] for i in range(3)]
            ends = (e[0] * e[0] + e[1] * e[1] + e[2] * e[2] <= apex_pad * apex_pad) & (t0 >= 0)
            if ends.all():
                out[sl] = self._any_cols(ot, dt, t0, t1, apex, apex_pad)
                continue
            for rows, a in ((np.flatnonzero(ends), apex), (np.flatnonzero(~ends), None)):
                out[c0 + rows] = self._any_cols(ot.take(rows, axis=1), dt.take(rows, axis=1),
                                                t0[rows], t1[rows], a, apex_pad)
        return out

    def _any_cols(self, ot, dt, tmin, tmax, apex, apex_pad):
        """``any_hit`` of segments given as columns ot, dt (3, k)."""
        out = (self.quads.any_hit(Packets(ot, dt, tmin, tmax, apex, apex_pad))
               if self.quads is not None else np.zeros(ot.shape[1], bool))
        if len(self._rest) == 0 or out.all():
            return out
        if self.quads is None:
            return self._rest_any(ot, dt, tmin, tmax, apex, apex_pad)
        free = np.flatnonzero(~out)
        out[free] = self._rest_any(ot.take(free, axis=1), dt.take(free, axis=1), tmin[free],
                                   tmax[free], apex, apex_pad)
        return out

    def prepare_apex(self, apex, apex_pad: float) -> ApexGrid | None:
        """The apex grid of the non-quad triangles for segments ending within ``apex_pad`` of
        ``apex`` (built on first use; None where it would be too large: the BVH serves)."""
        key = (tuple(float(x) for x in apex), float(apex_pad))
        if key not in self._grids:
            try:
                tris = self.vertices[self.faces[self._rest]]
                self._grids[key] = ApexGrid(apex, tris, self._rest, apex_pad + self.pad)
            except GridTooLarge:
                self._grids[key] = None
        return self._grids[key]

    def _rest_any(self, ot, dt, tmin, tmax, apex, apex_pad):
        """(k,) bool: does a non-quad triangle cross each segment (columns ot, dt (3, k); all
        ending within ``apex_pad`` of ``apex`` where it is given)."""
        hit_fn = lambda r, p: self._intersect(ot, dt, tmin, tmax, r, p)[0]
        grid = self.prepare_apex(apex, apex_pad) if apex is not None else None
        if grid is not None:
            return grid.any_hit(ot - grid.apex[:, None], hit_fn)
        out = np.zeros(ot.shape[1], bool)
        o, d = ot.T, dt.T
        idx = self._rest_rays(o, d, tmin, tmax)
        if len(idx):
            rest = self._rest
            out[idx] = self._rest_bvh.any_hit(o[idx], d[idx], tmin[idx], tmax[idx],
                                              lambda r, q: hit_fn(idx[r], rest[q]))
        return out
