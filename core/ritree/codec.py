"""Compact, vectorized encodings for RI-Tree arrays, each with a proven worst-case error.

- Unit vectors <-> octahedral codes, 2 x int16 per vector (Cigolle et al. 2014, round to
  nearest). Worst angular error ``OCT_MAX_ERROR`` = 3 sqrt(2) / (2 * 32767) ~ 6.47e-5 rad: rounding
  moves the octahedral point by at most half a cell diagonal, sqrt(2) / (2 * 32767), and the
  map from the octahedral square to the sphere stretches lengths by at most 3 (at the centre of
  an octahedron face, where |p| = 1/sqrt(3) and a unit step in the square is sqrt(3) long).
  The zero vector (direction of a null ray) has the reserved code (-32768, -32768) and decodes
  to exactly (0, 0, 0). Inputs need not be unit length; any non-zero vector encodes its direction.
- Points <-> unsigned integer codes (uint16 or uint32 per coordinate) on a uniform grid of the
  box [lo, hi]. Worst error per axis ``point_error_bound(lo, hi, bits)`` = (hi - lo) / (2^bits - 1)
  / 2 plus float64 rounding (a few ulps of max(|lo|, |hi|)); points outside the box are clamped
  to it and counted.
- Normalized patch parameters in [0, 1]^2 <-> 2 x uint16 codes on a uniform grid (worst error
  1 / (2 * 65535) per coordinate; values outside are clamped).
Arrays of any leading shape are accepted; work is done in blocks of ``BLOCK`` rows.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

OCT_SCALE = 32767                                  # octahedral codes lie in [-32767, 32767]
OCT_ZERO = -32768                                  # reserved code component: the zero vector
OCT_MAX_ERROR = 3.0 * np.sqrt(2.0) / (2.0 * OCT_SCALE)   # rad, worst case of the round trip
POINT_DTYPES = {16: np.uint16, 32: np.uint32}      # bits per coordinate -> code dtype
# Rows per block: bounds the float64 temporaries to a few tens of MB for any input size.
BLOCK = 1 << 18


def _blockwise(fn: Callable[[np.ndarray], np.ndarray], x: np.ndarray, width: int,
               dtype) -> np.ndarray:
    """Apply ``fn`` to (rows, x.shape[-1]) blocks of ``x``; output (..., width) of ``dtype``."""
    flat = x.reshape(-1, x.shape[-1])
    out = np.empty((flat.shape[0], width), dtype)
    for i in range(0, flat.shape[0], BLOCK):
        out[i:i + BLOCK] = fn(flat[i:i + BLOCK])
    return out.reshape(x.shape[:-1] + (width,))


def _last_axis(x, n: int, name: str) -> np.ndarray:
    x = np.asarray(x)
    if x.ndim == 0 or x.shape[-1] != n:
        raise ValueError(f"{name}: expected shape (..., {n}), got {x.shape}")
    return x


def _sign(x: np.ndarray) -> np.ndarray:
    """+1 for x >= 0 (zero included, so the fold is well defined on the axes), else -1."""
    return np.where(x >= 0, 1.0, -1.0)


# --------------------------------------------------------------------------- unit vectors
def _oct_encode_block(v: np.ndarray) -> np.ndarray:
    l1 = np.abs(v).sum(axis=1)
    zero = l1 == 0
    p = v[:, :2] / np.where(zero, 1.0, l1)[:, None]
    folded = (1.0 - np.abs(p[:, ::-1])) * _sign(p)
    p = np.where((v[:, 2] < 0)[:, None], folded, p)
    q = np.rint(p * OCT_SCALE).astype(np.int16)
    q[zero] = OCT_ZERO
    return q


def _oct_decode_block(q: np.ndarray) -> np.ndarray:
    p = q.astype(np.float64) / OCT_SCALE
    z = 1.0 - np.abs(p).sum(axis=1)
    unfolded = (1.0 - np.abs(p[:, ::-1])) * _sign(p)
    v = np.empty((q.shape[0], 3))
    v[:, :2] = np.where((z < 0)[:, None], unfolded, p)
    v[:, 2] = z
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v[(q == OCT_ZERO).any(axis=1)] = 0.0
    return v


def encode_unit_vectors(v) -> np.ndarray:
    """(..., 3) float vectors -> (..., 2) int16 octahedral codes; zero vectors -> (-32768, -32768).

    Raises ValueError on non-finite components.
    """
    v = _last_axis(v, 3, "vectors").astype(np.float64, copy=False)
    if not np.isfinite(v).all():
        raise ValueError("vectors: non-finite components cannot be encoded")
    return _blockwise(_oct_encode_block, v, 2, np.int16)


def decode_unit_vectors(codes) -> np.ndarray:
    """(..., 2) int16 octahedral codes -> (..., 3) float64 unit vectors (zero for the zero code)."""
    codes = _last_axis(codes, 2, "codes")
    if codes.dtype != np.int16:
        raise ValueError(f"codes: expected int16 octahedral codes, got {codes.dtype}")
    return _blockwise(_oct_decode_block, codes, 3, np.float64)


# --------------------------------------------------------------------------- points in a box
def _box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """lo, hi as float64 (3,) (scalars broadcast); checks finite and lo <= hi."""
    try:
        lo, hi = (np.broadcast_to(np.asarray(x, np.float64), (3,)) for x in (lo, hi))
    except ValueError:
        raise ValueError(f"box: lo and hi must be scalars or 3-vectors, got {lo!r}, {hi!r}") \
            from None
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi >= lo).all()):
        raise ValueError(f"box: need finite lo <= hi per axis, got lo={lo}, hi={hi}")
    return lo, hi


def _levels(bits: int) -> int:
    if bits not in POINT_DTYPES:
        raise ValueError(f"bits: expected one of {sorted(POINT_DTYPES)}, got {bits}")
    return (1 << bits) - 1


def point_error_bound(lo, hi, bits: int = 16) -> np.ndarray:
    """Worst-case per-axis error (3,) of a point round trip inside the box (before rounding)."""
    lo, hi = _box(lo, hi)
    return (hi - lo) / _levels(bits) / 2.0


def encode_points(points, lo, hi, bits: int = 16) -> tuple[np.ndarray, int]:
    """(..., 3) points -> ((..., 3) uint16/uint32 grid codes of the box [lo, hi], n_clamped).

    n_clamped counts points with a coordinate outside the box (they are clamped onto it). An axis
    with hi == lo encodes every coordinate as 0. Raises ValueError on non-finite points.
    """
    lo, hi = _box(lo, hi)
    levels = _levels(bits)
    x = _last_axis(points, 3, "points").astype(np.float64, copy=False)
    if not np.isfinite(x).all():
        raise ValueError("points: non-finite coordinates cannot be encoded")
    extent = hi - lo
    scale = np.divide(levels, extent, out=np.zeros(3), where=extent > 0)
    outside = ((x < lo) | (x > hi)).any(axis=-1)

    def block(b: np.ndarray) -> np.ndarray:
        return np.rint(np.clip((b - lo) * scale, 0, levels))

    return _blockwise(block, x, 3, POINT_DTYPES[bits]), int(outside.sum())


def decode_points(codes, lo, hi) -> np.ndarray:
    """(..., 3) uint16/uint32 grid codes of the box [lo, hi] -> (..., 3) float64 points."""
    lo, hi = _box(lo, hi)
    codes = _last_axis(codes, 3, "codes")
    bits = {np.dtype(t): b for b, t in POINT_DTYPES.items()}.get(codes.dtype)
    if bits is None:
        raise ValueError(f"codes: expected uint16 or uint32 point codes, got {codes.dtype}")
    step = (hi - lo) / _levels(bits)
    return _blockwise(lambda b: lo + b * step, codes, 3, np.float64)


# --------------------------------------------------------------------------- patch parameters
PARAM_LEVELS = (1 << 16) - 1


def encode_params(uv) -> np.ndarray:
    """(..., 2) normalized patch parameters in [0, 1] -> (..., 2) uint16 codes (clamped)."""
    x = _last_axis(uv, 2, "parameters").astype(np.float64, copy=False)
    if not np.isfinite(x).all():
        raise ValueError("parameters: non-finite values cannot be encoded")
    return np.rint(np.clip(x, 0.0, 1.0) * PARAM_LEVELS).astype(np.uint16)


def decode_params(codes) -> np.ndarray:
    """(..., 2) uint16 codes -> (..., 2) float64 normalized parameters."""
    return _last_axis(codes, 2, "codes").astype(np.float64) / PARAM_LEVELS
