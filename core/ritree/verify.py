"""Verifying the viewpoint-level interpolation (the paper's "future work": non-uniform viewpoint
subdivision, here driven by measured error).

The direction trees are verified from their own viewpoints only (bake/directions.py's
midpoint tests).
Between viewpoints nothing is: a query ray entering the box inside a viewpoint cell blends the
answers of the cell's four corner viewpoints. This module measures that blend where it is
furthest from the corners - at the cell's centre and edge midpoints - on the rays the scene's
cameras send through those points: each test ray is answered through the tree exactly as the
renderer answers it (``TreeQuery``, no pairwise thresholds) and compared with the exact f.
"""

from __future__ import annotations

import numpy as np

from ..scene.camera import pixel_rays, project_points
from .dircube import UV_AXES
from .interp import angle_between
from .locate import entry_points
from .params import BOUNDARY, PATH_CHANGE

# Test points of a viewpoint cell, cell-local (x, y): the centre and the four edge midpoints.
TEST_POINTS = np.array([[0.5, 0.5], [0.5, 0.0], [0.0, 0.5], [1.0, 0.5], [0.5, 1.0]])
# How the measured test rays answer mirror rays (QueryOptions.mirror_rays), pinned here, not
# taken from the render-time default: "reflect", the interpolated hit and normal (the default
# from 65bd543 to 0d51411, 2026-12-02/03; earlier trees measured the paper's blended rays). The
# measured errors are the interpolation's, which the tolerance bounds; "newton"'s exact hits
# would measure ~0 where they apply. Recorded in the tree's meta as "viewpoint_mirror_rays".
MEASURE_MIRROR_RAYS = "reflect"
# Whether the measured test rays may be answered null (QueryOptions.null_interp), pinned here:
# False since 527fbe9, 2026-12-04 (the render-time default: such rays are traced, so nothing to
# measure); True before, when a null answer was measured (0 deg if the exact ray is trapped).
MEASURE_NULL_INTERP = False
# Edge midpoints are moved this far (cell-local) towards the centre, so that a point on an edge
# two cells share is located in the cell it tests (the locator sends shared edges upwards).
EDGE_NUDGE = 1e-6


def test_rays(tree, cells, cameras):
    """Camera rays through the test points of viewpoint-forest leaf ``cells``: (origins,
    directions, the cell each tests), only rays inside a camera's image that enter the box
    through the cell's own face. ``cameras``: (Camera, width, height) triples."""
    f = tree.vp_forest
    face = f.tree_of_nodes()[cells]
    dom = f.domain[face]
    pts = TEST_POINTS + EDGE_NUDGE * np.sign(0.5 - TEST_POINTS)
    size = np.exp2(-f.level[cells].astype(np.float64))[:, None]
    span_x, span_y = (dom[:, 1] - dom[:, 0])[:, None], (dom[:, 3] - dom[:, 2])[:, None]
    x = dom[:, 0, None] + span_x * (f.ix[cells][:, None] + pts[:, 0]) * size
    y = dom[:, 2, None] + span_y * (f.iy[cells][:, None] + pts[:, 1]) * size
    axes = np.array([UV_AXES[k // 2] for k in range(6)])
    n = x.size
    p = np.zeros((n, 3))
    fr = np.repeat(face, len(TEST_POINTS))
    rows = np.arange(n)
    p[rows, fr // 2] = np.where(fr % 2 == 1, tree.box_hi[fr // 2], tree.box_lo[fr // 2])
    p[rows, axes[fr, 0]] = x.ravel()
    p[rows, axes[fr, 1]] = y.ravel()
    cell = np.repeat(cells, len(TEST_POINTS))
    out = []
    for cam, w, h in cameras:
        px, py, depth = project_points(cam, w, h, p)
        ok = np.flatnonzero((depth > 0) & (px >= 0) & (px <= w) & (py >= 0) & (py <= h))
        o, d = pixel_rays(cam, w, h, px[ok], py[ok])
        _, ef, _, _, inside = entry_points(tree, o, d)
        keep = (ef == fr[ok]) & ~inside
        out.append((o[keep], d[keep], cell[ok[keep]]))
    return tuple(np.concatenate([r[k] for r in out]) for k in range(3))


def viewpoint_errors(tree, st, cameras):
    """Measured error of the viewpoint-level interpolation per viewpoint-forest node:
    (err (Kv,) float32 degrees, NaN where nothing was measured; flags (Kv,) uint8). A cell's
    error is the largest output-direction error of its test rays the tree answers by
    interpolation (inf for a wrong kind of answer: a miss, hit or null state the exact ray
    does not have); its flags mark test rays that both hit and miss the object (BOUNDARY) or
    hits with different ray-tree hashes (PATH_CHANGE)."""
    from .query import EXTRAPOLATED_S, FULL, MISS, NULL_S, QueryOptions, TreeQuery
    f = tree.vp_forest
    err = np.full(len(f.child), np.nan, np.float32)
    flags = np.zeros(len(f.child), np.uint8)
    cells = np.flatnonzero((f.child < 0) & np.all(f.corner >= 0, axis=1))
    if len(cells) == 0 or not cameras:
        return err, flags
    o, d, cell = test_rays(tree, cells, cameras)
    tmax = st.env.hit_distance(o, d)
    front = st.box_entry(o, d) < tmax            # rays the renderer asks the object about
    o, d, cell, tmax = o[front], d[front], cell[front], tmax[front]
    if len(o) == 0:
        return err, flags
    ex = st.object_function(o, d, tmax)
    paper = QueryOptions(angle_deg=None, max_error_deg=None,     # the rules, no tolerance
                         mirror_rays=MEASURE_MIRROR_RAYS, null_interp=MEASURE_NULL_INTERP,
                         many_classes="trace", solve_paths=False, fresnel_tree=False)
    res, ans, _, _ = TreeQuery(tree, st, paper)(o, d, tmax)
    e = np.full(len(o), np.nan)
    interp = (ans >= FULL) & (ans <= EXTRAPOLATED_S)
    both = interp & res.hit & ex.hit & ~ex.null
    e[both] = np.degrees(angle_between(res.out_dir[both], ex.out_dir[both]))
    e[interp & ~both] = np.inf
    e[ans == NULL_S] = np.where(ex.null[ans == NULL_S], 0.0, np.inf)
    e[ans == MISS] = np.where(ex.hit[ans == MISS], np.inf, 0.0)
    m = ~np.isnan(e)
    acc = np.full(len(f.child), -np.inf)
    np.maximum.at(acc, cell[m], e[m])
    err[acc > -np.inf] = acc[acc > -np.inf]
    hit_any = np.zeros(len(f.child), bool)
    miss_any = np.zeros(len(f.child), bool)
    hit_any[cell[ex.hit]] = True
    miss_any[cell[~ex.hit]] = True
    flags[hit_any & miss_any] |= BOUNDARY
    h = ex.hit
    lo = np.full(len(f.child), np.iinfo(np.int64).max)
    hi = np.full(len(f.child), -1)
    np.minimum.at(lo, cell[h], ex.tree[h].astype(np.int64))
    np.maximum.at(hi, cell[h], ex.tree[h].astype(np.int64))
    flags[(hi >= 0) & (hi != lo)] |= PATH_CHANGE
    return err, flags
