"""Baking the RI-Tree (paper 3.3 and 4.3), level by level over all trees at once.

1. Viewpoint trees: the six faces of the padded box, split uniformly to ``viewpoint_depth``;
   only the leaf cells in the requested region get their corner viewpoints (shared corners are
   sampled once).
2. Direction trees: for every viewpoint, the hemicube slots that can see the object. Each level
   traces the midpoints of all open cells at once, interpolates them from the cell corners with
   the renderer's own rules (``interp.cell_weights``, usable = same class as the traced midpoint
   and not null), and splits the cells where the corners disagree in class or null state or
   where the interpolated output ray, hit point or normal misses the traced one by more than the
   tolerance. New corner samples are keyed on the finest grid, so cells share them.
3. Extra samples for leaves whose corners fall in two classes: the one- and two-interpolant
   cases, the class boundary located on the cell edges by binary search.

Tracing runs in chunks over worker processes; ``progress(fraction, message)`` is called between
chunks and ``cancel()`` (returning True) stops the bake with ``BakeCancelled``.
"""

from __future__ import annotations

import time

import numpy as np

from ..parallel import map_chunks
from .cache import fingerprint
from .dircube import CUBE, DOMAIN, N_SLOTS, UV_AXES, cube_to_dir
from .interp import FAIL, angle_between, cell_weights
from .quadtree import CORNERS, Forest
from .region import Region
from .tree import BakeParams, RITree, Samples

TRACE_CHUNK = 8192          # rays per worker task (bounds worker memory, keeps progress fluid)
SLOT_PROBE = 17             # probe rays per slot side when testing whether a slot sees the object


class BakeCancelled(Exception):
    """The bake was cancelled; nothing was written."""


class _Tracer:
    """Traces batches of (viewpoint, cube face, u, v) sample rays with the exact f."""

    def __init__(self, st, vp_pos, workers, report, cancel):
        self.st, self.vp_pos, self.workers = st, vp_pos, workers
        self.report, self.cancel = report, cancel
        self.rays = 0

    def __call__(self, vp, face, u, v) -> Samples:
        o = self.vp_pos[vp]
        d = cube_to_dir(face, u, v)

        def work(a, b):
            return Samples.from_rays(self.st.object_function(o[a:b], d[a:b]))

        def prog(frac):
            if self.cancel is not None and self.cancel():
                raise BakeCancelled("bake cancelled")
            self.report(frac)

        parts = map_chunks(work, len(o), TRACE_CHUNK, self.workers, prog) if len(o) else []
        self.rays += len(o)
        out = Samples.empty()
        for p in parts:
            out.extend(p)
        return out


class _SampleIndex:
    """Sample ids by integer key, appended level by level (dedup of shared corners)."""

    def __init__(self):
        self.keys = np.zeros(0, np.int64)
        self.ids = np.zeros(0, np.int64)

    def lookup(self, keys):
        pos = np.searchsorted(self.keys, keys)
        pos = np.minimum(pos, len(self.keys) - 1) if len(self.keys) else pos
        found = (len(self.keys) > 0) & (self.keys[pos] == keys) if len(self.keys) else \
            np.zeros(len(keys), bool)
        return np.where(found, self.ids[pos] if len(self.keys) else -1, -1)

    def add(self, keys, ids):
        k = np.concatenate([self.keys, keys])
        i = np.concatenate([self.ids, ids])
        order = np.argsort(k, kind="stable")
        self.keys, self.ids = k[order], i[order]


def _progress_reporter(progress, stages):
    """Map (stage, fraction within stage) to an overall fraction with an ETA message."""
    t0 = time.perf_counter()

    def report(stage, frac, label):
        if progress is None:
            return
        total = (stage + min(max(frac, 0.0), 1.0)) / stages
        el = time.perf_counter() - t0
        eta = el / total - el if total > 0 else float("nan")
        progress(total, f"{label}: {100 * total:.0f}% (eta {eta:.0f} s)")
    return report


