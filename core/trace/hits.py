"""The exact tracer's answer for a batch of rays: their nearest hits on the object's patches."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PatchHit:
    """Nearest hits of a batch of rays. Arrays are (N,) or (N,3); misses have t = inf,
    patch = -1, cls = -1, tri = -1 and zero point/normals/uv. ``normal`` is the unit shading
    normal and ``geo_normal`` the unit geometric normal, both as the surface is oriented (not
    flipped toward the ray): the same on a NURBS patch, the blend of the corner normals and the
    triangle's winding normal on a smooth mesh patch. (u, v) are the patch's own parameters
    (barycentric (b1, b2) for mesh patches, on triangle ``tri`` of the tracer's mesh patches,
    ``PatchTracer.meshes``; -1 on NURBS)."""

    hit: np.ndarray
    t: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    patch: np.ndarray
    cls: np.ndarray
    u: np.ndarray
    v: np.ndarray
    geo_normal: np.ndarray
    tri: np.ndarray

    @classmethod
    def misses(cls, n: int) -> "PatchHit":
        """``n`` rays that hit nothing (yet)."""
        return cls(hit=np.zeros(n, bool), t=np.full(n, np.inf), point=np.zeros((n, 3)),
                   normal=np.zeros((n, 3)), patch=np.full(n, -1, np.int64),
                   cls=np.full(n, -1, np.int64), u=np.zeros(n), v=np.zeros(n),
                   geo_normal=np.zeros((n, 3)), tri=np.full(n, -1, np.int64))

    def take(self, idx) -> "PatchHit":
        """The rows ``idx`` of every array."""
        return PatchHit(**{k: v[idx] for k, v in self.__dict__.items()})

    def put(self, rows, other: "PatchHit") -> None:
        """Overwrite rows ``rows`` with ``other`` (len(rows) hits), in place."""
        for k, v in self.__dict__.items():
            v[rows] = getattr(other, k)
