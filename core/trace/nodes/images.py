"""Image and Environment Texture nodes: images sampled like Cycles' CPU image kernel (pixel
centres at (i + 0.5) / W), flat or box projection, and Blender's equirectangular map."""

from __future__ import annotations

import numpy as np

from .colour import srgb_to_linear
from .values import safe_normalize, saturate


def _wrap_index(i, n: int, extension: str):
    if extension == "repeat":
        return i % n
    if extension == "mirror":
        m = np.abs(i + (i < 0)) % (2 * n)
        return np.where(m >= n, 2 * n - m - 1, m)
    return np.clip(i, 0, n - 1)


def _read(image, ix, iy, extension: str):
    """Pixels at column ix, row iy counted from the bottom (Cycles' convention); with "clip"
    indices outside the image read black."""
    h, w = image.shape[:2]
    if extension == "clip":
        inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
        px = image[h - 1 - np.clip(iy, 0, h - 1), np.clip(ix, 0, w - 1)]
        return np.where(inside[..., None], px, 0.0)
    return image[h - 1 - _wrap_index(iy, h, extension), _wrap_index(ix, w, extension)]


def sample_image(image: np.ndarray, x, y, interpolation: str, extension: str,
                 srgb: bool) -> np.ndarray:
    """(N, 3) of an (H, W, 3) image (rows top first) at texture coordinates (x, y), (0, 0) the
    bottom-left corner, like Cycles' CPU image kernel: "closest" reads pixel floor(x W),
    "linear" blends the four pixels around (x W - 0.5, y H - 0.5); ``extension`` repeat /
    extend (clamp) / clip (black outside) / mirror. ``srgb``: the pixels are sRGB-encoded and
    are linearized after interpolation (Cycles' 8-bit sRGB images)."""
    h, w = image.shape[:2]
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    x, y = np.nan_to_num(x), np.nan_to_num(y)
    if interpolation == "closest":
        out = _read(image, np.floor(x * w).astype(np.int64), np.floor(y * h).astype(np.int64),
                    extension)
    else:
        fx, fy = x * w - 0.5, y * h - 0.5
        ix, iy = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
        tx, ty = (fx - ix)[..., None], (fy - iy)[..., None]
        out = ((1 - ty) * ((1 - tx) * _read(image, ix, iy, extension)
                           + tx * _read(image, ix + 1, iy, extension))
               + ty * ((1 - tx) * _read(image, ix, iy + 1, extension)
                       + tx * _read(image, ix + 1, iy + 1, extension)))
    return srgb_to_linear(out) if srgb else out


def _box_weights(n, blend: float) -> np.ndarray:
    """(N, 3) blend weights of the x, y, z projections for object-space normals ``n``
    (Cycles' svm_node_tex_image_box)."""
    a = np.abs(np.asarray(n, float))
    s = a.sum(axis=-1, keepdims=True)
    a = a / np.where(s > 0, s, 1.0)
    nx, ny, nz = a[..., 0], a[..., 1], a[..., 2]
    limit = 0.5 * (1.0 + blend)
    w = np.zeros(a.shape)
    cx = (nx > limit * (nx + ny)) & (nx > limit * (nx + nz))
    cy = ~cx & (ny > limit * (nx + ny)) & (ny > limit * (ny + nz))
    cz = ~cx & ~cy & (nz > limit * (nx + nz)) & (nz > limit * (ny + nz))
    rest = ~(cx | cy | cz)
    w[cx, 0] = w[cy, 1] = w[cz, 2] = 1.0
    if blend <= 0:
        w[rest, 0] = 1.0
        return w
    with np.errstate(all="ignore"):
        c4 = rest & (nz < (1.0 - limit) * (ny + nx))
        c5 = rest & ~c4 & (nx < (1.0 - limit) * (ny + nz))
        c6 = rest & ~c4 & ~c5 & (ny < (1.0 - limit) * (nx + nz))
        c7 = rest & ~(c4 | c5 | c6)
        off = 0.5 * (1.0 - blend)
        wx = saturate((nx / (nx + ny) - off) / blend)
        w[c4, 0], w[c4, 1] = wx[c4], 1.0 - wx[c4]
        wy = saturate((ny / (ny + nz) - off) / blend)
        w[c5, 1], w[c5, 2] = wy[c5], 1.0 - wy[c5]
        wx2 = saturate((nx / (nx + nz) - off) / blend)
        w[c6, 0], w[c6, 2] = wx2[c6], 1.0 - wx2[c6]
        three = ((2.0 - limit) * a + (limit - 1.0)) / (2.0 * limit - 1.0)
    w[c7] = three[c7]
    return w


def equirectangular(d) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) of Blender's equirectangular map for directions d: u = 0.5 - atan2(dy, dx)/(2 pi)
    (+X at the centre), v = 0.5 + atan2(dz, hypot(dx, dy))/pi (the zenith at the top)."""
    d = np.asarray(d, float)
    u = 0.5 - np.arctan2(d[..., 1], d[..., 0]) / (2.0 * np.pi)
    v = 0.5 + np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1])) / np.pi
    return u, v


# --------------------------------------------------------------------------- nodes
# Every node evaluation: (node, inputs, shading points, wanted outputs) -> {output: value}
def image(node, inp, pts, want) -> dict:
    """Image Texture: flat (x, y of the vector) or box projection (three projections blended
    by the object-space normal)."""
    pr = node.props
    img, interp, ext, srgb = pr["image"], pr["interpolation"], pr["extension"], pr["srgb"]
    co = np.broadcast_to(np.asarray(inp["vector"], float), (len(pts), 3))
    if pr["projection"] == "flat":
        return {"color": sample_image(img, co[:, 0], co[:, 1], interp, ext, srgb)}
    n = pts.normal @ np.asarray(pr["normal_matrix"]).T
    w = _box_weights(n, float(pr["blend"]))
    x, y, z = co[:, 0], co[:, 1], co[:, 2]
    out = np.zeros((len(pts), 3))
    for k, (u, v) in enumerate(((np.where(n[:, 0] < 0, 1.0 - y, y), z),
                                (np.where(n[:, 1] > 0, 1.0 - x, x), z),
                                (np.where(n[:, 2] > 0, 1.0 - y, y), x))):
        sel = w[:, k] > 0
        if sel.any():
            out[sel] += w[sel, k, None] * sample_image(img, u[sel], v[sel], interp, ext, srgb)
    return {"color": out}


def environment(node, inp, pts, want) -> dict:
    """Environment Texture: the equirectangular image in the vector's direction."""
    pr = node.props
    u, v = equirectangular(safe_normalize(np.broadcast_to(
        np.asarray(inp["vector"], float), (len(pts), 3))))
    return {"color": sample_image(pr["image"], u, v, pr["interpolation"], "repeat", pr["srgb"])}


NODES = {"image": image, "environment": environment}
