"""Exact first hits without the full search where the samples and the occlusion proxy vouch
for them (QueryOptions.certify_first_hits).

The query needs the exact first hit of rays whose samples disagree on the class (two or more
classes among the 16, or a miss the bake did not verify). The full search (BVH walk, candidate
pairs, root finding) costs 20-40 us a ray; this costs about a third of that:

- Newton from the parameters of the ray's heaviest sample of each class its samples hit
  (``trace.polish``), the nearest root kept: a hit on that patch, not yet known the nearest;
- the fine triangle proxy (``trace.proxy``): a ray with a root whose segment from its origin
  to the root (less the end stretch the proxy cannot look at) meets no proxy triangle hits
  nothing nearer, so the root is its first hit; a ray without a root that meets no proxy
  triangle up to its tmax misses the object.

Rays neither certifies (a proxy triangle in the way, a root at a grazing angle where the
untested end stretch is long) get the full search. What the stretch next to a certified hit
could hide is another crossing within a few proxy deviations of it, which the ray's samples
vouch against (their classes are the candidates Newton tried).
"""

from __future__ import annotations

import numpy as np

from ...trace.hits import PatchHit
from ...trace.patches import T_MIN_REL
from ...trace.polish import Seeds, polish_hits
from ...trace.proxy import MIN_END_SINE
from ..answers import COL
from .sets import corner_weights

# A root is kept within this distance of its seed sample's hit (relative to the box diagonal)
# and with a normal within this angle of the seed's: the proxy decides whether it is the
# nearest, so the limits only keep Newton from wandering to far crossings; those of the path
# solver (query/paths.py), measured on the sample scenes' close views (every root kept there
# was the full search's first hit).
CERTIFY_MAX_MOVE_REL = 5e-2
CERTIFY_MAX_TURN_DEG = 30.0


def first_hits(q, b, rows, loc=None, classes=None) -> PatchHit:
    """Exact first hits (within their tmax) of query rays ``rows``: certified where the proxy
    allows (``q.proxy``; none: every ray searched), the full search for the others.
    ``loc`` (Located, n rows) and ``classes`` (n, K: classes of each ray's samples, -1 unused)
    give Newton its candidates; without them only misses are certified."""
    n = len(rows)
    if q.proxy is None or not q.opt.certify_first_hits or n == 0:
        return q.st.tracer.intersect(b.o[rows], b.d[rows], tmax=b.tmax[rows])
    o, d, tmax = b.o[rows], b.d[rows], b.tmax[rows]
    roots = PatchHit.misses(n) if classes is None else _nearest_roots(q, o, d, tmax, loc,
                                                                      classes)
    sine = np.abs(np.einsum("ij,ij->i", d, roots.normal))
    steep = roots.hit & (sine >= MIN_END_SINE)
    end = np.where(steep, roots.t - q.proxy.end_stretch(d, roots.normal), tmax)
    look = np.flatnonzero(steep | ~roots.hit)
    clear = np.zeros(n, bool)
    clear[look] = ~q.proxy.mesh.any_hit(o[look], d[look], np.zeros(len(look)),
                                        np.maximum(end[look], 0.0))
    out = PatchHit.misses(n)
    good = np.flatnonzero(clear & roots.hit)
    out.put(good, roots.take(good))
    rest = np.flatnonzero(~clear)
    if len(rest):
        out.put(rest, q.st.tracer.intersect(o[rest], d[rest], tmax=tmax[rest]))
    b.certified_first_hits += n - len(rest)
    return out


def _nearest_roots(q, o, d, tmax, loc, classes) -> PatchHit:
    """The nearest Newton root of each ray over its candidate ``classes`` (n, K), each from
    the parameters of the ray's heaviest sample of that class (one Newton run over every
    (ray, class) pair)."""
    n = len(o)
    ids, w = corner_weights(q.tree, loc)
    ray, slot = np.nonzero(classes >= 0)
    wk = np.where(q.table.cls[ids[ray]] == classes[ray, slot, None], w[ray], -1.0)
    sid = ids[ray, np.argmax(wk, axis=1)]
    seeds = Seeds(q.table.patch[sid].astype(np.int64),
                  q.table.vals[sid][:, COL.UV].astype(np.float64), None, None)
    move, cos = CERTIFY_MAX_MOVE_REL * q.tree.diag, np.cos(np.radians(CERTIFY_MAX_TURN_DEG))
    h = polish_hits(q.st.tracer, o[ray], d[ray], seeds, move, cos,
                    np.full(len(ray), T_MIN_REL * q.tree.diag), tmax[ray])
    # per ray, the pair with the nearest root: sorted by ray, then t (misses last)
    order = np.lexsort((h.t, ray))
    first = order[np.flatnonzero(np.diff(ray[order], prepend=-1) != 0)]
    best = PatchHit.misses(n)
    keep = first[h.hit[first]]
    best.put(ray[keep], h.take(keep))
    return best
