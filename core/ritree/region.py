"""What to bake: only the viewpoint cells and hemicube slots the scene's cameras can use.

A camera ray that enters the object's padded box through face f at point Q is answered from
the viewpoint cell containing Q and from the hemicube slot of its direction, so baking the
cells (plus a one-cell margin: the four corner viewpoints of a neighbouring cell may be needed
where Q falls on a cell edge after rounding) and slots that the cameras' rays reach is enough
to render those views; anything else a query meets later is traced and counted as such.
"""

from __future__ import annotations

import numpy as np

from ..scene.camera import camera_rays
from .dircube import N_SLOTS, SLOT, U_AXIS, V_AXIS, dir_to_cube
from .locate import entry_points

# Most of a camera's rays the region keeps for the bake to trace and query (refinement,
# estimates): an evenly spaced subset beyond it. The cells and direction rectangles come from
# every pixel ray, KEY_CHUNK rays at a time, so an animation's bake stays bounded in memory at
# any render size (26 cameras at 960 x 540 asked for 3.4 GB in one array before).
MAX_CAMERA_RAYS = 1 << 18
KEY_CHUNK = 1 << 18


class Region:
    """What to bake. ``cells[f, ix, iy]``: the viewpoint cells of box face f (2^D x 2^D) whose
    corner viewpoints are sampled. ``levels[L] = (keys, rects)``: for viewpoints created at
    viewpoint level L, the direction trees needed, keyed ``viewpoint_key * 5 + slot``
    (viewpoint_key = f G^2 + gy G + gx on the finest grid, G = 2^(D + refine) + 1), and the
    (u0, u1, v0, v1) part of each that the cameras' rays use. ``rays`` = (origins, dirs, tmax)
    of the camera rays that reach the object's box (at most MAX_CAMERA_RAYS a camera), for
    refinement. ``cameras``: the (Camera,
    width, height) triples, whose rays verify the viewpoint-level interpolation. None:
    everything. ``unseen``: the names of the cameras left out because none of their rays
    reaches the object's box."""

    def __init__(self, cells=None, levels=None, rays=None, cameras=None, unseen=()):
        self.cells = cells
        self.levels = levels
        self.rays = rays
        self.cameras = cameras
        self.unseen = list(unseen)

    @property
    def tree_keys(self):
        return None if self.levels is None else self.levels[min(self.levels)][0]

    def rects_at(self, level):
        return self.levels[level]

    def describe(self) -> dict:
        if self.cells is None:
            return {"kind": "full"}
        return {"kind": "cameras", "faces": [int(f) for f in np.flatnonzero(self.cells.any((1, 2)))],
                "cells": int(self.cells.sum()), "cells_total": int(self.cells.size),
                "direction_trees": None if self.tree_keys is None else int(len(self.tree_keys)),
                "camera_rays": int(len(self.rays[0])) if self.rays is not None else 0}


class _Box:
    """The padded box the tree will have (entry_points needs box_lo / box_hi)."""

    def __init__(self, lo, hi):
        self.box_lo, self.box_hi = lo, hi


def check_object(st) -> None:
    """ValueError unless the object of ``st`` (a SceneTracer) has a bounding box of positive
    size (a tree of a point has nothing to sample; a flat object is fine)."""
    if not np.any(st.tracer.hi > st.tracer.lo):
        raise ValueError(f"the object {st.scene.object.name!r} has a bounding box of size zero: "
                         "nothing to bake")


