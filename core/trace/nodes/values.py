"""The points being shaded, the closure a graph returns, and the value helpers every node uses:
float values are arrays (N,) or () constants, vectors and colours (N, 3) or (3,)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...scene.graph import COLOR, FLOAT, LUMA, SHADER, VECTOR


@dataclass
class ShadingPoints:
    """N points being shaded (world space, float64). ``normal`` (shading) and ``true_normal``
    (geometric) face the incoming ray; ``incoming`` is the unit vector back towards the ray
    origin; ``uv`` the mesh's texture coordinates (zeros without a UV map); ``backfacing`` where
    the ray hit the side the winding normal points away from."""

    position: np.ndarray      # (N, 3)
    normal: np.ndarray        # (N, 3)
    true_normal: np.ndarray   # (N, 3)
    incoming: np.ndarray      # (N, 3)
    uv: np.ndarray            # (N, 2)
    backfacing: np.ndarray    # (N,) bool

    @classmethod
    def world(cls, dirs: np.ndarray) -> "ShadingPoints":
        """Background shading of unit ray directions ``dirs`` (N, 3): position D, normals and
        incoming -D, uv 0 (Cycles' shader_setup_from_background)."""
        d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        return cls(position=d, normal=-d, true_normal=-d, incoming=-d,
                   uv=np.zeros((len(d), 2)), backfacing=np.zeros(len(d), bool))

    def __len__(self) -> int:
        return len(self.position)


@dataclass
class Closure:
    """Emitted radiance and diffuse albedo, (N, 3) each (or broadcastable constants inside the
    evaluator)."""

    emission: np.ndarray
    albedo: np.ndarray


def closure(c) -> Closure:
    """``c``, or the black closure for an unlinked shader input (None)."""
    return c if c is not None else Closure(emission=np.zeros(3), albedo=np.zeros(3))


def gray(c):
    """Luminance of colours ``c`` (..., 3) with Blender's weights."""
    return c @ np.asarray(LUMA)


def convert(v, src: str, dst: str):
    """A value of kind ``src`` as kind ``dst`` (graph.py's conversion rules)."""
    if src == dst or {src, dst} == {VECTOR, COLOR}:
        return v
    if dst == SHADER:
        return Closure(emission=convert(v, src, COLOR), albedo=np.zeros(3))
    if src == FLOAT:
        return np.asarray(v)[..., None] * np.ones(3)
    return gray(v) if src == COLOR else np.mean(v, axis=-1)


def expand(x):
    """``x`` (a float value) shaped to broadcast against vectors."""
    return np.asarray(x)[..., None]


def safe_divide(a, b):
    """a / b, 0 where b is 0."""
    b = np.asarray(b)
    return np.where(b != 0, a / np.where(b != 0, b, 1.0), 0.0)


def safe_normalize(v):
    """Unit vectors along ``v`` (..., 3); zero vectors stay zero."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n != 0, v / np.where(n != 0, n, 1.0), v)


def dot(a, b):
    """Dot products along the last axis."""
    return np.sum(np.asarray(a) * np.asarray(b), axis=-1)


def affine(m: np.ndarray, p):
    """Points p (..., 3) through the 4 x 4 affine matrix ``m``."""
    return np.asarray(p) @ m[:3, :3].T + m[:3, 3]


def saturate(x):
    """x clamped to [0, 1]."""
    return np.clip(x, 0.0, 1.0)
