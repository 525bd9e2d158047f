"""Extra samples of two-class direction leaves (paper 4.3): the class boundary located on the
cell edges by binary search.

Corner slots c0..c3 = (0,0), (1,0), (0,1), (1,1); edges are searched from a corner of one
class towards its neighbour of the other class.

- one-interpolant (kind 1): lone corner L; v1 on the edge L->(L^1) (x edge), v2 on L->(L^2)
  (y edge), both in L's class; v3, v4 the other-class ends of the same brackets.
- two-interpolant (kind 2): corners A1, A2 of class A on one side, edges A1->B1, A2->B2;
  v1, v2 in class A (on those edges), v3, v4 in class B (same edges).
- diagonal 2-vs-2 cells get none.

``ex_corner`` stores (L, -1, -1, -1) or (A1, A2, B1, B2).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..quadtree import CORNERS, Forest
from ..tree import Samples
from .state import classes, take


@dataclass
class ExtraSearch:
    """What the edge search reads and where it appends: the direction ``forest`` (corners =
    sample ids) and its ``samples``, the patches' ``class_of``, the maximum direction depth
    ``M`` and the binary-search ``steps``; ``probe(trees, gxy)`` traces rays of direction trees
    at points ``gxy`` (n, 2) of the finest grid (Samples), ``keep(samples, step, leaf_level)``
    appends the probes kept (returns their ids)."""

    forest: Forest
    samples: Samples
    class_of: np.ndarray
    M: int
    steps: int
    probe: Callable
    keep: Callable

    def corner_class(self, ids) -> np.ndarray:
        """Class of sample ids, -2 for null samples (a class of its own here)."""
        return np.where(self.samples.null[ids], -2, classes(self.samples, ids, self.class_of))


@dataclass
class _Cells:
    """The two-class leaves to search: (E,) leaves and kind, (E, 4) corner ids and
    ``ex_corner``, (E, 2) the edges' start and end corner slots."""

    leaves: np.ndarray
    corner: np.ndarray
    kind: np.ndarray
    ex_corner: np.ndarray
    e_from: np.ndarray
    e_to: np.ndarray


def extra_samples(search: ExtraSearch, leaves, tree_of) -> dict:
    """The extra samples of the two-class cells among direction ``leaves`` (``tree_of``: the
    tree of each node), as RITree's ``ex_*`` arrays sorted by node."""
    cells = _two_class_cells(search, leaves)
    lo_f, hi_f, lo_s, hi_s = _bisect(search, cells, tree_of[cells.leaves])
    # local cell coordinates of the bracket ends
    a = CORNERS[cells.e_from].astype(np.float64)                       # (E, 2, 2)
    b = CORNERS[cells.e_to].astype(np.float64)
    pos_lo = a + (b - a) * lo_f[..., None]
    pos_hi = a + (b - a) * hi_f[..., None]
    ex_ids = np.concatenate([lo_s, hi_s], axis=1)                       # v1 v2 (start class), v3 v4
    ex_pos = np.concatenate([pos_lo, pos_hi], axis=1).astype(np.float32)
    order = np.argsort(cells.leaves)
    return {"ex_node": cells.leaves[order], "ex_kind": cells.kind[order].astype(np.int8),
            "ex_ids": ex_ids[order], "ex_pos": ex_pos[order],
            "ex_corner": cells.ex_corner[order]}


def _two_class_cells(search: ExtraSearch, leaves) -> _Cells:
    """The leaves whose sampled corners fall in exactly two classes (null a class of its
    own), one- or two-interpolant, with the two edges to search in each."""
    corner = search.forest.corner[leaves]
    valid = np.all(corner >= 0, axis=1)
    leaves, corner = leaves[valid], corner[valid]
    cls = search.corner_class(corner)
    srt = np.sort(cls, axis=1)
    # exactly two classes: sorted row is a a b b, a b b b or a a a b
    two = (srt[:, 0] != srt[:, 3]) & (np.sum(srt[:, 1:] != srt[:, :-1], axis=1) == 1)
    leaves, corner, cls = leaves[two], corner[two], cls[two]
    first = cls == cls[:, :1]
    n_first = first.sum(1)
    # the lone corner of a 1-vs-3 cell
    lone = np.where(n_first == 1, np.argmax(first, 1),
                    np.where(n_first == 3, np.argmin(first, 1), -1))
    # two-vs-two: adjacent pairs share an edge (same row: c0c1 / c2c3, or same column: c0c2 /
    # c1c3)
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
    return _Cells(leaves=leaves, corner=corner, kind=kind, ex_corner=ex_corner, e_from=e_from,
                  e_to=e_to)


def _bisect(search: ExtraSearch, cells: _Cells, tr):
    """Binary search along each cell's two edges (``tr``: the cells' trees) for the class
    boundary, ``search.steps`` steps. Returns (lo_f, hi_f, lo_s, hi_s), each (E, 2): the
    bracket ends as fractions along the edges (lo in the start corner's class, hi in the
    other) and their sample ids (the corners', or the probes kept, appended by
    ``search.keep``)."""
    E, corner = len(cells.leaves), cells.corner
    cc = search.forest.corner_coords(cells.leaves, search.M).astype(np.float64)   # (E, 4, 2)
    rows = np.arange(E)[:, None]
    p0 = cc[rows, cells.e_from]                                         # (E, 2, 2)
    p1 = cc[rows, cells.e_to]
    c_from = search.corner_class(corner[rows, cells.e_from])
    lo_f = np.zeros((E, 2))                                             # fraction in start class
    hi_f = np.ones((E, 2))                                              # fraction in other class
    lo_s = corner[rows, cells.e_from].copy()
    hi_s = corner[rows, cells.e_to].copy()
    trr = np.repeat(tr, 2)
    # bracket ends: corner sample ids (>= 0) or probes, coded -1 - (index into probes)
    probes = Samples.empty()
    for _ in range(search.steps):
        f = 0.5 * (lo_f + hi_f)
        g = p0 + (p1 - p0) * f[..., None]                              # (E, 2, 2)
        s = search.probe(trr, g.reshape(-1, 2))
        c = np.where(s.null, -2, np.where(s.patch >= 0, search.class_of[np.maximum(s.patch, 0)],
                                          -1)).reshape(E, 2)
        ids = (-1 - probes.extend(s)).reshape(E, 2)
        same = c == c_from
        lo_f = np.where(same, f, lo_f)
        lo_s = np.where(same, ids, lo_s)
        hi_f = np.where(same, hi_f, f)
        hi_s = np.where(same, hi_s, ids)
    # keep only the probes that ended as bracket ends
    ends = np.concatenate([lo_s, hi_s], axis=1)
    used, inv = np.unique(-1 - ends[ends < 0], return_inverse=True)
    per_step = max(2 * E, 1)
    new = search.keep(take(probes, used), used // per_step,
                      search.forest.level[cells.leaves[(used % per_step) // 2]])
    ends[ends < 0] = new[inv.ravel()]
    return lo_f, hi_f, ends[:, :2], ends[:, 2:]
