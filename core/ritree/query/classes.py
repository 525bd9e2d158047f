"""The class of each located ray (paper 4.2, the two-patch condition): one class among its 16
samples is the ray's; two classes are told apart by the exact first hit against only their
candidate patches; more than two are decided by the exact first hit against every patch
(QueryOptions.many_classes "first_hit") or traced (the paper)."""

from __future__ import annotations

import numpy as np

from ..answers import MISS, WHY_CLASSES, WHY_UNSAMPLED
from .certify import first_hits


def classify(q, b) -> None:
    """``b.pc``: the class of each located ray (-1: miss; -2: traced)."""
    with b.clock("group"):
        srt = np.sort(b.sets.cls, axis=1)
        n_cls = 1 + np.sum(srt[:, 1:] != srt[:, :-1], axis=1)
        r_n = n_cls[b.set_of]
        rows = b.loc.ray
        pc = np.where(r_n == 1, srt[b.set_of, 0], -2)
        two = np.flatnonzero(r_n == 2)
        many = np.flatnonzero(r_n > 2)
        if q.opt.many_classes == "trace":
            b.trace(rows[many], WHY_CLASSES)
            many = many[:0]
    if len(two) or len(many):
        with b.clock("first_hits"):
            hit = first_hits(q, b, rows[two], b.loc.take(two),
                             srt[b.set_of[two]][:, [0, -1]]) if len(two) else None
            if len(two):
                b.known.add(rows[two], hit)
                pc[two] = first_hit_class(q, b, two, np.flatnonzero(n_cls == 2), hit)
            if len(many):
                pc[many] = first_hit_of_many(q, b, many, srt[b.set_of[many]])
    b.exact_first_hits = len(two) + len(many)
    b.ans[rows[pc == -1]] = MISS
    b.pc = pc
    b.loc_pc = pc.copy()


def first_hit_class(q, b, two, two_sets, hit) -> np.ndarray:
    """Class of the exact first hit (-1: miss) of the located rays ``two`` against only the
    distinct patches of their two-class sets (``two_sets``, sorted). ``hit``, their first hits
    against every patch, decides where the nearest hit is a candidate's or there is none; the
    few rays whose nearest hit is another patch's are searched again against their candidates
    only."""
    rows = b.loc.ray[two]
    pat = np.sort(q.table.patch[b.sets.ids[two_sets]].astype(np.int64), axis=1)
    dup = np.zeros_like(pat, bool)
    dup[:, 1:] = pat[:, 1:] == pat[:, :-1]
    cand = np.where(dup | (pat < 0), -1, pat)
    cand = cand[np.searchsorted(two_sets, b.set_of[two])]
    cls = np.where(hit.hit, hit.cls, -1)
    other = np.flatnonzero(hit.hit & ~np.any(cand == hit.patch[:, None], axis=1))
    if len(other):
        r = rows[other]
        h2 = q.st.tracer.intersect(b.o[r], b.d[r], tmax=b.tmax[r], patches=cand[other])
        cls[other] = np.where(h2.hit, h2.cls, -1)
    return cls


def first_hit_of_many(q, b, many, srt) -> np.ndarray:
    """Class of the exact first hit against every patch (-1: miss) of the located rays
    ``many``, whose sets hold more than two classes (``srt``: each ray's samples' classes,
    sorted). A ray whose hit is of a class none of its samples has is traced (WHY_UNSAMPLED):
    -2."""
    rows = b.loc.ray[many]
    distinct = np.where(np.diff(srt, axis=1, prepend=-2) != 0, srt, -1)
    hit = first_hits(q, b, rows, b.loc.take(many), distinct)
    b.known.add(rows, hit)
    cls = np.where(hit.hit, hit.cls, -1)
    sampled = np.any(srt == cls[:, None], axis=1) | (cls == -1)
    b.trace(rows[~sampled], WHY_UNSAMPLED)
    return np.where(sampled, cls, -2)
