"""Per-ray interpolation weights (paper 4.1-4.3, 5.1, 5.3): each DQ bilinear over four usable
corners, barycentric over three, or from its leaf's extra samples; then the viewpoint level
combines the usable DQs the same way. The thresholds cut interpolants first."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..extras import extra_weights
from ..interp import EXTRA, EXTRAPOLATED, FAIL, cell_weights
from ..locate import Located
from .sets import DEFAULT_ITEMS, DQ_SLOTS, N_CORNERS, N_DQ, N_EXTRAS, SET_CORNERS
from .thresholds import (direction_thresholds, far_bits, intermediate_thresholds,
                         viewpoint_thresholds)


@dataclass
class Weights:
    """The weights of the open rays (m), in the order of ``Batch.go``. Per DQ k: slot weights
    over its 4 corners and 2 extras (``w``), the set items those slots hold (``item``, 0-31),
    its status (interp.FAIL...); per ray: the viewpoint-level weights ``W`` over the 4 DQs and
    status ``qst``."""

    loc: Located                       # (m) where the rays fall
    usable: np.ndarray                 # (m, 4, 4) usable corners per DQ
    checked: np.ndarray                # (m, 4) DQs the thresholds compare
    thr_hit: np.ndarray                # (m, 4) DQs whose interpolants the thresholds cut
    w: np.ndarray | None = None        # (m, 4, 6) slot weights
    item: np.ndarray | None = None     # (m, 4, 6) item of each slot
    dq_st: np.ndarray | None = None    # (m, 4) DQ status
    is_extra: np.ndarray | None = None  # (m, 4) the DQ interpolates from its extras
    dq_ok: np.ndarray | None = None    # (m, 4) usable DQs
    thr_q: np.ndarray | None = None    # (m,) the viewpoint-level threshold dropped a DQ
    W: np.ndarray | None = None        # (m, 4) viewpoint weights
    qst: np.ndarray | None = None      # (m,) viewpoint status
    few: np.ndarray | None = None      # (m,) too few interpolants (not for the thresholds)
    thr: np.ndarray | None = None      # (m,) False: too few because the thresholds cut them


def weights(q, b) -> None:
    """``b.weights`` for the open rays."""
    with b.clock("weights"):
        u, unit_of = b.units, b.unit_of
        loc = b.loc.take(b.go)
        m = len(loc)
        wt = Weights(loc=loc, usable=u.ok[unit_of, :SET_CORNERS].reshape(m, N_DQ, N_CORNERS),
                     checked=u.checked[unit_of], thr_hit=np.zeros((m, N_DQ), bool))
        fr = np.flatnonzero(u.far[unit_of])         # rays that need the pairwise tests
        if len(fr):
            direction_thresholds(u, wt, fr, unit_of)
        direction_weights(q, b, wt)
        wt.thr_q = np.zeros(m, bool)
        if q.opt.per_sample and len(fr):
            viewpoint_thresholds(wt, far_bits(u.far_pairs)[u.far_row[unit_of[fr]]], fr)
        elif q.opt.thresholds and not q.opt.per_sample:
            intermediate_thresholds(q, b, wt)
        wt.W, wt.qst = cell_weights(wt.dq_ok, loc.alpha, loc.beta, q.opt.extrapolation)
        few = wt.qst == FAIL
        # too few interpolants because the thresholds cut them: traced "by the threshold"
        wt.thr = ~(few & (wt.thr_q | np.any(wt.thr_hit & ~wt.dq_ok, axis=1)))
        wt.few = few & wt.thr
        b.weights = wt


def direction_weights(q, b, wt) -> None:
    """Each DQ's slot weights over its usable corners, or (where those fail) over its leaf's
    extras; every DQ of every ray in one call, rows 4 * ray + DQ."""
    loc, usable = wt.loc, wt.usable
    m = len(loc)
    w = np.zeros((m, N_DQ, DQ_SLOTS))
    wk, dq_st = cell_weights(usable.reshape(-1, N_CORNERS), loc.lx.ravel(), loc.ly.ravel(),
                             q.opt.extrapolation)
    w[:, :, :N_CORNERS] = wk.reshape(m, N_DQ, N_CORNERS)
    dq_st = dq_st.reshape(m, N_DQ)
    item = np.broadcast_to(DEFAULT_ITEMS, (m, N_DQ, DQ_SLOTS))
    fail = np.flatnonzero(dq_st.ravel() == FAIL)
    if len(fail):
        ea = extra_weights(q.tree, loc.leaf.ravel()[fail], loc.lx.ravel()[fail],
                           loc.ly.ravel()[fail], usable.reshape(-1, N_CORNERS)[fail],
                           b.pc[fail // N_DQ], q.opt.extrapolation)
        r, k = np.divmod(fail[ea.rows], N_DQ)
        if len(r):
            item = item.copy()
            w[r, k] = ea.w
            item[r, k, N_CORNERS:] = SET_CORNERS + N_EXTRAS * k[:, None] + ea.extra
            dq_st[r, k] = np.where(ea.extrapolated, EXTRAPOLATED, EXTRA)
    wt.w, wt.item, wt.dq_st = w, item, dq_st
    wt.is_extra = (dq_st == EXTRA) | (dq_st == EXTRAPOLATED)
    wt.dq_ok = dq_st != FAIL
