"""Paper 5.3's pairwise angle / distance thresholds at both levels: far samples of a DQ are not
usable (an outlier is dropped), and far DQs are not combined. Far pairs are found once per
unit (units.far_units); here each ray applies them where it falls in its cells."""

from __future__ import annotations

import numpy as np

from ..answers import COL
from ..interp import UNIT_CORNERS, drop_outlier, drop_outlier_units, far_pairs
from .sets import DQ_SLOTS, N_CORNERS, N_DQ, RAY_SLOTS, SET_CORNERS


def far_bits(far) -> np.ndarray:
    """Far-pair matrices (F, 32, 32) bool as bit rows (F, 32) uint32: bit j of row i."""
    return np.packbits(far, axis=2, bitorder="little").view("<u4")[..., 0].astype(np.uint32)


def direction_thresholds(u, wt, fr, unit_of) -> None:
    """Direction level for the rays ``fr`` (rows of ``wt``; ``unit_of`` their units in ``u``):
    far corners of a DQ are not usable (``wt.usable``, ``wt.thr_hit``; an outlier is dropped,
    which one depends on where the ray falls in the cell). Degrees and leftovers are found per
    unit, not per ray."""
    rows, pos = np.unique(u.far_row[unit_of[fr]], return_inverse=True)
    first = np.zeros(len(rows), np.int64)
    first[pos] = np.arange(len(fr))          # a ray of each unit (all share its usable)
    used = u.ok[unit_of[fr[first]], :SET_CORNERS].reshape(-1, N_DQ, N_CORNERS)
    f = u.far_pairs[rows, :SET_CORNERS, :SET_CORNERS].reshape(-1, N_DQ, N_CORNERS, N_DQ,
                                                             N_CORNERS)
    loc = wt.loc
    for k in range(N_DQ):
        wt.usable[fr, k], wt.thr_hit[fr, k] = drop_outlier_units(
            f[:, k, :, k], used[:, k], pos, UNIT_CORNERS,
            np.stack([loc.lx[fr, k], loc.ly[fr, k]], 1))


def viewpoint_thresholds(wt, bits, fr) -> None:
    """Viewpoint level for the rays ``fr`` (rows of ``wt``; ``bits`` (R, 32): their units' far
    pairs as bit rows, bit j of row i set where items i and j are far): DQs are far apart when
    any of their interpolants are (an extra-sample triangle's samples for extras); a DQ with a
    far pair inside is unusable (``wt.dq_ok``, ``wt.thr_hit``), then an outlying DQ is dropped
    (``wt.thr_q``)."""
    n = len(fr)
    member = np.concatenate([wt.usable[fr], np.zeros((n, N_DQ, DQ_SLOTS - N_CORNERS), bool)],
                            axis=2)
    member = np.where(wt.is_extra[fr, :, None], wt.w[fr] != 0, member)
    member = member & wt.dq_ok[fr, :, None] & wt.checked[fr, :, None]    # (n, 4, 6)
    it = wt.item[fr]
    # each DQ's member items as a bit set (a ray's items are distinct: sum = or), and
    # the items far from any of them
    mask = np.where(member, np.left_shift(np.uint32(1), it.astype(np.uint32)),
                    np.uint32(0)).sum(axis=2, dtype=np.uint32)             # (n, 4)
    far_of_items = np.take_along_axis(bits, it.reshape(n, RAY_SLOTS), axis=1).reshape(
        n, N_DQ, DQ_SLOTS)
    reach = np.bitwise_or.reduce(np.where(member, far_of_items, np.uint32(0)), axis=2)
    blocks = (reach[:, :, None] & mask[:, None, :]) != 0                   # (n, 4, 4)
    r = np.flatnonzero(blocks.any(axis=(1, 2)))
    blocks = blocks[r]
    inner = np.diagonal(blocks, axis1=1, axis2=2)                           # (R, 4)
    r = fr[r]
    wt.thr_hit[r] |= inner
    wt.dq_ok[r] &= ~inner
    wt.dq_ok[r], wt.thr_q[r] = drop_outlier(blocks, wt.dq_ok[r], UNIT_CORNERS,
                                            np.stack([wt.loc.alpha[r], wt.loc.beta[r]], 1))


def intermediate_thresholds(q, b, wt) -> None:
    """threshold_on "intermediate": compare the four DQs' intermediate rays f*(R_VP) (parallel
    query rays from the four viewpoints); an outlying DQ is dropped (``wt.dq_ok``,
    ``wt.thr_q``)."""
    inter = np.einsum("nkj,nkjc->nkc", wt.w.astype(np.float32),
                      b.sets.items.item_vals(b.set_of[:, None, None], wt.item)
                      ).astype(np.float64)
    idir = inter[:, :, COL.OUT_D] / np.maximum(
        np.linalg.norm(inter[:, :, COL.OUT_D], axis=2), 1e-300)[:, :, None]
    r2, blocks = far_pairs(idir, inter[:, :, COL.OUT_O], wt.dq_ok, q.max_angle, q.max_dist)
    wt.dq_ok[r2], wt.thr_q[r2] = drop_outlier(blocks, wt.dq_ok[r2], UNIT_CORNERS,
                                              np.stack([wt.loc.alpha[r2], wt.loc.beta[r2]], 1))
