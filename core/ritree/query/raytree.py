"""Bala et al.'s policy (QueryOptions.policy "raytree", for comparison): interpolate (16
samples, bilinear at both levels) only where all 16 samples share one ray tree and class and
none is null; trace otherwise. Decided once per sample set."""

from __future__ import annotations

import numpy as np

from ..answers import COL, FULL, MISS, WHY_BLEND, WHY_RAYTREE
from ..interp import bilinear_weights
from .blend import MIN_BLEND_NORM, blend
from .fill import Blended, fill
from .sets import SET_CORNERS, SetItems, group


def raytree(q, b) -> None:
    """Answer the located rays ``b.loc`` by the ray-tree rule."""
    tab = q.table
    group(q, b)
    s_ids, s_cls, set_of = b.sets.ids, b.sets.cls, b.set_of
    with b.clock("group"):
        th = tab.tree[s_ids]
        same = np.all(th == th[:, :1], axis=1) & np.all(s_cls == s_cls[:, :1], axis=1) \
            & ~np.any(tab.null[s_ids], axis=1)
        r_same = same[set_of]
        rows = b.loc.ray
        b.ans[rows[r_same & (s_cls[set_of, 0] == -1)]] = MISS
        b.trace(rows[~r_same], WHY_RAYTREE)
    with b.clock("blend"):
        g = np.flatnonzero(r_same & (s_cls[set_of, 0] != -1))
        if len(g) == 0:
            return
        loc = b.loc
        wq = bilinear_weights(loc.alpha[g], loc.beta[g])
        wdq = bilinear_weights(loc.lx[g], loc.ly[g])                    # (g, 4, 4)
        weights = (wq[:, :, None] * wdq).reshape(len(g), SET_CORNERS)
        sg = set_of[g]
        items = SetItems.of(q.tree, b.sets.leaf, s_ids)
        out = blend(items.corner_vals, sg, weights)
        od, nm = out[:, COL.OUT_D], out[:, COL.NORMAL]
        lod, lnm = np.linalg.norm(od, axis=1), np.linalg.norm(nm, axis=1)
        ok = (lod > MIN_BLEND_NORM) & (lnm > MIN_BLEND_NORM)      # opposed samples: traced
        b.trace(rows[g[~ok]], WHY_BLEND)
        g, sg, out, od, nm, lod, lnm = (a[ok] for a in (g, sg, out, od, nm, lod, lnm))
        b.ans[rows[g]] = FULL
        fill(q, b, Blended(rows=rows[g], oo=out[:, COL.OUT_O], od=od / lod[:, None],
                           pt=out[:, COL.POINT], nm=nm / lnm[:, None],
                           cls=s_cls[sg, 0].astype(np.int64),
                           patch=tab.patch[s_ids[sg, 0]].astype(np.int64)))
