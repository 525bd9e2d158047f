"""Triangle meshes of the environment: closest hit and any-hit (shadow rays) for ray arrays.

All meshes are concatenated into one triangle set with one BVH. The ray-triangle test is
Moller-Trumbore in float64, with triangles grown by BARY_EPS in barycentric units so that a ray
through an edge or vertex shared by neighbouring triangles hits at least one of them, and
triangle boxes padded so that slab-test rounding never drops a candidate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scene.model import Mesh
from .bvh import BVH

BARY_EPS = 1e-10        # barycentric units: closes rounding gaps along shared edges/vertices
PARALLEL_EPS = 1e-12    # |cos(ray, plane normal)| below which a ray counts as parallel: no hit
BOX_PAD = 1e-9          # fraction of the scene's bounding-box diagonal added around each
                        # triangle box, so the BVH slab test is conservative under rounding
RAY_CHUNK = 16384       # rays per traversal chunk: bounds the (ray, triangle) pair arrays
LEAF_SIZE = 4           # triangles per BVH leaf


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

    @property
    def num_triangles(self) -> int:
        return int(self.faces.shape[0])

    def _intersect(self, o, d, tmin, tmax, r, p):
        """Moller-Trumbore on pairs (ray r, triangle p); o, d (3, N). Returns (t, b1, b2) with
        t = inf where the pair misses or the hit lies outside [tmin, tmax]."""
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
        origins, dirs, tmin, tmax, n = self._prep(origins, dirs, tmin, tmax)
        t, tri = self._closest(origins, dirs, tmin, tmax, n)
        return self._hit_record(origins, dirs, tmin, tmax, t, tri)

    def closest_t(self, origins, dirs, tmin=None, tmax=None):
        """(t (N,), tri (N,)) of the closest hits only (inf / -1 on a miss)."""
        return self._closest(*self._prep(origins, dirs, tmin, tmax))

    def _closest(self, origins, dirs, tmin, tmax, n):
        t = np.full(n, np.inf)
        tri = np.full(n, -1, dtype=np.int64)
        for sl, o, d, fn in self._chunks(origins, dirs, tmin, tmax):
            t[sl], tri[sl] = self.bvh.closest_hit(o, d, tmin[sl], tmax[sl], fn)
        return t, tri

    def _chunks(self, origins, dirs, tmin, tmax):
        """(slice, origins, dirs, hit_fn) per RAY_CHUNK rays; hit_fn(ray, tri) -> t for BVH."""
        for c0 in range(0, len(origins), RAY_CHUNK):
            sl = slice(c0, min(len(origins), c0 + RAY_CHUNK))
            o, d = origins[sl], dirs[sl]
            ot, dt = np.ascontiguousarray(o.T), np.ascontiguousarray(d.T)
            t0, t1 = tmin[sl], tmax[sl]
            yield sl, o, d, (lambda r, p: self._intersect(ot, dt, t0, t1, r, p)[0])

    def _hit_record(self, origins, dirs, tmin, tmax, t, tri) -> MeshHit:
        n = len(t)
        hit = tri >= 0
        idx = np.flatnonzero(hit)
        p = tri[idx]
        _, b1h, b2h = self._intersect(np.ascontiguousarray(origins[idx].T),
                                      np.ascontiguousarray(dirs[idx].T),
                                      tmin[idx], tmax[idx], np.arange(len(idx)), p)
        b1, b2 = np.zeros(n), np.zeros(n)
        b1[idx], b2[idx] = b1h, b2h
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
        return MeshHit(hit=hit, t=t, tri=tri, mesh=mesh, b1=b1, b2=b2, point=point,
                       geo_normal=geo, normal=nrm, uv=uv)

    def any_hit(self, origins, dirs, tmin=None, tmax=None) -> np.ndarray:
        """(N,) bool: does the segment [tmin (default 0), tmax (default inf)] hit a triangle.
        A ray stops traversing at its first hit."""
        origins, dirs, tmin, tmax, n = self._prep(origins, dirs, tmin, tmax)
        out = np.zeros(n, dtype=bool)
        for sl, o, d, fn in self._chunks(origins, dirs, tmin, tmax):
            out[sl] = self.bvh.any_hit(o, d, tmin[sl], tmax[sl], fn)
        return out
