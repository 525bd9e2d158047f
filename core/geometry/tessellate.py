"""Triangle tessellation of NURBS surfaces (shadow proxies, previews): not used for exact hits."""

from __future__ import annotations

import numpy as np

from .nurbs import NurbsSurface, evaluate


def tessellate(surf: NurbsSurface, n_u: int = 24, n_v: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ((n_u+1)(n_v+1), 3) on a uniform parameter grid and (2 n_u n_v, 3) triangles."""
    u0, u1, v0, v1 = surf.domain
    uu, vv = np.meshgrid(np.linspace(u0, u1, n_u + 1), np.linspace(v0, v1, n_v + 1), indexing="ij")
    (pts,) = evaluate(surf, uu.ravel(), vv.ravel(), derivatives=0)
    idx = np.arange((n_u + 1) * (n_v + 1)).reshape(n_u + 1, n_v + 1)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return pts, tris.astype(np.int64)
