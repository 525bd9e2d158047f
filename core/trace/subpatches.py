"""The object's NURBS patches as flat sub-patches: each patch cut into rational Bezier pieces
and subdivided until its net is flat (``geometry.bezier``), with conservative boxes, stacked
per degree, one BVH over all (``flat_subpatches``); each patch's parameter domain and whether it
is closed (``bezier_pieces``). Lengths are in scene units (metres)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import bezier as bz
from ..geometry.nurbs import evaluate as nurbs_evaluate
from ..scene.model import SpecularObject
from .bvh import BVH

# Flatness of sub-patches, relative to the object's bounding-box diagonal: the control net
# deviates from its bilinear corner interpolation by at most this much (a good Newton seed).
FLAT_TOL_REL = 2e-3
# A root whose ray makes an angle below the sub-patch's normal-cone half-angle with the tangent
# plane may have a twin root in the same sub-patch (two roots in one net need the normal to turn
# by at least twice that angle). The cone of a rational net is an estimate: it is widened by
# this factor and margin before use.
TWIN_CONE_SAFETY = 1.5
TWIN_CONE_MARGIN_DEG = 1.0
# A patch is closed in u (v) where its two u (v) edges coincide within this distance, relative to
# the object's diagonal, at CLOSED_PROBES points along them.
CLOSED_TOL_REL = 1e-9
CLOSED_PROBES = 9


@dataclass
class SubPatchGroup:
    """Sub-patches of one (degree_u, degree_v), from all NURBS patches of the object."""

    ctrl: np.ndarray      # (M, p+1, q+1, 4) homogeneous
    patch: np.ndarray     # (M,) patch id
    cone_sin: np.ndarray  # (M,) sine of the (widened) normal-cone half-angle: grazing limit
    u0: np.ndarray        # (M,) NURBS parameter rectangle of the sub-patch
    u1: np.ndarray
    v0: np.ndarray
    v1: np.ndarray
    ps0: np.ndarray       # (M,) the sub-patch's rectangle in its Bezier piece's [0,1]^2
    ps1: np.ndarray
    pt0: np.ndarray
    pt1: np.ndarray


def bezier_pieces(obj: SpecularObject, diag: float):
    """({patch id: its Bezier pieces} for the NURBS patches; (P, 4) every patch's parameter
    domain (u0, u1, v0, v1); (P, 2) whether it is closed in u / in v) for an object whose box
    diagonal is ``diag`` (m)."""
    # each patch's parameter domain (u0, u1, v0, v1): NURBS knot range, [0, 1]^2 for a
    # mesh patch (barycentric); PatchHit (u, v) divided by it is the normalized parameter
    uv_domain = np.tile(np.array([0.0, 1.0, 0.0, 1.0]), (len(obj.patches), 1))
    pieces: dict[int, bz.BezierPieces] = {}
    # (P, 2): the patch is closed in u / in v (its two edges coincide: a surface of
    # revolution's seam), so parameters wrap around
    closed = np.zeros((len(obj.patches), 2), bool)
    for pid, patch in enumerate(obj.patches):
        if patch.surface is None:
            continue
        pcs = pieces[pid] = bz.extract_bezier(patch.surface)
        uv_domain[pid] = (pcs.u0.min(), pcs.u1.max(), pcs.v0.min(), pcs.v1.max())
        closed[pid] = _closed(patch.surface, uv_domain[pid], CLOSED_TOL_REL * diag)
    return pieces, uv_domain, closed


def flat_subpatches(pieces: dict, diag: float):
    """(groups: list[SubPatchGroup], sub_group, sub_local, bvh) for the Bezier pieces of each
    patch (``bezier_pieces``) of an object whose box diagonal is ``diag`` (m): the BVH's
    primitive k is sub-patch sub_local[k] of groups[sub_group[k]]; bvh None without pieces."""
    flat_tol = FLAT_TOL_REL * diag
    recs_of: dict[tuple[int, int], list] = {}
    for pid, pcs in pieces.items():
        sub = bz.subdivide_flat(pcs, flat_tol)
        pi = sub.piece
        du = pcs.u1[pi] - pcs.u0[pi]
        dv = pcs.v1[pi] - pcs.v0[pi]
        cone = TWIN_CONE_SAFETY * bz.normal_cone_half_angle(sub.ctrl) \
            + np.radians(TWIN_CONE_MARGIN_DEG)
        rec = (sub.ctrl, np.full(len(pi), pid), np.sin(np.minimum(cone, np.pi / 2)),
               pcs.u0[pi] + du * sub.s0, pcs.u0[pi] + du * sub.s1,
               pcs.v0[pi] + dv * sub.t0, pcs.v0[pi] + dv * sub.t1,
               sub.s0, sub.s1, sub.t0, sub.t1, sub.lo, sub.hi)
        recs_of.setdefault(sub.ctrl.shape[1:3], []).append(rec)
    groups: list[SubPatchGroup] = []
    los, his, gid = [], [], []
    for g, recs in enumerate(recs_of.values()):
        cat = [np.concatenate([r[k] for r in recs]) for k in range(13)]
        groups.append(SubPatchGroup(*cat[:11]))
        los.append(cat[11])
        his.append(cat[12])
        gid.append(np.full(len(cat[0]), g))
    if not los:
        return groups, np.zeros(0, np.int64), np.zeros(0, np.int64), None
    sub_local = np.concatenate([np.arange(len(g.patch)) for g in groups])
    bvh = BVH.build(np.concatenate(los), np.concatenate(his))
    return groups, np.concatenate(gid), sub_local, bvh


def _closed(surf, dom, tol) -> tuple[bool, bool]:
    """Whether NURBS ``surf`` (domain ``dom`` = u0, u1, v0, v1) is closed in u and in v."""
    x = np.linspace(0.0, 1.0, CLOSED_PROBES)
    out = []
    for edge in ((dom[0], dom[1], dom[2] + x * (dom[3] - dom[2]), True),
                 (dom[2], dom[3], dom[0] + x * (dom[1] - dom[0]), False)):
        lo, hi, along, is_u = edge
        a = np.full(CLOSED_PROBES, lo)
        b = np.full(CLOSED_PROBES, hi)
        p0 = nurbs_evaluate(surf, a, along, 0)[0] if is_u else nurbs_evaluate(surf, along, a, 0)[0]
        p1 = nurbs_evaluate(surf, b, along, 0)[0] if is_u else nurbs_evaluate(surf, along, b, 0)[0]
        out.append(bool(np.linalg.norm(p0 - p1, axis=1).max() <= tol))
    return out[0], out[1]
