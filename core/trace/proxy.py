"""A fine triangle proxy of the object, with its measured distance from the exact surface, for
cheap conservative tests of whether a segment between two known surface points crosses the
object in between (a triangle any-hit is a few microseconds; the exact search tens).

The tessellation covers every Bezier piece of every NURBS patch (the patch's knot spans) with
its own uniform grid, refined piece by piece until the gap between the surface and the grid at
the cells' centres and edge midpoints is within MAX_GAP_REL (mesh patches as they are).
``deviation`` bounds how far the tessellation lies from the surface: the largest such gap times
DEVIATION_SAFETY. The proxy is two shells, the tessellation moved by ``deviation`` along its
vertex normals either way, closed along the tessellation's open edges (a sheet's rim, a
piece's border) by a wall from one shell to the other: the surface lies inside, so a segment
that meets the surface meets a shell or a wall, even one grazing a convex patch that the
tessellation alone would miss or one lying in a flat patch's plane. Near a
segment's ends (which lie on the surface) a shell can be met although the surface is not: those
stretches, twice ``deviation`` over the sine of the segment's angle with the surface there, are
not tested.

Units: scene units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.nurbs import evaluate
from ..scene.model import Mesh
from .meshes import MeshSet

# Grid cells per Bezier piece side: from PIECE_CELLS, doubled (up to MAX_PIECE_CELLS) until
# the piece's measured gap is within MAX_GAP_REL of the object's diagonal: the untested end
# stretches grow with the gap.
PIECE_CELLS = 2
MAX_PIECE_CELLS = 64
MAX_GAP_REL = 2e-4
# The proxy's deviation is at least this (relative to the diagonal): a flat patch's proxy is
# exact, but a segment starting on it must not meet it at its own start (float rounding).
MIN_DEVIATION_REL = 1e-7
# The sampled gaps (cell centres, edge midpoints) under-estimate the largest one inside a cell
# by a little; doubled they bound it for the smooth patches the grid resolves.
DEVIATION_SAFETY = 2.0
# Sine of the segment's angle with the surface below which the end stretch is taken as this
# (a grazing segment's untested stretch would be most of it).
MIN_END_SINE = 0.05
# Below this sine of a segment's angle with the surface at an end, its untested stretch exceeds
# ten deviations: callers ask the exact tracer about such segments instead.
GRAZING_SINE = 0.2


@dataclass
class Proxy:
    """The proxy's triangles (both shells) and its deviation from the surface (scene units)."""

    mesh: MeshSet
    deviation: float

    @classmethod
    def of(cls, tracer) -> "Proxy":
        """The proxy of a PatchTracer's object (its Bezier pieces: ``piece_rect``,
        ``piece_patch``)."""
        meshes, gap = [], 0.0
        target = MAX_GAP_REL * tracer.diag
        for pid, p in enumerate(tracer.object.patches):
            if p.surface is None:
                meshes.append(Mesh(name=p.name, vertices=p.vertices, triangles=p.triangles,
                                   material=""))
                continue
            rects = tracer.piece_rect[tracer.piece_patch == pid]
            cells = PIECE_CELLS
            verts, tris, base = [], [], 0
            while len(rects):
                v, t, g = _piece_grids(p.surface, rects, cells)
                done = (g <= target) | (cells >= MAX_PIECE_CELLS)
                per = (cells + 1) ** 2
                for k in np.flatnonzero(done):
                    verts.append(v[k])
                    tris.append(t + base)
                    base += per
                gap = max(gap, float(g[done].max(initial=0.0)))
                rects, cells = rects[~done], cells * 2
            meshes.append(Mesh(name=p.name, vertices=np.concatenate(verts),
                               triangles=np.concatenate(tris), material=""))
        dev = max(DEVIATION_SAFETY * gap, MIN_DEVIATION_REL * tracer.diag)
        shells = []
        for m in meshes:
            shift = dev * _vertex_normals(m.vertices, m.triangles)
            shells += [Mesh(name=f"{m.name}+", vertices=m.vertices + shift,
                            triangles=m.triangles, material=""),
                       Mesh(name=f"{m.name}-", vertices=m.vertices - shift,
                            triangles=m.triangles, material=""),
                       _rim_wall(m, shift)]
        return cls(mesh=MeshSet([s for s in shells if len(s.triangles)]), deviation=dev)

    def crossed(self, start, d, length, n_start, n_end=None) -> np.ndarray:
        """(N,) bool: whether the segments from surface points ``start`` (N, 3) along unit
        ``d`` for ``length`` (N,; inf: a ray) meet the proxy away from their ends; ``n_start``
        and ``n_end`` (N, 3) are the unit surface normals at the ends (n_end unused for rays)."""
        t0 = self.end_stretch(d, n_start)
        t1 = np.asarray(length, np.float64).copy()
        fin = np.isfinite(t1)
        if n_end is not None and fin.any():
            t1[fin] -= self.end_stretch(d[fin], n_end[fin])
        out = np.zeros(len(start), bool)
        live = np.flatnonzero(t1 > t0)
        if len(live):
            out[live] = self.mesh.any_hit(start[live], d[live], t0[live], t1[live])
        return out

    def end_stretch(self, d, n) -> np.ndarray:
        """How far from a surface point a segment leaving it along ``d`` (normal ``n``) may
        still be inside the shells: twice the deviation over the sine of its angle."""
        sine = np.abs(np.einsum("ij,ij->i", d, n))
        return 2.0 * self.deviation / np.maximum(sine, MIN_END_SINE)


