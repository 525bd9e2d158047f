"""Hit points, normals and output origins that follow from the rest: not stored twice (tree
layout 5).

Every sample that hits a NURBS patch keeps its first hit's normalized patch parameters
(``uv_q``: the mirror query's Newton seeds). Its hit point and normal are the surface's at
those parameters, so the cache file keeps them only where they do not follow: on mesh patches,
and where the surface at the quantized parameters is farther than DERIVE_MAX_MOVE_REL or
DERIVE_MAX_TURN_DEG from the traced hit (a guard: 16-bit parameters move a hit by about 1e-5
of its patch). A mirror ray reflected once leaves from its hit point: an output origin within
one code unit of the hit point's is that point. Per sample ``geom`` says what follows: the
low two bits GEOM_STORED, GEOM_SURFACE (the surface's normal) or GEOM_FLIPPED (its opposite:
a sample's normal faces its ray), and the bit GEOM_OUT_AT_HIT (the output origin is the hit
point). The bake applies ``derive`` in memory, so a tree renders the same before its save and
after its load (on another machine a code may differ by one unit); a loaded tree gets them back from its object's surfaces (``fill``, which
``TreeQuery`` calls).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..trace.polish import surface_at
from .codec import decode_params, decode_points, decode_unit_vectors, encode_points, \
    encode_unit_vectors

GEOM_STORED, GEOM_SURFACE, GEOM_FLIPPED = 0, 1, 2     # bits 0-1: the point and normal
GEOM_NORMAL = 3                                       # (mask of those two bits)
GEOM_OUT_AT_HIT = 4                                   # the output origin is the hit point
# The surface at a sample's quantized parameters stands for its traced hit only within these:
# the point within this fraction of the object's (unpadded) box diagonal, the normal within
# this angle. 16-bit parameters move a hit by at most half a step times the surface's
# parametric speed: on the sample scenes' full and camera trees (6.9 M hits) by at most
# 3.5e-5 of the diagonal (three point codes) and 0.026 degrees.
DERIVE_MAX_MOVE_REL = 1e-4
DERIVE_MAX_TURN_DEG = 0.1
# Hits per block of surface evaluation (bounds the float64 work arrays to ~0.3 GB).
DERIVE_BLOCK = 1 << 20


def derive(samples, tracer, diag: float):
    """``samples`` (PackedSamples) with the point and normal codes of every hit that follows
    from its patch and parameters replaced by the surface's there, and the output origin of
    every such hit that left there (codes within one unit) by its point; ``geom`` records
    which. ``tracer``: the object's PatchTracer; ``diag``: its (unpadded) box diagonal (scene
    units). ``samples`` must hold traced codes (not a loaded file's pending ones)."""
    if samples.pending:
        raise ValueError("derive needs traced samples, not a loaded tree's pending ones")
    out = replace(samples, point_q=samples.point_q.copy(), normal_q=samples.normal_q.copy(),
                  out_o_q=samples.out_o_q.copy(), geom=np.zeros(len(samples), np.uint8),
                  pending=False)
    move = DERIVE_MAX_MOVE_REL * diag
    min_cos = np.cos(np.radians(DERIVE_MAX_TURN_DEG))
    for hit in _blocks(np.flatnonzero(samples.patch >= 0)):
        pt, nm, ok = surface_at(tracer, samples.patch[hit], decode_params(samples.uv_q[hit]))
        p0 = decode_points(samples.point_q[hit], samples.lo, samples.hi)
        n0 = decode_unit_vectors(samples.normal_q[hit])
        flip = np.einsum("ij,ij->i", nm, n0) < 0
        nm[flip] *= -1
        near = ok & (np.linalg.norm(pt - p0, axis=1) <= move) \
            & (np.einsum("ij,ij->i", nm, n0) >= min_cos)
        at_hit = near & np.all(np.abs(samples.out_o_q[hit].astype(np.int64)
                                      - samples.point_q[hit]) <= 1, axis=1)
        rows = hit[near]
        out.geom[rows] = np.where(flip[near], GEOM_FLIPPED, GEOM_SURFACE)
        out.geom[hit[at_hit]] |= GEOM_OUT_AT_HIT
        out.point_q[rows] = encode_points(pt[near], samples.lo, samples.hi)[0]
        out.normal_q[rows] = encode_unit_vectors(nm[near])
        out.out_o_q[hit[at_hit]] = out.point_q[hit[at_hit]]
    return out


def fill(samples, tracer):
    """``samples`` (PackedSamples, a loaded file's: ``pending``) with the point, normal and
    output origin codes that follow computed from ``tracer``'s surfaces, as ``derive`` made
    them. ValueError where a derived hit's patch is not a NURBS patch of ``tracer`` (another
    object's tree)."""
    out = replace(samples, point_q=samples.point_q.copy(), normal_q=samples.normal_q.copy(),
                  out_o_q=samples.out_o_q.copy(), pending=False)
    for rows in _blocks(np.flatnonzero(samples.geom & GEOM_NORMAL != GEOM_STORED)):
        patch = samples.patch[rows].astype(np.int64)
        if len(rows) and patch.max() >= len(tracer.piece_base):
            raise ValueError("the tree's samples hit patches this object does not have")
        pt, nm, ok = surface_at(tracer, patch, decode_params(samples.uv_q[rows]))
        if not ok.all():
            raise ValueError("the tree's samples hit NURBS patches where this object has "
                             "meshes")
        nm[samples.geom[rows] & GEOM_NORMAL == GEOM_FLIPPED] *= -1
        out.point_q[rows] = encode_points(pt, samples.lo, samples.hi)[0]
        out.normal_q[rows] = encode_unit_vectors(nm)
    at = np.flatnonzero(samples.geom & GEOM_OUT_AT_HIT)
    out.out_o_q[at] = out.point_q[at]
    return out


def _blocks(rows: np.ndarray) -> list[np.ndarray]:
    """``rows`` in consecutive blocks of at most DERIVE_BLOCK (one, possibly empty, at least)."""
    return np.array_split(rows, max(1, -(-len(rows) // DERIVE_BLOCK)))


def valid_codes(geom: np.ndarray) -> bool:
    """Whether ``geom`` (a file's, hits only) holds only codes ``derive`` makes."""
    low = geom & GEOM_NORMAL
    return bool(np.all((geom & ~np.uint8(7) == 0) & (low != 3)
                       & ((geom & GEOM_OUT_AT_HIT == 0) | (low != GEOM_STORED))))


def kept_rows(geom: np.ndarray) -> dict[str, np.ndarray]:
    """Of hits with ``geom`` codes, which rows' point / normal and output-origin codes a file
    keeps: {"point_q", "normal_q", "out_o_q"} -> bool masks."""
    own = geom & GEOM_NORMAL == GEOM_STORED
    return {"point_q": own, "normal_q": own, "out_o_q": geom & GEOM_OUT_AT_HIT == 0}
