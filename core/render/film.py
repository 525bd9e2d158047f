"""The film: camera rays of a frame's samples, and their values turned into pixels.

A frame of W x H pixels at N samples per pixel has W*H*N camera rays, pixel-major (row-major,
top row first) with a pixel's samples consecutive (scene.camera.sample_positions). Rays are
made share by share (:meth:`Film.rays`), so a frame's memory is bounded by its pixels, not its
rays. Each share's values are developed into a :class:`FilmPart` (the few rows it touches),
and the parts are joined into images:

- *filtered* channels (colours): with one sample the pixel's own ray, as it is (no filter);
  with N > 1 every sample is splatted with Cycles' pixel filter, Blackman-Harris 1.5 pixels
  wide (separable: w(dx) * w(dy), dx, dy in pixels from a pixel centre), into every pixel it
  covers, and each pixel is normalized by its summed weights;
- *box* channels (masks, counts): sums over each pixel's own samples (no filter), from which
  callers take per-pixel fractions (a mask's coverage) or means.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scene.camera import pixel_rays, sample_positions

FILTER_WIDTH_PX = 1.5     # Cycles' default pixel filter width (Blackman-Harris)
_BH = (0.35875, 0.48829, 0.14128, 0.01168)    # Blackman-Harris window coefficients


def blackman_harris(x, width: float = FILTER_WIDTH_PX) -> np.ndarray:
    """The 1-D Blackman-Harris filter at ``x`` pixels from the centre, normalized to integrate
    to 1 over its support |x| <= width / 2 (0 outside); 1/px."""
    x = np.asarray(x, np.float64)
    t = 2.0 * np.pi * (x / width + 0.5)
    a0, a1, a2, a3 = _BH
    w = a0 - a1 * np.cos(t) + a2 * np.cos(2 * t) - a3 * np.cos(3 * t)
    return np.where(np.abs(x) <= 0.5 * width, w / (a0 * width), 0.0)


@dataclass
class FilmPart:
    """One share's samples developed over the window rows row0.. it touches."""
    row0: int
    weight: np.ndarray       # (rows*W,) summed filter weights
    filtered: dict           # name -> (rows*W, k) filter-weighted sums
    box: dict                # name -> (rows*W,) sums over each pixel's own samples


@dataclass
class Developed:
    """A frame's film: filtered images and per-pixel box sums, (H, W[, k]) each."""
    images: dict
    box: dict
    samples: int

    def fraction(self, name: str) -> np.ndarray:
        """Per pixel, the share of its samples ``name`` (a 0/1 box channel) counts: a float
        image in [0, 1]; with one sample per pixel a bool image."""
        s = self.box[name]
        return s > 0 if self.samples == 1 else s / self.samples

    def mean(self, name: str, count: str) -> np.ndarray:
        """Per pixel, box sum ``name`` over box count ``count``; NaN where the count is 0."""
        n = self.box[count]
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(n > 0, self.box[name] / np.maximum(n, 1), np.nan)


class Film:
    """The camera rays of a window of the frame at ``samples`` per pixel, and their pixels.

    ``window`` (col0, row0, w, h), in pixels of the width x height frame, top-down: the
    pixels rendered (default the whole frame); samples outside it are not taken, so a pixel
    on its border is filtered from the samples inside."""

    def __init__(self, cam, width: int, height: int, samples: int = 1, window=None):
        self.cam, self.width, self.height, self.samples = cam, width, height, int(samples)
        self.window = tuple(int(v) for v in (window or (0, 0, width, height)))
        self.n_rays = self.window[2] * self.window[3] * self.samples

    def _pixels(self, a: int, b: int):
        """(window pixel index, sample index) of rays a..b."""
        r = np.arange(a, b, dtype=np.int64)
        return r // self.samples, r % self.samples

    def rays(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """World-space origins and unit directions (b-a, 3) of rays a..b."""
        c0, r0, w, _ = self.window
        p, s = self._pixels(a, b)
        px, py = sample_positions(c0 + p % w, r0 + p // w, s, self.samples)
        return pixel_rays(self.cam, self.width, self.height, px, py)

    def develop(self, a: int, b: int, filtered: dict, box: dict) -> FilmPart:
        """Rays a..b's values into a FilmPart: ``filtered`` name -> (b-a, k) values (filtered
        into pixels), ``box`` name -> (b-a,) values (summed into each ray's own pixel)."""
        c0, r0, w, h = self.window
        p, s = self._pixels(a, b)
        row0 = max(int(p[0]) // w - 1, 0) if len(p) else 0
        rows = (min(int(p[-1]) // w + 2, h) - row0) if len(p) else 0
        size = rows * w
        own = p - row0 * w
        part = FilmPart(row0, np.zeros(size), {}, {})
        part.box = {k: np.bincount(own, weights=np.asarray(v, np.float64), minlength=size)
                    for k, v in box.items()}
        if self.samples == 1:
            part.weight[own] = 1.0
            part.filtered = {k: _put(size, own, v) for k, v in filtered.items()}
            return part
        part.filtered = {k: np.zeros((size, np.shape(v)[1])) for k, v in filtered.items()}
        px, py = sample_positions(c0 + p % w, r0 + p // w, s, self.samples)
        fx, fy = px - c0 - 0.5, py - r0 - 0.5      # sample relative to pixel centres, window
        col, row = p % w, p // w
        near = (-1, 0, 1)    # a sample within 0.75 px of a centre lies in or next to its pixel
        wx = [blackman_harris(fx - col - d) for d in near]
        wy = [blackman_harris(fy - row - d) for d in near]
        for dy, wty in zip(near, wy):
            for dx, wtx in zip(near, wx):
                x, y, wt = col + dx, row + dy, wtx * wty
                ok = (wt > 0) & (x >= 0) & (x < w) & (y >= 0) & (y < h)
                at = (y[ok] - row0) * w + x[ok]
                part.weight += np.bincount(at, weights=wt[ok], minlength=size)
                for k, v in filtered.items():
                    acc = part.filtered[k]
                    for c in range(acc.shape[1]):
                        acc[:, c] += np.bincount(at, weights=wt[ok] * v[ok, c], minlength=size)
        return part

    def join(self, parts) -> Developed:
        """The window's images from all its parts (pixels weighted by their summed weights)."""
        _, _, w, h = self.window
        weight = np.zeros(w * h)
        filt: dict = {}
        box: dict = {}
        for part in parts:
            sl = slice(part.row0 * w, part.row0 * w + len(part.weight))
            weight[sl] += part.weight
            for k, v in part.filtered.items():
                filt.setdefault(k, np.zeros((w * h, v.shape[1])))[sl] += v
            for k, v in part.box.items():
                box.setdefault(k, np.zeros(w * h))[sl] += v
        scale = 1.0 / np.where(weight > 0, weight, 1.0)
        images = {k: (v if self.samples == 1 else v * scale[:, None]).reshape(h, w, -1)
                  for k, v in filt.items()}
        return Developed(images, {k: v.reshape(h, w) for k, v in box.items()}, self.samples)


def _put(size: int, at: np.ndarray, values) -> np.ndarray:
    """A (size, k) array of zeros with ``values`` (n, k) at rows ``at``."""
    v = np.asarray(values, np.float64)
    out = np.zeros((size, v.shape[1]))
    out[at] = v
    return out
