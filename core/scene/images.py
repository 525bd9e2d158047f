"""The image files a scene refers to (textures, the world, image nodes): read once each,
checked to be radiance; and the images a Scene holds in memory, for writing them out."""

from __future__ import annotations

import os

import numpy as np

from ..imageio import ImageError, read_float_image, read_png, read_png_samples
from .model import Scene
from .validate import fail


class SceneImages:
    """Loads image files relative to ``base_dir`` once each (or not at all when disabled)."""

    def __init__(self, base_dir: str | None, load: bool):
        self.base_dir, self.load, self.cache = base_dir, load, {}

    def __call__(self, rel: str, path: str, encoded: bool = False) -> np.ndarray | None:
        """Linear pixels, or with ``encoded`` a PNG's sRGB-encoded samples as stored (in
        [0, 1]; .npy files are always taken as they are)."""
        if not self.load:
            return None
        full = rel if self.base_dir is None else os.path.join(self.base_dir, rel)
        key = (full, encoded and full.lower().endswith(".png"))
        if key not in self.cache:
            ext = os.path.splitext(full)[1].lower()
            if ext not in (".png", ".npy"):
                fail(path, f"unsupported image type {ext!r} (use .png or .npy)")
            if not os.path.exists(full):
                fail(path, f"image file not found: {full}")
            try:
                img = read_image(full, key[1])
            except ImageError as e:
                fail(path, str(e))
            except OSError as e:
                fail(path, f"cannot read {full} ({e.strerror})")
            check_radiance(img, full, path)
            self.cache[key] = img
        return self.cache[key]


def read_image(full: str, encoded: bool) -> np.ndarray:
    """(H, W, 3) float64 pixels of a .png or .npy file: linear, or with ``encoded`` (a PNG) its
    sRGB-encoded samples in [0, 1]. Sizes are checked from the headers before decoding."""
    if encoded:
        samples, maxcode = read_png_samples(full)
        img = samples[:, :, :3] if samples.shape[2] >= 3 else \
            np.repeat(samples[:, :, :1], 3, axis=2)
        return img.astype(np.float64) / maxcode
    return read_png(full) if full.lower().endswith(".png") else read_float_image(full)


def check_radiance(img: np.ndarray, full: str, path: str) -> None:
    """Image pixels are radiance (or reflectance): finite and >= 0."""
    if not np.isfinite(img).all():
        fail(path, f"image {full} contains NaN/inf")
    if (img < 0).any():
        i, j, c = (int(x) for x in np.argwhere(img < 0)[0])
        fail(path, f"image {full} has negative values ({float(img[i, j, c])!r} at row {i} "
                    f"column {j} channel {c}): pixels are radiance, which is >= 0")


def in_memory_images(scene: Scene) -> list:
    """[(pixels, set_path)] for every image the scene holds (textures, the world, image nodes
    of graphs), ``set_path(path)`` storing the file it is to be saved as."""
    out = []
    holders = [m.color for m in scene.materials.values() if m.kind != "nodes"] + [scene.world]
    for h in holders:
        if h.image is not None:
            out.append((h.image, lambda p, h=h: setattr(h, "path", p)))
    graphs = [m.graph for m in scene.materials.values() if m.kind == "nodes"]
    graphs += [scene.world.graph] if scene.world.kind == "nodes" else []
    for g in graphs:
        for n in g.nodes:
            if "image" in n.props:
                out.append((n.props["image"], lambda p, n=n: n.props.__setitem__("path", p)))
    return out
