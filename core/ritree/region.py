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
    """Per box face a boolean mask over the 2^D x 2^D viewpoint cells ``cells[f, ix, iy]`` and
    per cell the hemicube slots ``slots[f, ix, iy, s]``; None means everything."""

    def __init__(self, cells: np.ndarray | None = None, slots: np.ndarray | None = None):
        self.cells = cells
        self.slots = slots

    def describe(self) -> dict:
        if self.cells is None:
            return {"kind": "full"}
        return {"kind": "cameras", "faces": [int(f) for f in np.flatnonzero(self.cells.any((1, 2)))],
                "cells": int(self.cells.sum()), "cells_total": int(self.cells.size)}


class _Box:
    """The padded box the tree will have (entry_points needs box_lo / box_hi)."""

    def __init__(self, lo, hi):
        self.box_lo, self.box_hi = lo, hi


def region_for_cameras(st, params, cameras, width, height, margin: int = 1) -> Region:
    """The Region that the rays of ``cameras`` (a list of scene Cameras, e.g. one per frame of
    an animation) at ``width`` x ``height`` pixels can enter the object through."""
    diag = st.tracer.diag
    pad = params.pad * diag + 1e-12
    box = _Box(st.tracer.lo - pad, st.tracer.hi + pad)
    D = params.viewpoint_depth
    n = 1 << D
    cells = np.zeros((6, n, n), bool)
    slots = np.zeros((6, n, n, N_SLOTS), bool)
    for cam in cameras:
        o, d = camera_rays(cam, width, height)
        t_in, face, x, y, inside = entry_points(box, o, d)
        if np.any(inside):
            raise ValueError(f"camera {cam.name!r} is inside the object's bounding box: the "
                             "RI-Tree answers rays from outside it only; bake the full tree")
        ok = np.isfinite(t_in)
        face, x, y, d = face[ok], x[ok], y[ok], d[ok]
        axis = face // 2
        ua = np.array([p[0] for p in UV_AXES])[axis]
        va = np.array([p[1] for p in UV_AXES])[axis]
        fx = (x - box.box_lo[ua]) / (box.box_hi[ua] - box.box_lo[ua])
        fy = (y - box.box_lo[va]) / (box.box_hi[va] - box.box_lo[va])
        ix = np.clip((fx * n).astype(np.int64), 0, n - 1)
        iy = np.clip((fy * n).astype(np.int64), 0, n - 1)
        cf, _, _ = dir_to_cube(d)
        sl = SLOT[face, cf]
        good = sl >= 0
        for dx in range(-margin, margin + 1):
            for dy in range(-margin, margin + 1):
                jx = np.clip(ix + dx, 0, n - 1)
                jy = np.clip(iy + dy, 0, n - 1)
                cells[face, jx, jy] = True
                slots[face[good], jx[good], jy[good], sl[good]] = True
    return Region(cells=cells, slots=slots)
