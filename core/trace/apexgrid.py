"""Triangles binned by their direction as seen from one point, the *apex* (a point light), for
any-hit tests of segments that end at it (shadow rays): such a segment lies on the line through
the apex and its origin, so it can only meet the triangles listed in the cell of its origin's
direction, nearest to the apex first. A shadow ray costs one cell lookup and a test of a few
triangles instead of a hierarchy walk, and rays that pass beside the triangles cost no test.

Directions are cut by the cube around the apex into six faces, each with a grid of cells over
the rectangle where its triangles project (w_b / |w_a|, w_c / |w_a| on the face of axis a, w =
point - apex). A triangle is listed in every cell that the box of its projection overlaps,
grown by what ``pad`` can move a point: how far a segment's end may lie from the apex (the
segment then stays within ``pad`` of the line through the apex and its origin) plus the
rounding the triangle test allows. Triangles within NEAR_PADS pads of the apex are listed for
every ray (the *near* list). Units: scene units; face coordinates in [-1, 1].
"""

from __future__ import annotations

import numpy as np

CELLS_PER_BOX = 64.0    # grid cells per median projected box area: a list holds little more
                        # than the triangles layered along its direction
MAX_CELLS = 1 << 16     # cells per face: bounds the grid's memory (~0.5 MB of starts)
MAX_ENTRIES = 1 << 23   # (cell, triangle) entries in all: beyond, the grid is not built
EDGE = 1e-9             # face-coordinate margin around each projected box: covers rounding
NEAR_PADS = 7.0         # triangles within this many pads of the apex are listed for every ray
ROUNDS = 4              # candidates tested one per ray per round (a hit ends the ray's search);
                        # the rest of a long list are tested together after these


class GridTooLarge(Exception):
    """The grid would hold more than MAX_ENTRIES entries: test these segments another way."""


def _ranges(starts, counts):
    """Concatenation of arange(s, s + c) over (starts, counts)."""
    offs = np.cumsum(counts) - counts
    return np.repeat(starts - offs, counts) + np.arange(int(counts.sum()))


def _face_rects(w, f, eta, pad):
    """Bounds (x0, x1, y0, y1) (M,) of where triangles w (M, 3, 3), apex at 0, grown by
    ``pad``, project on face ``f`` (empty: x0 > x1): the part of each at depth >= ``eta`` along
    the face's axis is clipped off, projected and its box grown by what ``pad`` can move a
    point there."""
    a, s = f // 2, (1.0 if f % 2 else -1.0)
    dep = s * w[:, :, a]                                        # (M, 3)
    pts = [w[:, i] for i in range(3)]
    deps = [dep[:, i] for i in range(3)]
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in range(3):                                      # edge crossings of eta
            j = (i + 1) % 3
            lam = (eta - dep[:, i]) / (dep[:, j] - dep[:, i])
            pts.append(w[:, i] + lam[:, None] * (w[:, j] - w[:, i]))
            deps.append(np.where((lam > 0) & (lam < 1), eta, -np.inf))
        p, dp = np.stack(pts, 1), np.stack(deps, 1)             # (M, 6, 3), (M, 6)
        ok = dp >= eta
        x, y = p[:, :, (a + 1) % 3] / dp, p[:, :, (a + 2) % 3] / dp
        x0, x1 = np.where(ok, x, np.inf).min(1), np.where(ok, x, -np.inf).max(1)
        y0, y1 = np.where(ok, y, np.inf).min(1), np.where(ok, y, -np.inf).max(1)
        dmin = np.where(ok, dp, np.inf).min(1)
        grow = pad * (1.0 + np.maximum.reduce([np.abs(x0), np.abs(x1), np.abs(y0),
                                               np.abs(y1)])) / (dmin - pad) + EDGE
    x0, x1 = np.maximum(x0 - grow, -1.0 - EDGE), np.minimum(x1 + grow, 1.0 + EDGE)
    y0, y1 = np.maximum(y0 - grow, -1.0 - EDGE), np.minimum(y1 + grow, 1.0 + EDGE)
    empty = ~ok.any(axis=1)
    x0[empty], x1[empty] = 1.0, -1.0
    return x0, x1, y0, y1


