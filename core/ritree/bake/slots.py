"""Viewpoints and the direction trees they get: corner viewpoints of viewpoint cells (shared
corners sampled once), the hemicube slots each new viewpoint bakes and the (u, v) rectangle
of each (the region's, or every slot that can see the object over its whole domain), and the
conservative frustum tests behind them."""

from __future__ import annotations

import numpy as np

from ..dircube import CUBE, DOMAIN, N_SLOTS, U_AXIS, UV_AXES, V_AXIS

SLOT_MIN_DEPTH = 1e-9      # object-box parts nearer than this (x its extent) along a slot's
                            # axis are ignored by the slot test (they project to infinity)
_BOX_CORNERS = np.array([[(i >> k) & 1 for k in range(3)] for i in range(8)], bool)   # (8, 3)
_FACE_AXES = np.array([UV_AXES[k // 2] for k in range(6)])                           # (6, 2)


def add_viewpoints(cfg, state, leaves) -> np.ndarray:
    """Give viewpoint-forest ``leaves`` their corner viewpoint ids in ``state``, creating the
    ones not there yet (keyed on the finest viewpoint grid); returns the new viewpoints' ids."""
    vpf = state.vpf
    face = vpf.tree_of_nodes()[leaves]
    cc = vpf.corner_coords(leaves, cfg.Dmax)                             # (L, 4, 2)
    G = cfg.Gv
    keys = face[:, None] * G * G + cc[..., 1] * G + cc[..., 0]
    uk = np.unique(keys)
    vk = state.vp_key
    pos = np.searchsorted(vk, uk)
    have = (pos < len(vk)) & (vk[np.minimum(pos, len(vk) - 1)] == uk) if len(vk) else \
        np.zeros(len(uk), bool)
    new_keys = uk[~have]
    start = len(state.vp_key)
    f = new_keys // (G * G)
    gy, gx = (new_keys % (G * G)) // G, new_keys % G
    pos3 = np.zeros((len(new_keys), 3))
    ax = f // 2
    rows = np.arange(len(new_keys))
    lo, hi = cfg.box_lo, cfg.box_hi
    pos3[rows, ax] = np.where(f % 2 == 1, hi[ax], lo[ax])
    a_u, a_v = _FACE_AXES[f, 0], _FACE_AXES[f, 1]
    pos3[rows, a_u] = lo[a_u] + (hi[a_u] - lo[a_u]) * gx / (G - 1)
    pos3[rows, a_v] = lo[a_v] + (hi[a_v] - lo[a_v]) * gy / (G - 1)
    # ids follow creation order; vp_key keeps the keys sorted for lookups
    state.vp_pos = np.concatenate([state.vp_pos, pos3])
    state.vp_face = np.concatenate([state.vp_face, f])
    ids_all = np.concatenate([np.arange(start), start + rows])
    keys_all = np.concatenate([state.keys_by_id, new_keys])
    order = np.argsort(keys_all)
    state.vp_key, state.vp_key_id = keys_all[order], ids_all[order]
    state.keys_by_id = keys_all
    vpf.corner[leaves] = state.vp_key_id[np.searchsorted(state.vp_key, keys)]
    return start + rows


def add_trees(cfg, state, region, level, vps) -> np.ndarray:
    """Direction trees for the newest viewpoints ``vps``, created at viewpoint level ``level``:
    every hemicube slot gets a tree's domain and rectangle (the domain clipped to what
    ``region`` needs there); returns the ids of the trees to bake (the slots needed)."""
    n = len(vps)
    dom = DOMAIN[state.vp_face[vps]]                                     # (n, 5, 4)
    needed, rects = _slots_and_rects(cfg, state, region, level, vps, dom)
    rects = np.stack([np.maximum(rects[..., 0], dom[..., 0]),
                      np.minimum(rects[..., 1], dom[..., 1]),
                      np.maximum(rects[..., 2], dom[..., 2]),
                      np.minimum(rects[..., 3], dom[..., 3])], -1)
    first = len(state.dirf.root)                    # = 5 * vps[0]: vps are the newest
    state.dirf.domain = np.concatenate([state.dirf.domain, dom.reshape(-1, 4)])
    state.dirf.root = np.concatenate([state.dirf.root, -np.ones(n * N_SLOTS, np.int64)])
    state.rect = np.concatenate([state.rect, rects.reshape(-1, 4)])
    return first + np.flatnonzero(needed.ravel())


def _slots_and_rects(cfg, state, region, level, vps, dom):
    """(needed (n, 5), rects (n, 5, 4)) of viewpoints ``vps`` with slot domains ``dom``:
    ``region``'s at viewpoint ``level``, or every slot that can see the object over its whole
    domain (no region)."""
    if region is None or region.tree_keys is None:
        return (_slots_seeing(state.vp_pos[vps], state.vp_face[vps], cfg.st.tracer.lo,
                              cfg.st.tracer.hi), dom.copy())
    keys, rects = region.rects_at(level)
    tk = (state.keys_by_id[vps][:, None] * N_SLOTS + np.arange(N_SLOTS)).ravel()
    pos = np.clip(np.searchsorted(keys, tk), 0, max(len(keys) - 1, 0))
    found = (keys[pos] == tk) if len(keys) else np.zeros(len(tk), bool)
    out = dom.reshape(-1, 4).copy()
    out[found] = rects[pos[found]]
    return found.reshape(-1, N_SLOTS), out.reshape(-1, N_SLOTS, 4)


def _slots_seeing(vp_pos, vface, lo, hi):
    """(V, 5) whether the object's box [lo, hi] meets each hemicube slot's frustum from each
    viewpoint (conservative: ``rect_sees_boxes`` on the slot domains)."""
    V = len(vp_pos)
    out = np.zeros((V, N_SLOTS), bool)
    ext = np.max(hi - lo)
    for s in range(N_SLOTS):
        dom = DOMAIN[vface, s]
        out[:, s] = rect_sees_boxes(vp_pos, CUBE[vface, s], dom, np.broadcast_to(lo, (V, 3)),
                                    np.broadcast_to(hi, (V, 3)), ext)
    return out


def rects_see_object(tracer, p, cube, rect):
    """(k,) whether some ray from ``p`` (k, 3) through cube-face rectangles ``rect`` (k, 4) on
    faces ``cube`` (k,) may meet the object of ``tracer`` (trace.patches.PatchTracer):
    conservative, on the boxes of its flat sub-patches and triangles (its BVHs)."""
    out = np.zeros(len(p), bool)
    bvhs = [tracer.bvh] + ([tracer.meshes.bvh] if tracer.meshes is not None else [])
    for bvh in (b for b in bvhs if b is not None):
        out |= bvh.any_box(len(p), lambda q, lo, hi: rect_sees_boxes(p[q], cube[q], rect[q], lo,
                                                                     hi, tracer.diag))
    return out


def rect_sees_boxes(p, cube, rect, lo, hi, ext):
    """(k,) whether some ray from points ``p`` (k, 3) with a direction in the cube-face
    rectangle ``rect`` (k, 4: u0, u1, v0, v1 on cube faces ``cube`` (k,)) may meet the boxes
    [lo, hi] (k, 3) (conservative). The face has axis b: the part of a box in front of p along b
    (depth >= SLOT_MIN_DEPTH * ``ext``) is again a box, the central projection of its corners
    bounds its image on the face, and that bound must overlap the rectangle."""
    k = len(p)
    rows = np.arange(k)
    b = cube // 2
    sign = np.where(cube % 2 == 1, 1.0, -1.0)
    p_b = p[rows, b]
    front = p_b + sign * SLOT_MIN_DEPTH * (ext + 1e-300)
    lo_c, hi_c = np.array(lo, np.float64), np.array(hi, np.float64)
    lo_c[rows, b] = np.where(sign > 0, np.maximum(lo_c[rows, b], front), lo_c[rows, b])
    hi_c[rows, b] = np.where(sign > 0, hi_c[rows, b], np.minimum(hi_c[rows, b], front))
    ok = lo_c[rows, b] <= hi_c[rows, b]
    pts = np.where(_BOX_CORNERS[None], hi_c[:, None, :], lo_c[:, None, :])    # (k, 8, 3)
    rel = pts - p[:, None, :]
    col = np.arange(8)[None]
    depth = np.where(ok[:, None], sign[:, None] * rel[rows[:, None], col, b[:, None]], 1.0)
    u = rel[rows[:, None], col, U_AXIS[b][:, None]] / depth
    v = rel[rows[:, None], col, V_AXIS[b][:, None]] / depth
    return ok & (u.max(1) >= rect[:, 0]) & (u.min(1) <= rect[:, 1]) \
        & (v.max(1) >= rect[:, 2]) & (v.min(1) <= rect[:, 3])
