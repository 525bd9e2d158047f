"""Ray-box slab intervals, zero-safe (the one implementation the tracer, renderer and RI-Tree
share; the BVH keeps its own pairwise variant)."""

from __future__ import annotations

import numpy as np


def slab_intervals(o, d, lo, hi):
    """Per-axis parameter intervals (tnear, tfar), each (N, 3), of rays o + t d within the slabs
    of boxes [lo, hi] (lo/hi (3,) or (N, 3)). A zero direction component gives (-inf, inf)
    inside its slab and an empty interval (inf, -inf) outside, never NaN."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o) / d
        t2 = (hi - o) / d
    zero = d == 0.0
    tnear, tfar = np.minimum(t1, t2), np.maximum(t1, t2)
    if zero.any():
        ins = (o >= lo) & (o <= hi)
        tnear = np.where(zero, np.where(ins, -np.inf, np.inf), tnear)
        tfar = np.where(zero, np.where(ins, np.inf, -np.inf), tfar)
    return tnear, tfar
