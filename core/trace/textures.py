"""Texture and world (background) evaluation, vectorized over points / directions.

Texture coordinates (``Texture.coords``): "world" uses world xyz in metres (2D kinds, i.e.
"image", use (x, y)); "uv" uses the mesh UVs (u, v) and a third coordinate 0. Kinds:
  constant  ``color``
  checker   ``color`` where floor(c0*s) + floor(c1*s) [+ floor(c2*s)] is even, else ``color2``
            (3D in world coords, 2D on uv); s = ``scale`` checks per unit
  stripes   ``color`` where floor(c[axis]*s) is even, else ``color2``: bands 1/s wide
  gradient  ``color`` -> ``color2`` linearly as c[axis] goes ``start`` -> ``end`` (clamped)
  image     bilinear lookup at (u, v) * scale, repeat wrap; (0, 0) is the bottom-left corner of
            the image and (1, 1) the top-right (Blender's convention); pixel centres at
            ((i + 0.5) / W, 1 - (j + 0.5) / H) for column i, row j (rows top first)
World kinds (returned colours are multiplied by ``World.strength``):
  color     ``color``
  gradient  ``color`` (horizon) -> ``zenith`` with t = clamp(d_z, 0, 1); every direction at or
            below the horizon sees the horizon colour
  image     equirectangular, Blender's Environment Texture mapping: u = 0.5 - atan2(dy, dx)/(2 pi)
            (+X at the centre column, +Y at u = 0.25), v = 0.5 + atan2(dz, hypot(dx, dy))/pi
            (zenith at the top row); u wraps, v is clamped.
  nodes     the emission of the world's shader node graph (trace/nodes.py) for each direction
"""

from __future__ import annotations

import numpy as np

from ..scene.model import Texture, World
from .nodes import ShadingPoints, equirectangular, evaluate

# Checker/stripe coordinates are offset by this many checks before flooring so that surfaces lying
# exactly on a check boundary (a floor at z = 0 hit at z = -1e-15) do not flicker between colours.
CHECK_BIAS = 1e-6


def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray, wrap_v: bool) -> np.ndarray:
    """Bilinear sample of an (H, W, 3) image (rows top first) at (u, v), v up; u repeats,
    v repeats when ``wrap_v`` else clamps to the first/last row centres."""
    h, w = image.shape[:2]
    x = u * w - 0.5
    y = (1.0 - v) * h - 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    x0 = x0.astype(np.int64)
    y0 = y0.astype(np.int64)
    xa, xb = x0 % w, (x0 + 1) % w
    if wrap_v:
        ya, yb = y0 % h, (y0 + 1) % h
    else:
        ya, yb = np.clip(y0, 0, h - 1), np.clip(y0 + 1, 0, h - 1)
    top = image[ya, xa] * (1 - fx) + image[ya, xb] * fx
    bot = image[yb, xa] * (1 - fx) + image[yb, xb] * fx
    return top * (1 - fy) + bot * fy


def _two_tone(tex: Texture, odd: np.ndarray) -> np.ndarray:
    return np.where(odd[:, None], np.asarray(tex.color2, float), np.asarray(tex.color, float))


def eval_texture(tex: Texture, points: np.ndarray, uvs: np.ndarray | None) -> np.ndarray:
    """Colour (N, 3) float64 of ``tex`` at world ``points`` (N, 3) with mesh ``uvs`` (N, 2) or None.

    Raises ValueError when the texture needs UVs and ``uvs`` is None, or an image is not loaded.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = points.shape[0]
    if tex.kind == "constant":
        return np.broadcast_to(np.asarray(tex.color, float), (n, 3)).copy()
    if tex.coords == "uv":
        if uvs is None:
            raise ValueError(f"texture kind {tex.kind!r} with coords 'uv' needs mesh UVs")
        uv = np.asarray(uvs, dtype=np.float64).reshape(-1, 2)
        c = np.concatenate([uv, np.zeros((n, 1))], axis=1)
    else:
        c = points
    if tex.kind == "checker":
        dims = 2 if tex.coords == "uv" else 3
        idx = np.floor(c[:, :dims] * tex.scale + CHECK_BIAS).sum(axis=1)
        return _two_tone(tex, idx % 2 != 0)
    if tex.kind == "stripes":
        return _two_tone(tex, np.floor(c[:, tex.axis] * tex.scale + CHECK_BIAS) % 2 != 0)
    if tex.kind == "gradient":
        t = np.clip((c[:, tex.axis] - tex.start) / (tex.end - tex.start), 0.0, 1.0)[:, None]
        return (1 - t) * np.asarray(tex.color, float) + t * np.asarray(tex.color2, float)
    if tex.kind == "image":
        if tex.image is None or tex.image.size == 0:
            raise ValueError(f"image texture {tex.path!r} is not loaded or has no pixels")
        return _bilinear(tex.image, c[:, 0] * tex.scale, c[:, 1] * tex.scale, wrap_v=True)
    raise ValueError(f"unknown texture kind {tex.kind!r}")


def eval_world(world: World, dirs: np.ndarray) -> np.ndarray:
    """Background colour (N, 3) float64 seen along unit directions ``dirs`` (N, 3)."""
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    n = d.shape[0]
    if world.kind == "color":
        col = np.broadcast_to(np.asarray(world.color, float), (n, 3))
    elif world.kind == "gradient":
        t = np.clip(d[:, 2], 0.0, 1.0)[:, None]
        col = (1 - t) * np.asarray(world.color, float) + t * np.asarray(world.zenith, float)
    elif world.kind == "image":
        if world.image is None or world.image.size == 0:
            raise ValueError(f"world image {world.path!r} is not loaded or has no pixels")
        u, v = equirectangular(d)
        col = _bilinear(world.image, u, v, wrap_v=False)
    elif world.kind == "nodes":
        col = evaluate(world.graph, ShadingPoints.world(d)).emission
    else:
        raise ValueError(f"unknown world kind {world.kind!r}")
    return col * world.strength