def _vertex_normals(v, tris) -> np.ndarray:
    """(V, 3) unit vertex normals of a triangle mesh: the area-weighted sum of its triangles'
    normals (zero where they cancel or vanish, as at a collapsed edge's degenerate cells)."""
    n = np.cross(v[tris[:, 1]] - v[tris[:, 0]], v[tris[:, 2]] - v[tris[:, 0]])
    acc = np.zeros_like(v)
    for k in range(3):
        np.add.at(acc, tris[:, k], n)
    ln = np.linalg.norm(acc, axis=1)
    return acc / np.where(ln > 0, ln, 1.0)[:, None]


def _rim_wall(m: Mesh, shift) -> Mesh:
    """The wall that closes the two shells of ``m`` (vertices moved by +-``shift`` (V, 3))
    along its open edges (those of one triangle: a sheet's rim, a piece grid's border): a ray
    that reaches the surface between the shells through the rim, as one lying in a flat
    patch's plane does, meets the wall. Two triangles per open edge."""
    tris = m.triangles.astype(np.int64)
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    lo = len(m.vertices)                  # vertex i of the lower shell is lo + i
    key, count = np.unique(edges[:, 0] * lo + edges[:, 1], return_counts=True)
    a, b = np.divmod(key[count == 1], lo)
    v = np.concatenate([m.vertices + shift, m.vertices - shift])
    walls = np.concatenate([np.stack([a, b, lo + b], axis=1), np.stack([a, lo + b, lo + a], axis=1)])
    return Mesh(name=f"{m.name}|", vertices=v, triangles=walls.astype(m.triangles.dtype),
                material="")


def _piece_grids(surf, rects, cells: int):
    """The grid tessellations of ``surf`` over parameter rectangles ``rects`` (R, 4: u0, u1,
    v0, v1) with ``cells`` cells a side: (vertices (R, V, 3), triangles (T, 3) indexing one
    rectangle's vertices, gaps (R,)); a gap is the largest distance between the surface and the
    proxy at the cells' centres (against the midpoint of the diagonal the triangles share) and
    the grid edges' midpoints."""
    r, n = len(rects), cells + 1
    f = np.linspace(0.0, 1.0, 2 * cells + 1)              # vertices at even, midpoints at odd
    uu = rects[:, 0, None] + f * (rects[:, 1] - rects[:, 0])[:, None]          # (R, 2c+1)
    vv = rects[:, 2, None] + f * (rects[:, 3] - rects[:, 2])[:, None]
    U = np.broadcast_to(uu[:, :, None], (r, 2 * cells + 1, 2 * cells + 1))
    V = np.broadcast_to(vv[:, None, :], (r, 2 * cells + 1, 2 * cells + 1))
    (pts,) = evaluate(surf, U.ravel(), V.ravel(), derivatives=0)
    fine = pts.reshape(r, 2 * cells + 1, 2 * cells + 1, 3)
    grid = fine[:, ::2, ::2]
    gaps = np.stack([
        np.linalg.norm(fine[:, 1::2, 1::2] - (grid[:, :-1, :-1] + grid[:, 1:, 1:]) / 2,
                       axis=-1).reshape(r, -1).max(axis=1),
        np.linalg.norm(fine[:, 1::2, ::2] - (grid[:, :-1, :] + grid[:, 1:, :]) / 2,
                       axis=-1).reshape(r, -1).max(axis=1),
        np.linalg.norm(fine[:, ::2, 1::2] - (grid[:, :, :-1] + grid[:, :, 1:]) / 2,
                       axis=-1).reshape(r, -1).max(axis=1)]).max(axis=0)
    idx = np.arange(n * n).reshape(n, n)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int64)
    return grid.reshape(r, n * n, 3), tris, gaps
