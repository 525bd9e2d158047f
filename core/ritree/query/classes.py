"""The class of each located ray (paper 4.2, the two-patch condition): one class among its 16
samples is the ray's; two classes are told apart by the exact first hit against only their
candidate patches; more than two are traced."""

from __future__ import annotations

import numpy as np

from ..answers import MISS, WHY_CLASSES


def classify(q, b) -> None:
    """``b.pc``: the class of each located ray (-1: miss; -2: traced, more than two classes)."""
    with b.clock("group"):
        srt = np.sort(b.sets.cls, axis=1)
        n_cls = 1 + np.sum(srt[:, 1:] != srt[:, :-1], axis=1)
        r_n = n_cls[b.set_of]
        rows = b.loc.ray
        b.trace(rows[r_n > 2], WHY_CLASSES)
        pc = np.where(r_n == 1, srt[b.set_of, 0], -2)
        two = np.flatnonzero(r_n == 2)
    if len(two):
        with b.clock("first_hits"):
            pc[two] = first_hit_class(q, b, two, np.flatnonzero(n_cls == 2))
    b.exact_first_hits = len(two)
    b.ans[rows[pc == -1]] = MISS
    b.pc = pc


def first_hit_class(q, b, two, two_sets) -> np.ndarray:
    """Class of the exact first hit (-1: miss) of the located rays ``two`` against only the
    distinct patches of their two-class sets (``two_sets``, sorted). One tracer call against
    every patch finds it where the nearest hit is a candidate's or there is none (it is kept in
    ``b.known`` for the trace stage); the few rays whose nearest hit is another patch's are
    searched again against their candidates only."""
    o, d, tmax, tracer = b.o, b.d, b.tmax, q.st.tracer
    rows = b.loc.ray[two]
    pat = np.sort(q.table.patch[b.sets.ids[two_sets]].astype(np.int64), axis=1)
    dup = np.zeros_like(pat, bool)
    dup[:, 1:] = pat[:, 1:] == pat[:, :-1]
    cand = np.where(dup | (pat < 0), -1, pat)
    cand = cand[np.searchsorted(two_sets, b.set_of[two])]
    hit = tracer.intersect(o[rows], d[rows], tmax=tmax[rows])
    b.known.add(rows, hit)
    cls = np.where(hit.hit, hit.cls, -1)
    other = np.flatnonzero(hit.hit & ~np.any(cand == hit.patch[:, None], axis=1))
    if len(other):
        r = rows[other]
        h2 = tracer.intersect(o[r], d[r], tmax=tmax[r], patches=cand[other])
        cls[other] = np.where(h2.hit, h2.cls, -1)
    return cls