def bake(st, params: BakeParams | None = None, region: Region | None = None, progress=None,
         cancel=None, workers=None) -> RITree:
    """Bake the RI-Tree of ``st`` (render.exact.SceneTracer) with ``params`` over ``region``."""
    params = (params or BakeParams()).validate()
    t0 = time.perf_counter()
    lo, hi, diag = st.tracer.lo, st.tracer.hi, st.tracer.diag
    pad = params.pad * diag + 1e-12
    box_lo, box_hi = lo - pad, hi + pad
    D, M = params.viewpoint_depth, params.direction_depth
    stages = M + 2
    report = _progress_reporter(progress, stages)

    # ---- viewpoint trees: uniform to depth D, corners only for cells in the region
    vp_dom = np.array([[box_lo[a], box_hi[a], box_lo[b], box_hi[b]]
                       for f in range(6) for (a, b) in [UV_AXES[f // 2]]])
    vpf = Forest.empty(vp_dom)
    nodes = vpf.add_roots(np.arange(6))
    for _ in range(D):
        nodes = vpf.split(nodes).ravel()
    leaves = nodes
    face = vpf.tree_of_nodes()[leaves]
    lix, liy = vpf.ix[leaves], vpf.iy[leaves]
    want = np.ones(len(leaves), bool) if region is None or region.cells is None else \
        region.cells[face, lix, liy]
    G = (1 << D) + 1
    cc = vpf.corner_coords(leaves, D)                                   # (L, 4, 2)
    vkeys = face[:, None] * G * G + cc[..., 1] * G + cc[..., 0]
    uniq, inv = np.unique(vkeys[want], return_inverse=True)
    corner = -np.ones((len(leaves), 4), np.int64)
    corner[want] = inv.reshape(-1, 4)
    vpf.corner[leaves] = corner
    vface = uniq // (G * G)
    gy, gx = (uniq % (G * G)) // G, uniq % G
    axes = np.array([UV_AXES[f // 2] for f in range(6)])
    vp_pos = np.zeros((len(uniq), 3))
    ax_n = vface // 2
    rows = np.arange(len(uniq))
    vp_pos[rows, ax_n] = np.where(vface % 2 == 1, box_hi[ax_n], box_lo[ax_n])
    a_u, a_v = axes[vface, 0], axes[vface, 1]
    vp_pos[rows, a_u] = box_lo[a_u] + (box_hi[a_u] - box_lo[a_u]) * gx / (G - 1)
    vp_pos[rows, a_v] = box_lo[a_v] + (box_hi[a_v] - box_lo[a_v]) * gy / (G - 1)

    # ---- which hemicube slots each viewpoint needs
    V = len(vp_pos)
    dom = DOMAIN[vface].reshape(V * N_SLOTS, 4)
    rect = dom.copy()
    if region is None or region.tree_keys is None:
        slots = _slots_seeing(vp_pos, vface, lo, hi)
    else:
        tk = (uniq[:, None] * N_SLOTS + np.arange(N_SLOTS)).ravel()
        pos = np.clip(np.searchsorted(region.tree_keys, tk), 0, max(len(region.tree_keys) - 1, 0))
        found = (region.tree_keys[pos] == tk) if len(region.tree_keys) else np.zeros(len(tk), bool)
        slots = found.reshape(V, N_SLOTS)          # the cameras' own rays use these slots
        r = region.rects[pos[found]]
        rect[found] = np.stack([np.maximum(r[:, 0], dom[found, 0]), np.minimum(r[:, 1], dom[found, 1]),
                                np.maximum(r[:, 2], dom[found, 2]), np.minimum(r[:, 3], dom[found, 3])], 1)
    dirf = Forest.empty(dom)
    trees = np.flatnonzero(slots.ravel())
    tracer = _Tracer(st, vp_pos, workers, lambda f: None, cancel)
    samples = Samples.empty()
    index = _SampleIndex()
    Gd = (1 << M) + 1
    tree_vp = np.arange(V * N_SLOTS) // N_SLOTS
    tree_cube = CUBE[vface[tree_vp], np.arange(V * N_SLOTS) % N_SLOTS]

    def uv_of(tr, gxy):
        d = dom[tr]
        return (d[:, 0] + (d[:, 1] - d[:, 0]) * gxy[:, 0] / (Gd - 1),
                d[:, 2] + (d[:, 3] - d[:, 2]) * gxy[:, 1] / (Gd - 1))

    def ensure(tr, gxy, stage):
        """Sample ids for grid points (tree, gx, gy), tracing the ones not sampled yet."""
        keys = tr * Gd * Gd + gxy[:, 1] * Gd + gxy[:, 0]
        ids = index.lookup(keys)
        miss = np.flatnonzero(ids < 0)
        if len(miss):
            nk, first, inv2 = np.unique(keys[miss], return_index=True, return_inverse=True)
            t_new, g_new = tr[miss][first], gxy[miss][first]
            u, v = uv_of(t_new, g_new)
            tracer.report = lambda f: report(stage, f, "tracing")
            new = samples.extend(tracer(tree_vp[t_new], tree_cube[t_new], u, v))
            index.add(nk, new)
            ids[miss] = new[inv2.ravel()]
        return ids

    nodes = dirf.add_roots(trees)
    dirf.corner[nodes] = ensure(np.repeat(trees, 4), np.tile(CORNERS * (Gd - 1), (len(trees), 1)),
                                0).reshape(-1, 4)
    tol_ang = np.radians(params.tolerance_deg)
    tol_d = params.tolerance_dist * diag
    class_of = st.tracer.class_of
    for level in range(M):
        report(level, 0.0, f"direction level {level}")
        if len(nodes) == 0:
            break
        tr = dirf.tree_of_nodes()[nodes]
        cc = dirf.corner_coords(nodes, M)
        # only cells overlapping the tree's baked rectangle are refined
        u_lo, v_lo = uv_of(tr, cc[:, 0])
        u_hi, v_hi = uv_of(tr, cc[:, 3])
        inside = (u_hi >= rect[tr, 0]) & (u_lo <= rect[tr, 1]) & (v_hi >= rect[tr, 2]) \
            & (v_lo <= rect[tr, 3])
        nodes, tr, cc = nodes[inside], tr[inside], cc[inside]
        mid = (cc[:, 0] + cc[:, 3]) // 2
        if level < params.min_direction_depth:
            split = np.ones(len(nodes), bool)
        else:
            u, v = uv_of(tr, mid)
            tracer.report = lambda f: report(level, f, f"direction level {level}")
            ms = tracer(tree_vp[tr], tree_cube[tr], u, v)
            split = _needs_split(samples, dirf.corner[nodes], ms, class_of, tol_ang, tol_d)
            # the traced midpoint becomes a corner of the children: keep it
            mk = tr * Gd * Gd + mid[:, 1] * Gd + mid[:, 0]
            keep = np.flatnonzero(split)
            if len(keep):
                new = samples.extend(_take(ms, keep))
                index.add(mk[keep], new)
        sn = nodes[split]
        if len(sn) == 0:
            break
        kids = dirf.split(sn)                                            # (n, 4)
        kc = dirf.corner_coords(kids.ravel(), M)                         # (4n, 4, 2)
        ktr = np.repeat(tr[split], 4)
        dirf.corner[kids.ravel()] = ensure(np.repeat(ktr, 4), kc.reshape(-1, 2),
                                           level).reshape(-1, 4)
        nodes = kids.ravel()

    # ---- extra samples for two-class leaves (paper 4.3)
    report(M, 0.0, "extra samples")
    leaves = np.flatnonzero(dirf.child < 0)
    ltr = dirf.tree_of_nodes()[leaves]
    lcc = dirf.corner_coords(leaves, M)
    u_lo, v_lo = uv_of(ltr, lcc[:, 0])
    u_hi, v_hi = uv_of(ltr, lcc[:, 3])
    leaves = leaves[(u_hi >= rect[ltr, 0]) & (u_lo <= rect[ltr, 1]) & (v_hi >= rect[ltr, 2])
                    & (v_lo <= rect[ltr, 3])]
    ex = _extras(dirf, leaves, samples, class_of, tracer, tree_vp, tree_cube, uv_of, M, Gd,
                 params.search_steps, lambda f: report(M, f, "extra samples"))
    report(M + 1, 1.0, "done")
    tree = RITree(params=params, box_lo=box_lo, box_hi=box_hi, diag=diag,
                  class_of=class_of.astype(np.int64), vp_forest=vpf, vp_pos=vp_pos,
                  vp_face=vface.astype(np.int64), dir_forest=dirf, dir_rect=rect,
                  samples=samples, **ex,
                  meta={"fingerprint": fingerprint(st.scene.object, st.scene.render.max_events),
                        "region": (region or Region()).describe(),
                        "bake_seconds": round(time.perf_counter() - t0, 3),
                        "rays_traced": int(tracer.rays), "viewpoints": int(V),
                        "direction_trees": int(len(trees)), "samples": int(len(samples)),
                        "extra_cells": int(len(ex["ex_node"]))})
    return tree


def _take(s: Samples, idx) -> Samples:
    return Samples(**{k: getattr(s, k)[idx] for k in ("out_o", "out_d", "point", "normal",
                                                      "patch", "null", "tree")})


def _cls(samples: Samples, ids, class_of):
    p = samples.patch[ids]
    return np.where(p >= 0, class_of[np.maximum(p, 0)], -1)


def _needs_split(samples, corner, ms: Samples, class_of, tol_ang, tol_d):
    """Split test of cells with corner sample ids ``corner`` (N, 4) and traced midpoints ``ms``."""
    cc = _cls(samples, corner, class_of)
    cm = np.where(ms.patch >= 0, class_of[np.maximum(ms.patch, 0)], -1)
    cn = samples.null[corner]
    disagree = np.any(cc != cm[:, None], axis=1) | np.any(cn != ms.null[:, None], axis=1)
    usable = (cc == cm[:, None]) & ~cn
    half = np.full(len(corner), 0.5)
    w, st = cell_weights(usable, half, half)
    smooth = ~disagree & ~ms.null & (cm >= 0)
    err = np.zeros(len(corner), bool)
    if np.any(smooth):
        i = np.flatnonzero(smooth)
        wi = w[i][:, :, None]
        ci = corner[i]
        od = np.einsum("nkc,nk->nc", samples.out_d[ci].astype(np.float64), w[i])
        od /= np.maximum(np.linalg.norm(od, axis=1), 1e-300)[:, None]
        nm = (samples.normal[ci].astype(np.float64) * wi).sum(1)
        nm /= np.maximum(np.linalg.norm(nm, axis=1), 1e-300)[:, None]
        oo = (samples.out_o[ci].astype(np.float64) * wi).sum(1)
        pt = (samples.point[ci].astype(np.float64) * wi).sum(1)
        err[i] = ((angle_between(od, ms.out_d[i].astype(np.float64)) > tol_ang)
                  | (angle_between(nm, ms.normal[i].astype(np.float64)) > tol_ang)
                  | (np.linalg.norm(oo - ms.out_o[i], axis=1) > tol_d)
                  | (np.linalg.norm(pt - ms.point[i], axis=1) > tol_d)
                  | (st[i] == FAIL))
    return disagree | err


def _slots_seeing(vp_pos, vface, lo, hi):
    """(V, 5) whether any of a SLOT_PROBE^2 grid of directions of each hemicube slot reaches the
    object's (unpadded) box from the viewpoint."""
    g = (np.arange(SLOT_PROBE) + 0.5) / SLOT_PROBE
    gu, gv = np.meshgrid(g, g, indexing="ij")
    gu, gv = gu.ravel(), gv.ravel()
    V = len(vp_pos)
    out = np.zeros((V, N_SLOTS), bool)
    for s in range(N_SLOTS):
        dom = DOMAIN[vface, s]                                            # (V, 4)
        u = dom[:, None, 0] + (dom[:, None, 1] - dom[:, None, 0]) * gu
        v = dom[:, None, 2] + (dom[:, None, 3] - dom[:, None, 2]) * gv
        d = cube_to_dir(np.repeat(CUBE[vface, s], len(gu)), u.ravel(), v.ravel())
        o = np.repeat(vp_pos, len(gu), axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - o) / d, (hi - o) / d
        zero = d == 0
        ins = (o >= lo) & (o <= hi)
        tn = np.where(zero, np.where(ins, -np.inf, np.inf), np.minimum(t1, t2)).max(1)
        tf = np.where(zero, np.where(ins, np.inf, -np.inf), np.maximum(t1, t2)).min(1)
        out[:, s] = (np.maximum(tn, 0) <= tf).reshape(V, -1).any(1)
    return out


def _extras(dirf, leaves, samples, class_of, tracer, tree_vp, tree_cube, uv_of, M, Gd, steps,
            report):
    """Extra samples of two-class leaves. Corner slots c0..c3 = (0,0), (1,0), (0,1), (1,1);
    edges are searched from a corner of one class towards its neighbour of the other class.

    one-interpolant (kind 1): lone corner L; v1 on the edge L->(L^1) (x edge), v2 on L->(L^2)
    (y edge), both in L's class; v3, v4 the other-class ends of the same brackets.
    two-interpolant (kind 2): corners A1, A2 of class A on one side, edges A1->B1, A2->B2;
    v1, v2 in class A (on those edges), v3, v4 in class B (same edges).
    ``ex_corner`` stores (L, -1, -1, -1) or (A1, A2, B1, B2)."""
    corner = dirf.corner[leaves]
    valid = np.all(corner >= 0, axis=1)
    leaves, corner = leaves[valid], corner[valid]
    cls = np.where(samples.null[corner], -2, _cls(samples, corner, class_of))
    srt = np.sort(cls, axis=1)
    # exactly two classes: sorted row is a a b b, a b b b or a a a b
    two = (srt[:, 0] != srt[:, 3]) & (np.sum(srt[:, 1:] != srt[:, :-1], axis=1) == 1)
    leaves, corner, cls = leaves[two], corner[two], cls[two]
    first = cls == cls[:, :1]
    n_first = first.sum(1)
    # the lone corner of a 1-vs-3 cell
    lone = np.where(n_first == 1, np.argmax(first, 1), np.where(n_first == 3, np.argmin(first, 1), -1))
    # two-vs-two: adjacent pairs share an edge (same row: c0c1 / c2c3, or same column: c0c2 / c1c3)
    pair = n_first == 2
    same_row = pair & (first[:, 0] == first[:, 1])
    same_col = pair & (first[:, 0] == first[:, 2])
    kind = np.where(lone >= 0, 1, np.where(same_row | same_col, 2, 0))
    sel = kind > 0
    leaves, corner, kind, lone = leaves[sel], corner[sel], kind[sel], lone[sel]
    same_row, same_col = same_row[sel], same_col[sel]
    E = len(leaves)
    # edges (start corner, end corner) to search: two per cell
    e_from = np.zeros((E, 2), np.int64)
    e_to = np.zeros((E, 2), np.int64)
    k1 = kind == 1
    e_from[k1] = lone[k1, None]
    e_to[k1, 0] = lone[k1] ^ 1
    e_to[k1, 1] = lone[k1] ^ 2
    # two-interpolant: same row -> vertical edges c0->c2, c1->c3; same column -> c0->c1, c2->c3
    e_from[same_row] = [0, 1]
    e_to[same_row] = [2, 3]
    e_from[same_col] = [0, 2]
    e_to[same_col] = [1, 3]
    ex_corner = -np.ones((E, 4), np.int64)
    ex_corner[k1, 0] = lone[k1]
    k2 = kind == 2
    ex_corner[k2] = np.concatenate([e_from[k2], e_to[k2]], axis=1)

    tr = dirf.tree_of_nodes()[leaves]
    cc = dirf.corner_coords(leaves, M).astype(np.float64)               # (E, 4, 2) grid coords
    rows = np.arange(E)[:, None]
    p0 = cc[rows, e_from]                                               # (E, 2, 2)
    p1 = cc[rows, e_to]
    c_from = np.where(samples.null[corner[rows, e_from]], -2, _cls(samples, corner[rows, e_from], class_of))
    lo_f = np.zeros((E, 2))                                             # fraction in start class
    hi_f = np.ones((E, 2))                                              # fraction in other class
    lo_s = corner[rows, e_from].copy()
    hi_s = corner[rows, e_to].copy()
    trr = np.repeat(tr, 2)
    for step in range(steps):
        report(step / max(steps, 1))
        f = 0.5 * (lo_f + hi_f)
        g = p0 + (p1 - p0) * f[..., None]                              # (E, 2, 2)
        u, v = uv_of(trr, g.reshape(-1, 2))
        s = tracer(tree_vp[trr], tree_cube[trr], u, v)
        c = np.where(s.null, -2, np.where(s.patch >= 0, class_of[np.maximum(s.patch, 0)], -1)).reshape(E, 2)
        ids = samples.extend(s).reshape(E, 2)
        same = c == c_from
        lo_f = np.where(same, f, lo_f)
        lo_s = np.where(same, ids, lo_s)
        hi_f = np.where(same, hi_f, f)
        hi_s = np.where(same, hi_s, ids)
    # local cell coordinates of the bracket ends
    a = CORNERS[e_from].astype(np.float64)                             # (E, 2, 2)
    b = CORNERS[e_to].astype(np.float64)
    pos_lo = a + (b - a) * lo_f[..., None]
    pos_hi = a + (b - a) * hi_f[..., None]
    ex_ids = np.concatenate([lo_s, hi_s], axis=1)                       # v1 v2 (start class), v3 v4
    ex_pos = np.concatenate([pos_lo, pos_hi], axis=1).astype(np.float32)
    order = np.argsort(leaves)
    return {"ex_node": leaves[order], "ex_kind": kind[order].astype(np.int8),
            "ex_ids": ex_ids[order], "ex_pos": ex_pos[order], "ex_corner": ex_corner[order]}