class ApexGrid:
    """Triangles ``tris`` (M, 3 vertices, 3) binned as seen from ``apex`` (3,); ``ids`` (M,)
    are the caller's triangle indices, ``pad`` bounds how far a segment's end lies from the
    apex plus the rounding the caller's triangle test allows beyond a triangle."""

    def __init__(self, apex, tris, ids, pad: float):
        self.apex = np.asarray(apex, dtype=np.float64)
        self.pad = float(pad)
        w = np.asarray(tris, dtype=np.float64) - self.apex
        wl, wh = w.min(axis=1) - pad, w.max(axis=1) + pad
        self.near = np.linalg.norm(np.maximum(np.maximum(wl, -wh), 0.0), axis=1)
        # a grown triangle in a face's view at depth < 2 pad lies within 7 pad of the apex
        close = self.near <= NEAR_PADS * self.pad
        self.close_ids = np.asarray(ids)[close]
        cell_of, item_of = [], []
        self.rect = np.zeros((6, 4))                # x0, y0, cells per unit x, y
        self.shape = np.zeros((6, 2), np.int64)     # Gx, Gy
        self.base = np.zeros(7, np.int64)
        far = np.flatnonzero(~close)
        for f in range(6):
            x0, x1, y0, y1 = _face_rects(w[far], f, 2.0 * self.pad, self.pad)
            ok = (x0 <= x1) & (y0 <= y1)
            items = far[ok]
            self.base[f + 1] = self.base[f]
            if len(items) == 0:
                continue
            x0, x1, y0, y1 = x0[ok], x1[ok], y0[ok], y1[ok]
            fx0, fy0 = x0.min(), y0.min()
            wx, wy = max(x1.max() - fx0, EDGE), max(y1.max() - fy0, EDGE)
            area = max(float(np.median((x1 - x0) * (y1 - y0))), EDGE * EDGE)
            cells = int(np.clip(CELLS_PER_BOX * wx * wy / area, 1, MAX_CELLS))
            gx = int(np.clip(round(np.sqrt(cells * wx / wy)), 1, cells))
            gy = int(np.clip(cells // gx, 1, cells))
            self.rect[f] = fx0, fy0, gx / wx, gy / wy
            self.shape[f] = gx, gy
            self.base[f + 1] = self.base[f] + gx * gy
            ix0 = np.clip(((x0 - fx0) * self.rect[f, 2]).astype(np.int64), 0, gx - 1)
            ix1 = np.clip(((x1 - fx0) * self.rect[f, 2]).astype(np.int64), 0, gx - 1)
            iy0 = np.clip(((y0 - fy0) * self.rect[f, 3]).astype(np.int64), 0, gy - 1)
            iy1 = np.clip(((y1 - fy0) * self.rect[f, 3]).astype(np.int64), 0, gy - 1)
            nx, ny = ix1 - ix0 + 1, iy1 - iy0 + 1
            if sum(len(x) for x in item_of) + int((nx * ny).sum()) > MAX_ENTRIES:
                raise GridTooLarge(f"more than {MAX_ENTRIES} (cell, triangle) entries")
            rows = np.repeat(np.arange(len(items)), ny)          # one per (item, grid row)
            gyr = _ranges(iy0, ny)
            row_cells = np.repeat(self.base[f] + gyr * gx + ix0[rows], nx[rows])
            cell_of.append(row_cells + _ranges(np.zeros(len(rows), np.int64), nx[rows]))
            item_of.append(np.repeat(items[rows], nx[rows]))
        cell = np.concatenate(cell_of) if cell_of else np.zeros(0, np.int64)
        item = np.concatenate(item_of) if item_of else np.zeros(0, np.int64)
        order = np.lexsort((self.near[item], cell))               # per cell, nearest first
        self.entry = np.asarray(ids)[item[order]]
        self.entry_near = self.near[item[order]]
        self.start = np.searchsorted(cell[order], np.arange(self.base[6] + 1))

    def cells(self, wt):
        """(start, count) of the list of each direction wt (3, n) from the apex (count 0
        outside every face's rectangle, and for w = 0). A direction on a cube edge may take
        either face: each face's boxes cover all their points in front of it."""
        n = wt.shape[1]
        start = np.zeros(n, np.int64)
        count = np.zeros(n, np.int64)
        faces = np.flatnonzero(self.base[1:] > self.base[:-1])
        aw = np.abs(wt) if len(faces) else None
        for f in faces:
            a, s = f // 2, (1.0 if f % 2 else -1.0)
            wa, wb, wc = wt[a], wt[(a + 1) % 3], wt[(a + 2) % 3]
            depth = wa if s > 0 else -wa
            mask = (depth > 0) & (depth >= aw[(a + 1) % 3]) & (depth >= aw[(a + 2) % 3])
            if f != faces[0]:
                mask &= count == 0
            on = np.flatnonzero(mask)
            x0, y0, sx, sy = self.rect[f]
            gx, gy = self.shape[f]
            dep = depth[on]
            fx = (wb[on] / dep - x0) * sx
            fy = (wc[on] / dep - y0) * sy
            keep = (fx >= 0) & (fy >= 0) & (fx < gx) & (fy < gy)
            on = on[keep]
            cell = self.base[f] + fy[keep].astype(np.int64) * gx + fx[keep].astype(np.int64)
            start[on] = self.start[cell]
            count[on] = self.start[cell + 1] - start[on]
        return start, count

    def any_hit(self, wt, hit_fn) -> np.ndarray:
        """(n,) bool for segments from origins apex + wt (3, n) that end within ``pad`` of the
        apex (the caller's check): does ``hit_fn(rays, triangle ids)`` (t, inf for a miss)
        find a hit among the triangles listed for them."""
        n = wt.shape[1]
        start, count = self.cells(wt)
        out = np.zeros(n, bool)
        live = np.flatnonzero(count > 0)
        reach = np.zeros(n)
        wl = wt.take(live, axis=1)
        reach[live] = np.sqrt(wl[0] * wl[0] + wl[1] * wl[1] + wl[2] * wl[2]) + 2.0 * self.pad
        for k in range(ROUNDS):
            live = live[count[live] > k]
            if len(live) == 0:
                break
            e = start[live] + k
            near = self.entry_near[e] <= reach[live]
            live, e = live[near], e[near]           # farther ones: none later in the list
            hit = np.asarray(hit_fn(live, self.entry[e])) < np.inf
            out[live[hit]] = True
            live = live[~hit]
        live = live[count[live] > ROUNDS]
        if len(live):                               # long lists: the rest at once
            cnt = count[live] - ROUNDS
            r = np.repeat(live, cnt)
            e = _ranges(start[live] + ROUNDS, cnt)
            keep = self.entry_near[e] <= reach[r]
            r, e = r[keep], e[keep]
            out[r[np.asarray(hit_fn(r, self.entry[e])) < np.inf]] = True
        if len(self.close_ids):
            r = np.repeat(np.flatnonzero(~out), len(self.close_ids))
            p = np.tile(self.close_ids, n - int(out.sum()))
            out[r[np.asarray(hit_fn(r, p)) < np.inf]] = True
        return out
