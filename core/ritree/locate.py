"""Locating query rays in the RI-Tree (paper 4.1): box entry -> viewpoint cell -> hemicube
slot -> the four direction leaves (DQs) whose 16 corner samples answer the ray.

Everything works on whole arrays of rays; the quadtree descents loop over tree levels, never
over rays.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from ..rowops import all_last, argmax3, min3
from ..trace.boxes import slab_intervals
from .dircube import DOMAIN, N_SLOTS, SLOT, U_AXIS, V_AXIS, dir_to_cube


def entry_points(tree, o, d):
    """Entry distance, face and face coordinates of rays into the tree's padded box.
    Returns (t_in, face, x, y, inside): inside marks rays starting inside the box."""
    lo, hi = tree.box_lo, tree.box_hi
    tnear, tfar = slab_intervals(o, d, lo, hi)
    axis = argmax3(tnear)
    rows = np.arange(len(o))
    tn = tnear[rows, axis]
    tf = min3(tfar)
    # inside every slab (closed): t = 0 lies in every axis' interval
    inside = (tn <= 0) & (tf >= 0)
    t_in = np.where((tn <= tf) & (tf >= 0), np.maximum(tn, 0.0), np.inf)
    face = 2 * axis + (d[rows, axis] < 0)
    t = np.where(np.isfinite(t_in), t_in, 0.0)
    # the entry point's two coordinates on its face (o + t d, the others not formed)
    ua, va = U_AXIS[axis], V_AXIS[axis]
    return t_in, face, o[rows, ua] + t * d[rows, ua], o[rows, va] + t * d[rows, va], inside


@dataclass
class Located:
    """Rays that found their four direction leaves. ``ray`` indexes the query's rays; per DQ
    k (the viewpoint cell's corners in quadtree corner order): leaf node ``leaf[:, k]`` of its
    direction tree and the ray's cell-local (lx, ly) in it; (alpha, beta) is the entry point's
    position in the viewpoint cell ``vnode`` (a viewpoint-forest leaf), all in [0, 1]."""

    ray: np.ndarray      # (m,) int64
    vnode: np.ndarray    # (m,) int64
    alpha: np.ndarray    # (m,)
    beta: np.ndarray     # (m,)
    leaf: np.ndarray     # (m, 4) int64
    lx: np.ndarray       # (m, 4)
    ly: np.ndarray       # (m, 4)

    def __len__(self) -> int:
        return len(self.ray)

    def take(self, idx) -> "Located":
        """The rows ``idx`` of every field."""
        return Located(**{f.name: getattr(self, f.name)[idx] for f in fields(self)})


def locate(tree, o, d, tmax):
    """Locate rays (o, d unit, tmax: something in front ends the ray) in ``tree``.

    Returns (located, outside): ``outside`` are the rows the tree cannot answer (the ray
    starts inside the box, or its viewpoint cell, slot or leaves were not baked); rays that
    do not enter the box before tmax are in neither (they miss the object)."""
    t_in, face, x, y, inside = entry_points(tree, o, d)
    q = np.flatnonzero(np.isfinite(t_in) & (t_in < tmax) & ~inside)
    if len(q) < len(o):
        face, x, y, d = face[q], x[q], y[q], d[q]
    vnode, alpha, beta = tree.vp_locator.locate(face, x, y)
    vps = tree.vp_forest.corner.take(np.maximum(vnode, 0), axis=0)
    cf, u, v = dir_to_cube(d)
    slot = SLOT.take(face * 6 + cf)                       # SLOT[face, cf], -1: impossible
    ok = (vnode >= 0) & all_last(vps >= 0) & (slot >= 0)
    if not ok.any():         # no ray meets a baked viewpoint cell (a tree without viewpoints)
        nothing = np.zeros((0, 4))
        return Located(ray=q[:0], vnode=vnode[:0], alpha=alpha[:0], beta=beta[:0],
                       leaf=nothing.astype(np.int64), lx=nothing, ly=nothing), \
            np.concatenate([np.flatnonzero(inside), q])
    slot = np.maximum(slot, 0)
    trees = np.where(ok[:, None], vps * N_SLOTS + slot[:, None], 0)                # (m, 4)
    # the four direction trees of a viewpoint cell cover the same slot domain, DOMAIN[face,
    # slot] (their viewpoints lie on one box face): normalize once per ray
    dom = DOMAIN.reshape(-1, 4).take(face * N_SLOTS + slot, axis=0)
    fx = np.clip((u - dom[:, 0]) / (dom[:, 1] - dom[:, 0]), 0.0, 1.0)
    fy = np.clip((v - dom[:, 2]) / (dom[:, 3] - dom[:, 2]), 0.0, 1.0)
    leaf, lx, ly = tree.dir_locator.locate_normalized(trees, fx[:, None], fy[:, None])
    ok &= all_last(leaf >= 0)
    # leaves inside the baked rectangle with every corner sampled answer all their rays;
    # elsewhere each ray is checked (against its cell's four baked rectangles at once)
    good = np.flatnonzero(ok)
    check = good[~all_last(tree.leaf_ok.take(leaf[good]))]
    if len(check):
        rect = tree.cell_rect.reshape(-1, 4).take(vnode[check] * N_SLOTS + slot[check], axis=0)
        uc, vc = u[check], v[check]
        ok[check] = (uc >= rect[:, 0]) & (uc <= rect[:, 1]) & (vc >= rect[:, 2]) \
            & (vc <= rect[:, 3]) & all_last(tree.leaf_sampled.take(leaf[check]))
    outside = np.concatenate([np.flatnonzero(inside), q[~ok]])
    k = np.flatnonzero(ok)
    if len(k) == len(ok):
        k = slice(None)
    return Located(ray=q[k], vnode=vnode[k], alpha=alpha[k], beta=beta[k], leaf=leaf[k],
                   lx=lx[k], ly=ly[k]), outside
