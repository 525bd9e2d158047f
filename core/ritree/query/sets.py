"""Sample sets: located rays grouped by their four direction leaves (= their 16 corner samples),
and the items a set can interpolate from.

Counts: a ray's viewpoint cell has N_DQ = 4 corners (viewpoints), each with one direction
leaf (DQ) of N_CORNERS = 4 corner samples: SET_CORNERS = 16 samples per ray. A leaf of a one-
or two-interpolant cell also stores N_EXTRAS = 4 extra samples (paper 4.3): with them a set
has SET_ITEMS = 32 items (16 corners, then 16 extras, both in DQ order, 4 per DQ). One
interpolation at the direction level uses DQ_SLOTS = 6 slots (4 corners + the 2 extras of its
triangle): RAY_SLOTS = 24 per ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...rowops import any_last

N_DQ = 4
N_CORNERS = 4
N_EXTRAS = 4
SET_CORNERS = N_DQ * N_CORNERS             # 16
SET_ITEMS = SET_CORNERS + N_DQ * N_EXTRAS  # 32
DQ_SLOTS = N_CORNERS + 2                   # 6
RAY_SLOTS = N_DQ * DQ_SLOTS                # 24

# Item of each (DQ k, slot j) of a ray by default: the DQ's corners 4k + j, and for slots 4, 5
# the DQ's first two extras 16 + 4k, 16 + 4k + 1 (weight 0 unless the DQ uses its extras, which
# then name the two they use). The items of one ray are distinct.
DEFAULT_ITEMS = np.array([[N_CORNERS * k + j for j in range(N_CORNERS)]
                          + [SET_CORNERS + N_EXTRAS * k, SET_CORNERS + N_EXTRAS * k + 1]
                          for k in range(N_DQ)])


def group_rows(keys: np.ndarray):
    """Group the rows of an (m, k) integer array: (group id of each row (m,), index of the
    first row of each group (G,)); groups are numbered in sorted key order. Runs of equal
    consecutive rows (neighbouring pixels share their sample set) are sorted as one."""
    m = len(keys)
    if m == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    head = np.ones(m, bool)
    head[1:] = any_last(keys[1:] != keys[:-1])
    heads = np.flatnonzero(head)
    run_of = np.cumsum(head) - 1
    hk = keys[heads]
    sk, k = hk, hk.shape[1]
    if k > 1 and hk.min() >= 0 and hk.max() < 1 << 31:
        # pairs of columns as one int64 (order-preserving): half the sort keys
        h = hk.astype(np.int64)
        sk = np.concatenate([(h[:, 0:k - 1:2] << 32) | h[:, 1:k:2], h[:, k - k % 2:]], axis=1)
    order = np.argsort(sk[:, 0], kind="stable") if sk.shape[1] == 1 else np.lexsort(sk.T[::-1])
    sk = sk[order]
    new = np.ones(len(heads), bool)
    new[1:] = any_last(sk[1:] != sk[:-1])
    group = np.empty(len(heads), np.int64)
    group[order] = np.cumsum(new) - 1
    return group[run_of], heads[order[new]]


@dataclass
class SetItems:
    """What a sample set can interpolate from: the 16 corners (item 4k + j: DQ k, corner j)
    and each leaf's four extras (item 16 + 4k + e; id 0 and unusable where the leaf has
    none). Their values are RITree.blend_vals rows (output directions times the perspective
    weight), so one weighted sum blends every column."""

    ids: np.ndarray          # (S, 32) sample ids
    corner_vals: np.ndarray  # (S, 16, COL.N) float32: items 0-15
    extra_vals: np.ndarray   # (S, 16, COL.N) float32: items 16-31
    has_extra: np.ndarray    # (S, 4) the leaf stores extras

    @classmethod
    def of(cls, tree, s_leaf, s_ids) -> "SetItems":
        s = len(s_leaf)
        ex_ids = np.zeros((s, N_DQ * N_EXTRAS), np.int64)
        has = np.zeros((s, N_DQ), bool)
        if len(tree.ex_node):
            pos = np.minimum(np.searchsorted(tree.ex_node, s_leaf), len(tree.ex_node) - 1)
            has = tree.ex_node[pos] == s_leaf
            ex_ids = np.where(has[..., None], tree.ex_ids[pos], 0).reshape(s, N_DQ * N_EXTRAS)
        vals = tree.blend_vals
        return cls(ids=np.concatenate([s_ids, ex_ids], axis=1), corner_vals=vals[s_ids],
                   extra_vals=vals[ex_ids], has_extra=has)

    def item_vals(self, sets, item) -> np.ndarray:
        """Values (..., COL.N) of items ``item`` (0-31) of sets ``sets`` (broadcast together)."""
        c = self.corner_vals[sets, np.minimum(item, SET_CORNERS - 1)]
        e = self.extra_vals[sets, np.maximum(item - SET_CORNERS, 0)]
        return np.where((item < SET_CORNERS)[..., None], c, e)


@dataclass
class SampleSets:
    """The distinct sample sets (S) of a batch's located rays."""

    leaf: np.ndarray               # (S, 4) the four direction leaves
    ids: np.ndarray                # (S, 16) their corner sample ids
    cls: np.ndarray                # (S, 16) the samples' classes (-1: miss)
    items: SetItems | None = None  # corners and extras (formed for the sets still open)

    def take(self, keep) -> "SampleSets":
        """The sets ``keep`` (mask; items not formed yet)."""
        return SampleSets(leaf=self.leaf[keep], ids=self.ids[keep], cls=self.cls[keep])


def corner_weights(tree, loc):
    """(ids (n, 16), weights (n, 16)): the 16 corner samples of the located rays ``loc`` and
    their bilinear weights at the viewpoint and direction levels (summing to 1 a ray)."""
    ids = tree.dir_forest.corner[loc.leaf].reshape(-1, SET_CORNERS)
    w_vp = _bilinear(loc.alpha, loc.beta)                          # (n, 4) per DQ
    w_dir = np.stack([_bilinear(loc.lx[:, k], loc.ly[:, k]) for k in range(N_DQ)], axis=1)
    return ids, (w_vp[:, :, None] * w_dir).reshape(-1, SET_CORNERS)


def _bilinear(x, y) -> np.ndarray:
    """(n, 4) bilinear weights of the quadtree corners (0, 0), (1, 0), (0, 1), (1, 1)."""
    return np.stack([(1 - x) * (1 - y), x * (1 - y), (1 - x) * y, x * y], axis=1)


def group(q, b) -> None:
    """Group the located rays ``b.loc`` by their four leaves: ``b.sets``, ``b.set_of`` (per
    located ray), all of them open (``b.go``)."""
    with b.clock("group"):
        set_of, first = group_rows(b.loc.leaf)
        leaf = b.loc.leaf[first]
        ids = q.tree.dir_forest.corner[leaf].reshape(-1, SET_CORNERS)
        b.sets = SampleSets(leaf=leaf, ids=ids, cls=q.table.cls[ids])
        b.set_of = set_of
        b.go = np.arange(len(set_of))


def open_sets(q, b) -> None:
    """Keep only the sets the open rays use (all-miss sets hold many rays, answered already)
    and form their items."""
    keep = np.zeros(len(b.sets.leaf), bool)
    keep[b.set_of] = True
    b.set_of = (np.cumsum(keep) - 1)[b.set_of]
    b.sets = b.sets.take(keep)
    b.sets.items = SetItems.of(q.tree, b.sets.leaf, b.sets.ids)
