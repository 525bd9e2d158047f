"""Rules that read what the bake measured in the ray's four leaves and viewpoint cell, and the
paths its samples take: the baked-error tolerance (QueryOptions.max_error_deg), the trusted
misses, one path per blend, and path identity. Rays that fail them are traced (or solved
along a sample's path, query/paths.py)."""

from __future__ import annotations

import numpy as np

from ..answers import WHY_PATH, WHY_TOLERANCE, WHY_UNSAMPLED
from ..tree import BOUNDARY, PATH_CHANGE
from .certify import first_hits
from .sets import group_rows


def check_misses(q, b) -> None:
    """Tolerance mode, the open rays the samples answer MISS (class -1: all 16 miss, or the
    exact first hit against the candidate patches missed): the miss is trusted where the bake
    verified it (within the tolerance, no object/miss boundary in the four leaves or the
    cell); elsewhere the exact first hit against every patch decides, and a ray that hits
    is traced (WHY_UNSAMPLED: paper Fig. 9(b), or a patch none of its samples hit)."""
    tree, tol, known = q.tree, q.opt.max_error_deg, b.known
    s_leaf = b.sets.leaf
    s_ok = np.all((tree.dir_err[s_leaf] <= tol) & (tree.dir_flags[s_leaf] & BOUNDARY == 0),
                  axis=1)
    miss = b.pc == -1
    c = b.loc.vnode[b.go[miss]]
    ok = s_ok[b.set_of[miss]] & (tree.vp_err[c] <= tol) & (tree.vp_flags[c] & BOUNDARY == 0)
    r = b.loc.ray[b.go[miss][~ok]]
    if len(r):
        new = r[known.pos[r] < 0]        # the others' first hit stage searched every patch
        if len(new):
            known.add(new, first_hits(q, b, new))
        b.trace(r[known.hit(r)], WHY_UNSAMPLED)


def within_tolerance(q, b) -> None:
    """Keep the open rays whose four leaves (decided once per set) and viewpoint cell the bake
    measured within ``max_error_deg`` (an unmeasured NaN is not); the others are traced
    (WHY_TOLERANCE). With mirror_rays "newton", a mirror ray outside the tolerance whose leaves
    and cell the bake did not see change path goes on as one that only an exact hit may answer
    (``b.must``): the bake's errors are the blend's, which that hit replaces. Where the
    object's outline crosses them (BOUNDARY), only if the ray's exact first hit is known (a
    two-class ray): hit or miss is then not a guess. A leaf or cell the bake saw answered
    wrongly (inf) proves nothing: the ray is traced; one it did not measure (NaN: its midpoint
    changed class at the maximum depth, or no test ray was interpolated) is traced too, unless
    the exact first hit is known: its flags, which the bake sets from the traced corners and
    test rays whether or not it could measure, are then all the evidence the exact hit needs."""
    tol, tree = q.opt.max_error_deg, q.tree
    s_leaf, set_of = b.sets.leaf, b.set_of
    vnode, ray = b.loc.vnode[b.go], b.loc.ray[b.go]
    s_ok = np.all(tree.dir_err[s_leaf] <= tol, axis=1)
    ok = s_ok[set_of] & (tree.vp_err[vnode] <= tol)
    if q.opt.mirror_rays == "newton" and q.material.kind == "mirror":
        flags = np.bitwise_or.reduce(tree.dir_flags[s_leaf], axis=1)[set_of] \
            | tree.vp_flags[vnode]
        exact = b.known.pos[ray] >= 0
        s_err, c_err = tree.dir_err[s_leaf], tree.vp_err[vnode]
        measured = np.all(np.isfinite(s_err), axis=1)[set_of] & np.isfinite(c_err)
        seen_wrong = np.any(np.isinf(s_err), axis=1)[set_of] | np.isinf(c_err)
        calm = ~ok & (measured | (exact & ~seen_wrong)) & (flags & PATH_CHANGE == 0) \
            & ((flags & BOUNDARY == 0) | exact)
        b.must[ray[calm]] = True
        ok |= calm
    b.trace(ray[~ok], WHY_TOLERANCE)
    b.narrow(ok)


def _one_hash(q, b, groups=False):
    """(unit_of, first, same): the open rays' (set, class) units and whether each unit's
    usable samples (its set's corners of its class, not null) share one ray-tree hash; with
    ``groups``, one sequence of patch groups (``RITree.class_paths``) instead."""
    tab = q.table
    unit_of, first = group_rows(np.stack([b.set_of, b.pc], axis=1))
    ids = b.sets.ids[b.set_of[first]]
    use = (tab.cls[ids] == b.pc[first][:, None]) & ~tab.null[ids]
    h = (q.tree.class_paths[ids] >> np.uint64(1)).astype(np.int64) if groups \
        else tab.tree[ids].astype(np.int64)
    top = np.where(use, h, -1).max(axis=1)
    same = top <= np.where(use, h, np.iinfo(np.int64).max).min(axis=1)
    return unit_of, first, same


def one_path(q, b) -> None:
    """Tolerance mode: keep the open rays whose usable samples share one path (decided once
    per (set, class) unit). A blend of samples that take different paths (a total internal
    reflection more or less, trapped against leaving, another surface) is an interpolant of
    neither, however small the errors the bake's test rays met nearby: those rays are refused
    (WHY_PATH), then solved along a sample's path or traced. On a mirror a path is the
    sequence of patch groups it reflects off (a seam between two patches of one smooth group
    is no path boundary: the bake measured blends across it); else its ray-tree hash (the
    event kinds are in it)."""
    unit_of, _, same = _one_hash(q, b, groups=q.material.kind == "mirror")
    ok = same[unit_of]
    b.trace(b.loc.ray[b.go[~ok]], WHY_PATH)
    b.narrow(ok)


def same_path(q, b) -> None:
    """Keep the open rays whose usable samples share one ray-tree hash (``one_path``) and
    whose leaves and cell the bake did not see change path (PATH_CHANGE); decided once per
    (set, class) unit. The others are traced (WHY_PATH)."""
    unit_of, first, same = _one_hash(q, b)
    u_ok = same & ~np.any(q.tree.dir_flags[b.sets.leaf[b.set_of[first]]] & PATH_CHANGE, axis=1)
    ok = u_ok[unit_of] & (q.tree.vp_flags[b.loc.vnode[b.go]] & PATH_CHANGE == 0)
    b.trace(b.loc.ray[b.go[~ok]], WHY_PATH)
    b.narrow(ok)
