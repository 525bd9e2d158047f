"""Generic axis-aligned bounding-box hierarchy over M primitive boxes.

Build: top-down, one vectorized pass per tree level; every node with more than ``leaf_size``
primitives is split by a binned surface-area heuristic over its primitives' centroids (the
centroid median of the longest axis where no bin plane separates them, and below
SAH_MAX_DEPTH). Nodes are stored breadth-first in flat arrays; the two children of node i are
``child[i]`` and ``child[i] + 1`` (``child == -1`` marks a leaf, whose primitives are
``perm[prim_start : prim_start + prim_count]``).

Traversal: a wavefront of (ray, node) pairs advanced level by level, all pairs at once.
Boxes are closed sets: a segment touching a box face counts as overlapping. Callers that need
conservative hits under rounding (triangles, sub-patches) pad their boxes themselves.
"""

from __future__ import annotations

import numpy as np

SAH_BINS = 16           # centroid bins per axis and node in the SAH build (15 split planes)
SAH_MAX_DEPTH = 40      # deeper levels split at the median: bounds depth by 40 + log2(M)
MAX_PAIRS = 1 << 19     # (ray, node) pairs advanced at once; bounds traversal memory (~100 MB)


def _ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concatenation of arange(s, s + c) over (starts, counts)."""
    total = int(counts.sum())
    offs = np.cumsum(counts) - counts
    return np.repeat(starts - offs, counts) + np.arange(total)


def _half_area(lo, hi):
    """Half surface area of boxes (..., 3); 0 for empty boxes (lo = +inf, hi = -inf)."""
    e = np.maximum(hi - lo, 0.0)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def _split(c, lo, hi, counts, use_sah: bool):
    """Split keys for nodes whose primitives (centroids c, boxes lo/hi) are grouped by node
    with sizes ``counts``. Returns (key, nleft): sorting each node's primitives by key puts its
    left child's nleft primitives first. Binned SAH over SAH_BINS bins per axis; nodes where no
    bin plane separates the centroids, or all nodes unless ``use_sah``, split at the
    centroid median of their longest axis."""
    s = len(counts)
    seg = np.cumsum(counts) - counts
    owner = np.repeat(np.arange(s), counts)
    cmin = np.minimum.reduceat(c, seg, axis=0)
    ext = np.maximum.reduceat(c, seg, axis=0) - cmin
    scale = SAH_BINS / np.where(ext > 0, ext, 1.0)
    bins = np.minimum(((c - cmin[owner]) * scale[owner]).astype(np.int64), SAH_BINS - 1)
    cost = np.full((s, 3, SAH_BINS - 1), np.inf)
    nl_all = np.zeros((s, 3, SAH_BINS - 1), dtype=np.int64)
    for ax in range(3 if use_sah else 0):
        gk = owner * SAH_BINS + bins[:, ax]
        order = np.argsort(gk, kind="stable")
        gks = gk[order]
        first = np.flatnonzero(np.r_[True, gks[1:] != gks[:-1]])
        blo = np.full((s * SAH_BINS, 3), np.inf)
        bhi = np.full((s * SAH_BINS, 3), -np.inf)
        bcnt = np.zeros(s * SAH_BINS, dtype=np.int64)
        blo[gks[first]] = np.minimum.reduceat(lo[order], first, axis=0)
        bhi[gks[first]] = np.maximum.reduceat(hi[order], first, axis=0)
        bcnt[gks[first]] = np.diff(np.r_[first, len(gks)])
        blo = blo.reshape(s, SAH_BINS, 3)
        bhi = bhi.reshape(s, SAH_BINS, 3)
        bcnt = bcnt.reshape(s, SAH_BINS)
        left_a = _half_area(np.minimum.accumulate(blo, axis=1),
                            np.maximum.accumulate(bhi, axis=1))[:, :-1]
        right_a = _half_area(np.minimum.accumulate(blo[:, ::-1], axis=1),
                             np.maximum.accumulate(bhi[:, ::-1], axis=1))[:, -2::-1]
        nl = np.cumsum(bcnt, axis=1)[:, :-1]
        nr = counts[:, None] - nl
        cost[:, ax] = np.where((nl > 0) & (nr > 0), left_a * nl + right_a * nr, np.inf)
        nl_all[:, ax] = nl
    flat = cost.reshape(s, -1)
    best = np.argmin(flat, axis=1)
    sah = np.isfinite(flat[np.arange(s), best])
    b_ax, b_plane = best // (SAH_BINS - 1), best % (SAH_BINS - 1)
    med_ax = np.argmax(ext, axis=1)
    rows = np.arange(len(c))
    key = np.where(sah[owner], (bins[rows, b_ax[owner]] > b_plane[owner]).astype(np.float64),
                   c[rows, med_ax[owner]])
    nleft = np.where(sah, nl_all[np.arange(s), b_ax, b_plane], counts // 2)
    return key, nleft


def _slab(o, inv, lo, hi, r, idx, t0, t1):
    """Clip [t0, t1] of rays ``r`` against boxes ``lo[:, idx]``, ``hi[:, idx]`` (closed slabs).

    o, inv: (3, N) origins and 1/dirs (+-inf on zero components). A NaN from 0 * inf (origin
    on a slab plane, zero direction component) must not constrain t: np.minimum/maximum
    propagate it and np.fmax/fmin then ignore it."""
    with np.errstate(invalid="ignore", over="ignore"):
        for ax in range(3):
            oa = o[ax][r]
            ia = inv[ax][r]
            a = (lo[ax][idx] - oa) * ia
            b = (hi[ax][idx] - oa) * ia
            t0 = np.fmax(t0, np.minimum(a, b))
            t1 = np.fmin(t1, np.maximum(a, b))
    return t0, t1


class BVH:
    """Flat BVH. Attributes: node_lo, node_hi (3, nodes); child, prim_start, prim_count (nodes,);
    perm (M,) primitive indices in leaf order; leaf_lo, leaf_hi (3, M) their boxes in that
    order."""

    def __init__(self, node_lo, node_hi, child, prim_start, prim_count, perm, leaf_lo, leaf_hi):
        self.node_lo = node_lo
        self.node_hi = node_hi
        self.child = child
        self.prim_start = prim_start
        self.prim_count = prim_count
        self.perm = perm
        self.leaf_lo = leaf_lo
        self.leaf_hi = leaf_hi

    @property
    def num_nodes(self) -> int:
        return int(self.child.shape[0])

    @classmethod
    def build(cls, lo: np.ndarray, hi: np.ndarray, leaf_size: int = 4) -> "BVH":
        """Build over primitive boxes ``lo``, ``hi`` (M, 3)."""
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        if lo.ndim != 2 or lo.shape[1] != 3 or hi.shape != lo.shape:
            raise ValueError(f"lo/hi: expected two (M, 3) arrays, got {lo.shape} and {hi.shape}")
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            raise ValueError("lo/hi: boxes must be finite")
        if np.any(lo > hi):
            raise ValueError("lo/hi: some box has lo > hi")
        if leaf_size < 1:
            raise ValueError(f"leaf_size: must be >= 1, got {leaf_size}")
        m = lo.shape[0]
        cent = 0.5 * (lo + hi)
        perm = np.arange(m)
        levels = []                                  # per level: (lo, hi, child, start, count)
        starts = np.zeros(1 if m else 0, dtype=np.int64)
        counts = np.full(starts.shape, m, dtype=np.int64)
        next_id = len(starts)
        while len(starts):
            pos = _ranges(starts, counts)            # positions in perm, grouped by node
            prims = perm[pos]
            seg = np.cumsum(counts) - counts         # node offsets within pos
            nlo = np.minimum.reduceat(lo[prims], seg, axis=0)
            nhi = np.maximum.reduceat(hi[prims], seg, axis=0)
            split = counts > leaf_size
            child = np.full(len(starts), -1, dtype=np.int64)
            child[split] = next_id + 2 * np.arange(int(split.sum()))
            levels.append((nlo, nhi, child, starts, counts))
            if not split.any():
                break
            s_starts, s_counts = starts[split], counts[split]
            spos = _ranges(s_starts, s_counts)
            sprims = perm[spos]
            key, nleft = _split(cent[sprims], lo[sprims], hi[sprims], s_counts,
                                use_sah=len(levels) <= SAH_MAX_DEPTH)
            owner = np.repeat(np.arange(len(s_starts)), s_counts)
            perm[spos] = sprims[np.lexsort((key, owner))]
            starts = np.stack([s_starts, s_starts + nleft], axis=1).ravel()
            counts = np.stack([nleft, s_counts - nleft], axis=1).ravel()
            next_id += len(starts)
        if levels:
            cat = [np.concatenate(parts) for parts in zip(*levels)]
        else:
            cat = [np.zeros((0, 3)), np.zeros((0, 3))] + [np.zeros(0, dtype=np.int64)] * 3
        node_lo, node_hi, child, pstart, pcount = cat
        return cls(np.ascontiguousarray(node_lo.T), np.ascontiguousarray(node_hi.T),
                   child, pstart, pcount, perm,
                   np.ascontiguousarray(lo[perm].T), np.ascontiguousarray(hi[perm].T))

    def _walk(self, n: int, node_meets, max_pairs: int, done=None):
        """The wavefront of (query, node) pairs from the root, ``max_pairs`` at a time: a pair
        goes on down while ``node_meets(q, nodes)`` holds; at a leaf, yields (queries, positions
        in leaf order) of its primitives, one row per (query, primitive). Queries set in
        ``done`` (read as the walk goes: the caller may set it between yields) are dropped."""
        stack = [(np.arange(n), np.zeros(n, dtype=np.int64))]
        while stack:
            q, nd = stack.pop()
            if len(q) > max_pairs:
                stack.append((q[max_pairs:], nd[max_pairs:]))
                q, nd = q[:max_pairs], nd[:max_pairs]
            if done is not None:
                live = ~done[q]
                q, nd = q[live], nd[live]
            keep = node_meets(q, nd)
            q, nd = q[keep], nd[keep]
            ch = self.child[nd]
            leaf = ch < 0
            if leaf.any():
                cnt = self.prim_count[nd[leaf]]
                yield np.repeat(q[leaf], cnt), _ranges(self.prim_start[nd[leaf]], cnt)
            inner = ~leaf
            if inner.any():
                stack.append((np.repeat(q[inner], 2), (ch[inner][:, None] + np.arange(2)).ravel()))

    def candidates(self, origins: np.ndarray, dirs: np.ndarray, tmin: np.ndarray,
                   tmax: np.ndarray, max_pairs: int = MAX_PAIRS):
        """Every (ray, primitive) whose box the segment origin + t*dir, t in [tmin, tmax],
        overlaps. Returns (ray_idx, prim_idx, t_enter) (K,), sorted by ray then t_enter, where
        t_enter = max(tmin, entry of the ray into the primitive's box).

        Direction components may be exactly 0 (the slab test then checks the origin lies
        within the slab). At most ``max_pairs`` (ray, node) pairs are advanced at once.
        """
        origins = np.asarray(origins, dtype=np.float64)
        dirs = np.asarray(dirs, dtype=np.float64)
        n = origins.shape[0]
        tmin = np.broadcast_to(np.asarray(tmin, dtype=np.float64), (n,))
        tmax = np.broadcast_to(np.asarray(tmax, dtype=np.float64), (n,))
        empty = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0))
        if n == 0 or self.num_nodes == 0:
            return empty
        o = np.ascontiguousarray(origins.T)
        with np.errstate(divide="ignore", over="ignore"):
            inv = np.ascontiguousarray((1.0 / dirs).T)   # +-inf on zero components
        out_r, out_p, out_t = [], [], []

        def node_meets(r, nd):
            t0, t1 = _slab(o, inv, self.node_lo, self.node_hi, r, nd, tmin[r], tmax[r])
            return t0 <= t1

        for lr, pos in self._walk(n, node_meets, max_pairs):
            p0, p1 = _slab(o, inv, self.leaf_lo, self.leaf_hi, lr, pos, tmin[lr], tmax[lr])
            hit = p0 <= p1
            out_r.append(lr[hit])
            out_p.append(self.perm[pos[hit]])
            out_t.append(p0[hit])
        if not out_r:
            return empty
        ray_idx = np.concatenate(out_r)
        prim_idx = np.concatenate(out_p)
        t_enter = np.concatenate(out_t)
        order = np.lexsort((t_enter, ray_idx))
        return ray_idx[order], prim_idx[order], t_enter[order]

    def any_box(self, n: int, meets, max_pairs: int = MAX_PAIRS) -> np.ndarray:
        """(n,) bool: for queries 0..n-1, whether some primitive's box passes ``meets(q, lo,
        hi)`` (query ids q (k,), boxes lo, hi (k, 3) -> (k,) bool). ``meets`` must hold for a
        box whenever it holds for a box inside it: node boxes prune with it."""
        out = np.zeros(n, bool)
        if n == 0 or self.num_nodes == 0:
            return out
        for lq, pos in self._walk(n, lambda q, nd: meets(q, self.node_lo[:, nd].T,
                                                         self.node_hi[:, nd].T),
                                  max_pairs, done=out):
            out[lq[meets(lq, self.leaf_lo[:, pos].T, self.leaf_hi[:, pos].T)]] = True
        return out

    def closest_hit(self, origins, dirs, tmin, tmax, hit_fn, max_pairs: int = MAX_PAIRS):
        """Closest primitive hit per ray. ``hit_fn(ray_idx, prim_idx) -> t`` (inf for a miss;
        it must honour each ray's [tmin, tmax]). Leaves are tested as the wavefront reaches
        them and boxes beyond a ray's best t so far are pruned (on a 2k-triangle room: ~5%
        faster than testing all candidates, ~25% for any_hit). Returns (t (N,), prim (N,)), inf / -1
        for misses; ties go to the lower primitive index."""
        return self._hits(origins, dirs, tmin, tmax, hit_fn, max_pairs, stop_at_first=False)

    def any_hit(self, origins, dirs, tmin, tmax, hit_fn, max_pairs: int = MAX_PAIRS):
        """(N,) bool: does any primitive hit the ray (``hit_fn`` as in closest_hit); a ray
        leaves the traversal at its first hit."""
        t, _ = self._hits(origins, dirs, tmin, tmax, hit_fn, max_pairs, stop_at_first=True)
        return np.isneginf(t)

    def _hits(self, origins, dirs, tmin, tmax, hit_fn, max_pairs, stop_at_first):
        origins = np.asarray(origins, dtype=np.float64)
        dirs = np.asarray(dirs, dtype=np.float64)
        n = origins.shape[0]
        tmin = np.broadcast_to(np.asarray(tmin, dtype=np.float64), (n,))
        best = np.array(np.broadcast_to(np.asarray(tmax, dtype=np.float64), (n,)))
        found = np.zeros(n, dtype=bool)
        prim = np.full(n, -1, dtype=np.int64)
        if n == 0 or self.num_nodes == 0:
            return np.full(n, np.inf), prim
        o = np.ascontiguousarray(origins.T)
        with np.errstate(divide="ignore", over="ignore"):
            inv = np.ascontiguousarray((1.0 / dirs).T)

        def node_meets(r, nd):
            t0, t1 = _slab(o, inv, self.node_lo, self.node_hi, r, nd, tmin[r], best[r])
            return t0 <= t1

        for lr, pos in self._walk(n, node_meets, max_pairs):     # reads best as it shrinks
            lp = self.perm[pos]
            t = np.asarray(hit_fn(lr, lp), dtype=np.float64)
            better = (t <= best[lr]) & (t < np.inf)
            lr, lp, t = lr[better], lp[better], t[better]
            if stop_at_first:
                best[lr] = -np.inf                   # prunes every remaining pair of lr
            elif len(lr):
                order = np.lexsort((lp, t, lr))
                lr, lp, t = lr[order], lp[order], t[order]
                first = np.r_[True, lr[1:] != lr[:-1]]
                lr, lp, t = lr[first], lp[first], t[first]
                # equal t to an earlier best: keep the lower primitive index
                take = (t < best[lr]) | ~found[lr] | (lp < prim[lr])
                lr, lp, t = lr[take], lp[take], t[take]
                best[lr], prim[lr], found[lr] = t, lp, True
        if stop_at_first:
            return best, prim
        return np.where(found, best, np.inf), prim
