"""Per-unit decisions (a unit: a sample set with one class, shared by many rays): which of the
set's 32 items are usable, how its mirror rays are answered, which DQs the thresholds check,
and whether any pairwise threshold can bite. Nothing here depends on where a ray falls in its
cells."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...rowops import any_last
from ..answers import COL, WHY_TOLERANCE
from ..interp import far_pairs, may_have_far_pairs
from .options import MIRROR_BLEND, MIRROR_NEWTON, MIRROR_NORMAL
from .sets import N_CORNERS, SET_CORNERS, SET_ITEMS, group_rows, open_sets


@dataclass
class Units:
    """The units (U) of a batch's open rays (``Batch.unit_of``)."""

    set: np.ndarray                   # (U,) sample set
    pc: np.ndarray                    # (U,) class
    ok: np.ndarray                    # (U, 32) usable items: of the class, not null
    checked: np.ndarray               # (U, 4) DQs whose samples the thresholds compare
    mirror: np.ndarray | None = None  # (U,) int8 MIRROR_* (None: not a mirror, or "interpolate")
    far: np.ndarray | None = None     # (U,) bool: some threshold bites (a real far pair)
    far_pairs: np.ndarray | None = None  # (F + 1, 32, 32) far item pairs; the last: none
    far_row: np.ndarray | None = None    # (U,) row of each unit in far_pairs


def decide(q, b) -> None:
    """Form the units of the open rays (``b.units``, ``b.unit_of``), after keeping only the
    sets they use."""
    open_sets(q, b)
    tab, items = q.table, b.sets.items
    b.unit_of, ufirst = group_rows(np.stack([b.set_of, b.pc], axis=1))
    u_set, u_pc = b.set_of[ufirst], b.pc[ufirst]
    ids = items.ids[u_set]
    ok = (tab.cls[ids] == u_pc[:, None]) & ~tab.null[ids]
    ok[:, SET_CORNERS:] &= np.repeat(items.has_extra[u_set], N_CORNERS, axis=1)
    b.units = u = Units(set=u_set, pc=u_pc, ok=ok,
                        checked=np.ones((len(u_set), N_CORNERS), bool))
    if q.opt.mirror_rays != "interpolate" and q.material.kind == "mirror":
        mirror_modes(q, b)
    # the DQs whose samples the thresholds compare: all, or those the bake could not verify
    # (split to the maximum depth: a shallower leaf's midpoint matched)
    if q.opt.per_sample and q.opt.threshold_leaves == "unverified":
        u.checked = q.tree.dir_forest.level[b.sets.leaf[u_set]] >= q.tree.params.direction_depth
    u.far = np.zeros(len(u_set), bool)
    if q.opt.per_sample:
        far_units(q, b)


def used_items(u: Units, units) -> np.ndarray:
    """(n, 32) the usable items of units ``units`` that the thresholds check (a DQ's corners
    and its extras alike: 4 items of each half per DQ)."""
    return u.ok[units] & np.tile(np.repeat(u.checked[units], N_CORNERS, axis=1), 2)


def mirror_modes(q, b) -> None:
    """How the units' mirror rays are answered (``Units.mirror``): units whose usable samples
    all reflect once from the normal, and where they share one NURBS patch from Newton's hit on
    it. Rays past the tolerance (``b.must``) that Newton cannot answer are traced."""
    tab, u = q.table, b.units
    ids = b.sets.items.ids[u.set]
    once = np.all(tab.once[ids] | ~u.ok, axis=1)
    u.mirror = np.where(once, MIRROR_NORMAL, MIRROR_BLEND).astype(np.int8)
    if q.opt.mirror_rays == "newton":
        pid = tab.patch[ids]
        top = np.where(u.ok, pid, -1).max(axis=1)
        one = (top == np.where(u.ok, pid, np.iinfo(np.int32).max).min(axis=1)) \
            & (q.st.tracer.piece_base[np.maximum(top, 0)] >= 0)   # one NURBS patch
        u.mirror[once & one] = MIRROR_NEWTON
    lost = b.must[b.loc.ray[b.go]] & (u.mirror[b.unit_of] != MIRROR_NEWTON)
    if lost.any():
        b.trace(b.loc.ray[b.go[lost]], WHY_TOLERANCE)
        b.narrow(~lost)


def far_units(q, b) -> None:
    """Paper 5.3's far pairs, once per unit where some may exist: ``Units.far``,
    ``far_pairs``, ``far_row``."""
    u, tab = b.units, q.table
    ang, dist = q.max_angle, q.max_dist
    ids = b.sets.items.ids[u.set]
    # far_pairs' pretest on everything a ray of the unit can use: a unit that passes has no
    # far pair among any ray's interpolants
    v = tab.vals[ids].astype(np.float64)
    may = may_have_far_pairs(v[..., COL.OUT_D], v[..., COL.OUT_O], used_items(u, slice(None)),
                             ang, dist)
    fu = np.flatnonzero(may)
    used = used_items(u, fu)
    full = np.zeros((len(fu) + 1, SET_ITEMS, SET_ITEMS), bool)   # the last row: no far pair
    # units without usable extras compare their 16 corners only (a quarter of the pairs);
    # the 16 extras tested as two 64-bit words of 8 bools (rowops)
    ext = any_last(used[:, SET_CORNERS:].reshape(-1, 2, 8)).any(axis=1)
    for sel, k in ((np.flatnonzero(~ext), SET_CORNERS), (np.flatnonzero(ext), SET_ITEMS)):
        if len(sel):
            v = tab.vals[ids[fu[sel], :k]].astype(np.float64)
            rws, far = far_pairs(v[..., COL.OUT_D], v[..., COL.OUT_O], used[sel, :k], ang, dist)
            full[sel[rws], :k, :k] = far
    u.far_row = np.full(len(may), len(fu))
    u.far_row[fu] = np.arange(len(fu))
    u.far_pairs = full
    u.far = full.any(axis=(1, 2))[u.far_row]          # units with a real far pair