def region_for_cameras(st, params, cameras, width, height, margin: int = 1) -> Region:
    """The Region that the rays of ``cameras`` (a list of scene Cameras, e.g. one per frame of
    an animation) at ``width`` x ``height`` pixels need: the viewpoint cells they enter the box
    through (with ``margin`` cells around), and, for every viewpoint level up to the refinement
    limit, the hemicube slots and direction rectangles (widened by ``margin`` cells of the
    finest direction grid) used around each viewpoint; of each camera's rays that reach the
    object's box it keeps at most MAX_CAMERA_RAYS for the bake. Cameras none of whose rays reach the
    object's box (before the environment) are left out (``Region.unseen``); ValueError naming
    the first when that leaves none, or when the object has no size."""
    check_object(st)
    diag = st.tracer.diag
    pad = params.pad * diag + 1e-12
    box = _Box(st.tracer.lo - pad, st.tracer.hi + pad)
    D, M = params.viewpoint_depth, params.direction_depth
    Dmax = D + params.viewpoint_refine
    G = (1 << Dmax) + 1
    n = 1 << D
    cells = np.zeros((6, n, n), bool)
    parts = {level: [] for level in range(D, Dmax + 1)}    # (keys, rects) merged per camera
    rays = []
    seen, unseen = [], []
    for cam in cameras:
        o, d = camera_rays(cam, width, height)
        t_in, face, x, y, inside = entry_points(box, o, d)
        if np.any(inside):
            raise ValueError(f"camera {cam.name!r} is inside the object's bounding box: the "
                             "RI-Tree answers rays from outside it only; bake the full tree")
        cf, u, v = dir_to_cube(d)
        sl = SLOT[face, cf]
        env_t = st.env.hit_distance(o, d)
        ok = np.flatnonzero(np.isfinite(t_in) & (sl >= 0) & (t_in < env_t))
        if not len(ok):
            unseen.append(cam.name)
            continue
        seen.append(cam)
        keep = ok[np.unique(np.linspace(0, len(ok) - 1, min(len(ok), MAX_CAMERA_RAYS))
                            .astype(np.int64))]
        rays.append((o[keep], d[keep], env_t[keep]))
        face, x, y, u, v, sl = face[ok], x[ok], y[ok], u[ok], v[ok], sl[ok]
        axis = face // 2
        ua, va = U_AXIS[axis], V_AXIS[axis]
        fx = np.clip((x - box.box_lo[ua]) / (box.box_hi[ua] - box.box_lo[ua]), 0.0, 1.0)
        fy = np.clip((y - box.box_lo[va]) / (box.box_hi[va] - box.box_lo[va]), 0.0, 1.0)
        for level, got in parts.items():
            chunks = [_level_rects(tuple(a[c:c + KEY_CHUNK] for a in (face, fx, fy, sl, u, v)),
                                   level, D, Dmax, G, margin, cells)
                      for c in range(0, len(face), KEY_CHUNK)]
            got[:] = [_merge_rects(*zip(*(got + chunks)))]
    if not seen:
        raise ValueError(f"camera {unseen[0]!r} does not see the object "
                         f"{st.scene.object.name!r} (none of its {width} x {height} pixel rays "
                         "reaches the object's bounding box); nothing to bake")
    widen = margin * 2.0 / (1 << M)           # finest direction cells are at most 2 / 2^M wide
    levels = {level: (got[0][0], got[0][1] + np.array([-widen, widen, -widen, widen]))
              for level, got in parts.items()}
    o, d, t = (np.concatenate([r[k] for r in rays]) for k in range(3))
    return Region(cells=cells, levels=levels, rays=(o, d, t),
                  cameras=[(cam, width, height) for cam in seen], unseen=unseen)


def _level_rects(rec, level, D, Dmax, G, margin, cells):
    """(keys, rects) of one camera's rays ``rec`` = (face, fx, fy, slot, u, v) at viewpoint
    ``level``: the direction trees they need around the corners of their cell and its
    ``margin`` neighbours, each with the (u0, u1, v0, v1) the rays use; at the top level D
    the cells are marked in ``cells``."""
    face, fx, fy, sl, u, v = rec
    m = 1 << level
    step = 1 << (Dmax - level)
    ix = np.minimum((fx * m).astype(np.int64), m - 1)
    iy = np.minimum((fy * m).astype(np.int64), m - 1)
    keys = []
    for dx in range(-margin, margin + 1):
        for dy in range(-margin, margin + 1):
            jx = np.clip(ix + dx, 0, m - 1)
            jy = np.clip(iy + dy, 0, m - 1)
            if level == D:
                cells[face, jx, jy] = True
            for cx in (0, 1):
                for cy in (0, 1):
                    vk = face * G * G + (jy + cy) * step * G + (jx + cx) * step
                    keys.append(vk * N_SLOTS + sl)
    keys = np.concatenate(keys)
    reps = len(keys) // max(len(u), 1)
    uu, vv = np.tile(u, reps), np.tile(v, reps)
    return _merge_rects([keys], [np.stack([uu, uu, vv, vv], axis=1)])


def _merge_rects(keys, rects):
    """Unique keys of the concatenated ``keys`` with the union of their ``rects`` rows
    (u0, u1, v0, v1): the least u0 and v0, the greatest u1 and v1."""
    k = np.concatenate(keys)
    r = np.concatenate(rects)
    uk, inv = np.unique(k, return_inverse=True)
    inv = inv.ravel()
    out = np.empty((len(uk), 4))
    out[:, [0, 2]] = np.inf
    out[:, [1, 3]] = -np.inf
    np.minimum.at(out[:, 0], inv, r[:, 0])
    np.maximum.at(out[:, 1], inv, r[:, 1])
    np.minimum.at(out[:, 2], inv, r[:, 2])
    np.maximum.at(out[:, 3], inv, r[:, 3])
    return uk, out
