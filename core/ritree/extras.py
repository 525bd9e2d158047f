"""Direction-level interpolation from the extra samples of one- and two-interpolant leaf cells
(paper 4.3, Figure 12).

A leaf whose corners hold one usable interpolant (L) stores two extra samples v1, v2 on the
edges leaving L; a leaf with two usable interpolants on one side (A1, A2 or B1, B2) stores the
extras on the two edges leaving that side. The query interpolates barycentrically over the
triangle of the cell containing it: (L, v1, v2), or (c1, c2, ea) / (c2, ea, eb) for a pair.
Slots: 0..3 the cell's corners, 4 and 5 the two extras used.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .interp import EXTRAPOLATED, FAIL, UNIT_CORNERS, pick_triangle


@dataclass
class ExtraAnswer:
    """Rows (of the arrays passed in) answered from their leaf's extras: weights over the six
    slots, which two of the leaf's extras v1..v4 (0..3) slots 4 and 5 hold, and whether the
    answer is extrapolated."""

    rows: np.ndarray          # (g,)
    w: np.ndarray             # (g, 6)
    extra: np.ndarray         # (g, 2)
    extrapolated: np.ndarray  # (g,) bool


def extra_weights(tree, leaf, lx, ly, usable, pc, extrapolation) -> ExtraAnswer:
    """Extra-sample weights for queries at cell-local (lx, ly) of leaves ``leaf`` (n,) of
    ``tree`` whose usable corners ``usable`` (n, 4) (class ``pc`` (n,)) were too few for the
    cell itself."""
    n0 = len(leaf)
    empty = ExtraAnswer(np.zeros(0, np.int64), np.zeros((0, 6)), np.zeros((0, 2), np.int64),
                        np.zeros(0, bool))
    if n0 == 0 or len(tree.ex_node) == 0:
        return empty
    pos = np.minimum(np.searchsorted(tree.ex_node, leaf), len(tree.ex_node) - 1)
    has = tree.ex_node[pos] == leaf
    rows, pos = np.flatnonzero(has), pos[has]
    if len(rows) == 0:
        return empty
    kind = tree.ex_kind[pos]
    exc = tree.ex_corner[pos]
    exi = tree.ex_ids[pos]
    exp = tree.ex_pos[pos].astype(np.float64)
    us = usable[rows]
    table = tree.table
    ex_use = (table.cls[exi] == pc[rows, None]) & ~table.null[exi]
    n = len(rows)
    r = np.arange(n)
    tri_slot = np.zeros((n, 2, 3), np.int64)
    valid = np.zeros((n, 2), bool)
    cnt = us.sum(1)
    one = kind == 1
    L = np.where(one, exc[:, 0], 0)
    one_ok = one & us[r, L] & (cnt == 1) & ex_use[:, 0] & ex_use[:, 1]
    # two-interpolant: the usable pair must be (A1, A2) or (B1, B2)
    A = exc[:, 0:2].clip(0)
    B = exc[:, 2:4].clip(0)
    two = (kind == 2) & (cnt == 2)
    a_side = two & us[r, A[:, 0]] & us[r, A[:, 1]] & ex_use[:, 0] & ex_use[:, 1]
    b_side = two & us[r, B[:, 0]] & us[r, B[:, 1]] & ex_use[:, 2] & ex_use[:, 3]
    # one-interpolant: triangle (L, v1, v2)
    k1 = np.flatnonzero(one_ok)
    tri_slot[k1, 0] = np.stack([L[k1], np.full(len(k1), 4), np.full(len(k1), 5)], 1)
    valid[k1, 0] = True
    for side, (c1, c2) in ((a_side, (A[:, 0], A[:, 1])), (b_side, (B[:, 0], B[:, 1]))):
        s_ = np.flatnonzero(side)
        # T1 = (c1, c2, ea), T2 = (c2, ea, eb), ea on the edge from c1, eb from c2
        tri_slot[s_, 0] = np.stack([c1[s_], c2[s_], np.full(len(s_), 4)], 1)
        tri_slot[s_, 1] = np.stack([c2[s_], np.full(len(s_), 4), np.full(len(s_), 5)], 1)
        valid[s_] = True
    if not np.any(valid[:, 0]):
        return empty
    slot_pos = np.concatenate([np.broadcast_to(UNIT_CORNERS, (n, 4, 2)), np.zeros((n, 2, 2))],
                              axis=1)
    e_idx = np.where(b_side[:, None] & ~one_ok[:, None], [2, 3], [0, 1])
    slot_pos[:, 4] = exp[r, e_idx[:, 0]]
    slot_pos[:, 5] = exp[r, e_idx[:, 1]]
    tri_pos = slot_pos[r[:, None, None], tri_slot]
    qpt = np.stack([lx[rows], ly[rows]], 1)
    which, lam, st = pick_triangle(qpt, tri_pos, valid, extrapolation)
    st = np.where(valid[:, 0], st, FAIL)
    good = np.flatnonzero(st != FAIL)
    if len(good) == 0:
        return empty
    slots = tri_slot[good, which[good]]                                   # (g, 3)
    wk = np.zeros((len(good), 6))
    np.add.at(wk, (np.arange(len(good))[:, None], slots), lam[good])
    return ExtraAnswer(rows=rows[good], w=wk, extra=e_idx[good],
                       extrapolated=st[good] == EXTRAPOLATED)
