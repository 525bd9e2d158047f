"""What to bake: only the viewpoint cells and hemicube slots the scene's cameras can use.

A camera ray that enters the object's padded box through face f at point Q is answered from
the viewpoint cell containing Q and from the hemicube slot of its direction, so baking the
cells (plus a one-cell margin: the four corner viewpoints of a neighbouring cell may be needed
where Q falls on a cell edge after rounding) and slots that the cameras' rays reach is enough
to render those views; anything else a query meets later is traced and counted as such.
"""

from __future__ import annotations

import numpy as np

from ..render.camera import camera_rays
from .dircube import N_SLOTS, SLOT, UV_AXES, dir_to_cube
from .query import entry_points


class Region:
    """What to bake. ``cells[f, ix, iy]``: the viewpoint cells of box face f (2^D x 2^D) whose
    corner viewpoints are sampled. ``tree_keys`` (sorted) and ``rects`` (K, 4): the direction
    trees needed, keyed ``viewpoint_key * 5 + slot`` with viewpoint_key = f (2^D+1)^2 +
    gy (2^D+1) + gx, and the (u0, u1, v0, v1) part of each that the cameras' rays use. None
    means everything (the full tree)."""

    def __init__(self, cells=None, tree_keys=None, rects=None):
        self.cells = cells
        self.tree_keys = tree_keys
        self.rects = rects

    def describe(self) -> dict:
        if self.cells is None:
            return {"kind": "full"}
        return {"kind": "cameras", "faces": [int(f) for f in np.flatnonzero(self.cells.any((1, 2)))],
                "cells": int(self.cells.sum()), "cells_total": int(self.cells.size),
                "direction_trees": int(len(self.tree_keys))}


class _Box:
    """The padded box the tree will have (entry_points needs box_lo / box_hi)."""

    def __init__(self, lo, hi):
        self.box_lo, self.box_hi = lo, hi


def region_for_cameras(st, params, cameras, width, height, margin: int = 1) -> Region:
    """The Region that the rays of ``cameras`` (a list of scene Cameras, e.g. one per frame of
    an animation) at ``width`` x ``height`` pixels need: the viewpoint cells they enter the box
    through (with ``margin`` cells around), and for the corner viewpoints of those cells the
    hemicube slots and the direction rectangles their directions fall in (widened by
    ``margin`` cells of the finest direction grid)."""
    diag = st.tracer.diag
    pad = params.pad * diag + 1e-12
    box = _Box(st.tracer.lo - pad, st.tracer.hi + pad)
    D, M = params.viewpoint_depth, params.direction_depth
    n = 1 << D
    G = n + 1
    cells = np.zeros((6, n, n), bool)
    keys, us, vs = [], [], []
    for cam in cameras:
        o, d = camera_rays(cam, width, height)
        t_in, face, x, y, inside = entry_points(box, o, d)
        if np.any(inside):
            raise ValueError(f"camera {cam.name!r} is inside the object's bounding box: the "
                             "RI-Tree answers rays from outside it only; bake the full tree")
        cf, u, v = dir_to_cube(d)
        sl = SLOT[face, cf]
        ok = np.isfinite(t_in) & (sl >= 0)
        face, x, y, u, v, sl = face[ok], x[ok], y[ok], u[ok], v[ok], sl[ok]
        axis = face // 2
        ua = np.array([p[0] for p in UV_AXES])[axis]
        va = np.array([p[1] for p in UV_AXES])[axis]
        fx = (x - box.box_lo[ua]) / (box.box_hi[ua] - box.box_lo[ua])
        fy = (y - box.box_lo[va]) / (box.box_hi[va] - box.box_lo[va])
        ix = np.clip((fx * n).astype(np.int64), 0, n - 1)
        iy = np.clip((fy * n).astype(np.int64), 0, n - 1)
        for dx in range(-margin, margin + 1):
            for dy in range(-margin, margin + 1):
                jx = np.clip(ix + dx, 0, n - 1)
                jy = np.clip(iy + dy, 0, n - 1)
                cells[face, jx, jy] = True
                for cx in (0, 1):
                    for cy in (0, 1):
                        vk = face * G * G + (jy + cy) * G + (jx + cx)
                        keys.append(vk * N_SLOTS + sl)
                        us.append(u)
                        vs.append(v)
    keys = np.concatenate(keys) if keys else np.zeros(0, np.int64)
    uk, inv = np.unique(keys, return_inverse=True)
    inv = inv.ravel()
    rects = np.empty((len(uk), 4))
    rects[:, 0] = np.inf
    rects[:, 2] = np.inf
    rects[:, 1] = -np.inf
    rects[:, 3] = -np.inf
    u = np.concatenate(us) if us else np.zeros(0)
    v = np.concatenate(vs) if vs else np.zeros(0)
    np.minimum.at(rects[:, 0], inv, u)
    np.maximum.at(rects[:, 1], inv, u)
    np.minimum.at(rects[:, 2], inv, v)
    np.maximum.at(rects[:, 3], inv, v)
    widen = margin * 2.0 / (1 << M)           # finest direction cells are at most 2 / 2^M wide
    rects += np.array([-widen, widen, -widen, widen])
    return Region(cells=cells, tree_keys=uk, rects=rects)
