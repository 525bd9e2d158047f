"""The class of each located ray (paper 4.2, the two-patch condition): one class among its 16
samples is the ray's; two classes are told apart by the exact first hit against only their
candidate patches (found by Newton from the samples where the occlusion proxy certifies it); more than two are decided by the exact first hit against every patch
(QueryOptions.many_classes "first_hit") or traced (the paper)."""

from __future__ import annotations

import numpy as np

from ...trace.patches import T_MIN_REL, PatchHit
from ...trace.polish import Seeds, polish_hits
from ...trace.proxy import GRAZING_SINE
from ..answers import COL, MISS, WHY_CLASSES, WHY_UNSAMPLED
from .sets import corner_weights


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
            if len(two):
                hit = first_hits(q, b, two, srt)
                b.known.add(rows[two], hit)
                pc[two] = first_hit_class(q, b, two, np.flatnonzero(n_cls == 2), hit)
            if len(many):
                pc[many] = first_hit_of_many(q, b, many, srt)
    b.exact_first_hits = len(two) + len(many)
    b.ans[rows[pc == -1]] = MISS
    b.pc = pc
    b.loc_pc = pc.copy()


def first_hits(q, b, two, srt) -> PatchHit:
    """The exact first hits (against every patch, within tmax) of the located two-class rays
    ``two`` (``srt``: each set's classes, sorted). Where the query has its occlusion proxy
    (QueryOptions.solve_paths), Newton from the heaviest sample of each class on that sample's
    patch finds a root first, kept where nothing meets the proxy before it and the ray is not
    grazing there (then it is the nearest hit); the others are searched for in full."""
    rows = b.loc.ray[two]
    o, d, tmax = b.o[rows], b.d[rows], b.tmax[rows]
    hit = PatchHit.misses(len(two))
    if q.proxy is not None:
        hit = newton_first_hits(q, b.loc.take(two), o, d, tmax, srt[b.set_of[two]])
        b.newton_first_hits = int(hit.hit.sum())
    rest = np.flatnonzero(~hit.hit)
    if len(rest):
        hit.put(rest, q.st.tracer.intersect(o[rest], d[rest], tmax=tmax[rest]))
    return hit


def newton_first_hits(q, loc, o, d, tmax, classes) -> PatchHit:
    """Hits of rays ``o``, ``d`` found by Newton from the heaviest sample of each of their two
    classes (``classes`` (n, k) sorted: the first and last), the nearer kept where the proxy
    certifies it is the first (trace.proxy); the others are misses here."""
    tracer, n = q.st.tracer, len(o)
    ids, w = corner_weights(q.tree, loc)
    cls = q.table.cls[ids]
    best = PatchHit.misses(n)
    floor = np.full(n, T_MIN_REL * tracer.diag)
    for c in (classes[:, 0], classes[:, -1]):
        wc = np.where(cls == c[:, None], w, -1.0)
        j = np.argmax(wc, axis=1)
        sid = ids[np.arange(n), j]
        live = np.flatnonzero((c >= 0) & (wc[np.arange(n), j] >= 0))
        seeds = Seeds(q.table.patch[sid[live]].astype(np.int64),
                      q.table.vals[sid[live], COL.UV].astype(np.float64), None, None)
        h = polish_hits(tracer, o[live], d[live], seeds, 2.0 * tracer.diag, -1.0, floor[live],
                        tmax[live])
        nearer = np.flatnonzero(h.hit & (h.t < best.t[live]))
        best.put(live[nearer], h.take(nearer))
    k = np.flatnonzero(best.hit)
    sine = np.abs(np.einsum("ij,ij->i", best.normal[k], d[k]))
    k = k[sine >= GRAZING_SINE]
    k = k[~q.proxy.crossed(o[k], d[k], best.t[k], d[k], best.normal[k])]
    out = PatchHit.misses(n)
    out.put(k, best.take(k))
    return out


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
    ``many``, whose sets hold more than two classes (``srt``: each set's classes, sorted). A
    ray whose hit is of a class none of its samples has is traced (WHY_UNSAMPLED): -2."""
    rows = b.loc.ray[many]
    hit = q.st.tracer.intersect(b.o[rows], b.d[rows], tmax=b.tmax[rows])
    b.known.add(rows, hit)
    cls = np.where(hit.hit, hit.cls, -1)
    sampled = np.any(srt[b.set_of[many]] == cls[:, None], axis=1) | (cls == -1)
    b.trace(rows[~sampled], WHY_UNSAMPLED)
    return np.where(sampled, cls, -2)
