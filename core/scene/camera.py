"""Camera rays with Blender's conventions (BKE_camera_params_compute_viewplane, square pixels).

Camera space: the camera looks down its local -Z, local +Y is up, +X right. Pixel coordinates
(px, py) are continuous, in pixels, from the top-left corner of the image: x to the right, y down;
pixel (column i, row j) covers [i, i+1] x [j, j+1] and its centre is (i + 0.5, j + 0.5).

Frame (Blender's rule): the fitted side is the width for sensor_fit HORIZONTAL, the height for
VERTICAL, and the larger side for AUTO (width on ties). The fitted side spans ``sensor/lens`` at
unit distance (perspective; the sensor is sensor_height for VERTICAL, else sensor_width, so AUTO
always uses sensor_width) or ``ortho_scale`` metres (orthographic). shift_x/shift_y move the frame
by that many fitted-side lengths. Perspective rays start at the camera position; orthographic rays
start on the camera plane (local z = 0). The scale of ``matrix_world`` is ignored.

Samples per pixel: one sample is the pixel centre. N > 1 samples are stratified sub-pixel
positions (:func:`sample_positions`): a sqrt(N) x sqrt(N) jittered grid when N is a square,
else N-rooks (one sample in each of N columns and each of N rows of the pixel) placed on a
Fibonacci lattice, jittered. The jitter is a hash of the pixel and the sample, so a frame (and
any region of it) gets the same rays on every render.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .io import MAX_IMAGE_SIDE
from .model import Camera

MAX_SAMPLES = 4096     # samples per pixel


@dataclass(frozen=True)
class Shot:
    """What a frame renders: a camera of the scene by name (None: the first) at width x height
    pixels (None: the scene's render size), with ``samples`` camera rays per pixel."""
    camera: str | None = None
    width: int | None = None
    height: int | None = None
    samples: int = 1

    def __post_init__(self):
        n = self.samples
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= n <= MAX_SAMPLES:
            raise ValueError(f"samples per pixel must be an integer 1..{MAX_SAMPLES} (got {n!r})")

    def resolve(self, scene) -> tuple[Camera, int, int]:
        """(the scene Camera, width, height)."""
        w = int(scene.render.width if self.width is None else self.width)
        h = int(scene.render.height if self.height is None else self.height)
        return scene.camera(self.camera), w, h


def _frame(cam: Camera, width: int, height: int) -> tuple[float, float, float]:
    """(x0, y1, pix): left and top edges of the frame and the pixel size, in camera-space units
    at distance 1 (perspective) or metres on the camera plane (orthographic)."""
    if width < 1 or height < 1:
        raise ValueError(f"image size must be at least 1x1 (got {width}x{height})")
    fit = cam.sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if width >= height else "VERTICAL"
    viewfac = float(width if fit == "HORIZONTAL" else height)
    if cam.kind == "orthographic":
        size = cam.ortho_scale
    else:
        size = (cam.sensor_height if cam.sensor_fit == "VERTICAL" else cam.sensor_width) / cam.lens
    pix = size / viewfac
    x0 = (-0.5 * width + cam.shift_x * viewfac) * pix
    y1 = (0.5 * height + cam.shift_y * viewfac) * pix
    return x0, y1, pix


def _pose(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(R, t): camera-to-world rotation with unit columns, and the camera position."""
    m = np.asarray(cam.matrix_world, dtype=np.float64)
    r = m[:3, :3] / np.linalg.norm(m[:3, :3], axis=0)
    return r, m[:3, 3].copy()


def pixel_rays(cam: Camera, width: int, height: int, px: np.ndarray, py: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays through continuous pixel coordinates ``px``, ``py`` (any equal shapes,
    flattened). Returns origins (N, 3) and unit directions (N, 3), float64."""
    x0, y1, pix = _frame(cam, width, height)
    px = np.asarray(px, dtype=np.float64).ravel()
    py = np.asarray(py, dtype=np.float64).ravel()
    xc = x0 + px * pix
    yc = y1 - py * pix
    r, t = _pose(cam)
    n = px.size
    if cam.kind == "orthographic":
        local = np.stack([xc, yc, np.zeros(n)], axis=1)
        origins = local @ r.T + t
        dirs = np.broadcast_to(-r[:, 2], (n, 3)).copy()
    else:
        local = np.stack([xc, yc, -np.ones(n)], axis=1)
        d = local @ r.T
        dirs = d / np.linalg.norm(d, axis=1, keepdims=True)
        origins = np.broadcast_to(t, (n, 3)).copy()
    return origins, dirs


def check_image_size(width: int, height: int) -> None:
    """ValueError unless both sides are 1..MAX_IMAGE_SIDE pixels."""
    for name, v in (("width", width), ("height", height)):
        if not 1 <= int(v) <= MAX_IMAGE_SIDE:
            raise ValueError(f"image {name} must be 1..{MAX_IMAGE_SIDE} pixels (got {v})")


def camera_rays(cam: Camera, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """One ray through every pixel centre, row-major with the top row first: (H*W, 3) each.
    Sizes are 1..MAX_IMAGE_SIDE pixels, however they arrive (scene file, flag or API)."""
    check_image_size(width, height)
    py, px = np.mgrid[0:height, 0:width].astype(np.float64) + 0.5
    return pixel_rays(cam, width, height, px, py)


def _hash01(key: np.ndarray) -> np.ndarray:
    """Uniform numbers in [0, 1) from uint64 keys (splitmix64's finalizer), float64."""
    z = key + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) * 2.0 ** -53


def _lattice_step(n: int) -> int:
    """The integer nearest n / golden ratio that is coprime to n: (i * step) mod n is then a
    permutation of 0..n-1 spreading the rows of N-rooks samples like a Fibonacci lattice."""
    g = max(1, round(n / 1.618033988749895))
    while np.gcd(g, n) != 1:
        g += 1
    return g


def sample_positions(col, row, sample, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous pixel coordinates (px, py) of sample ``sample`` (0..samples-1) of pixel
    (column ``col``, row ``row``) of the frame (equal-shape integer arrays). One sample: the
    centre. A square N = k*k: cell (sample // k, sample % k) of a k x k grid, jittered in it.
    Else N-rooks on a Fibonacci lattice: column ``sample``, row (sample * step) mod N of an
    N x N grid, jittered in the cell. Every position lies inside its pixel."""
    col = np.asarray(col, np.int64)
    row = np.asarray(row, np.int64)
    if samples == 1:
        return col.astype(np.float64) + 0.5, row.astype(np.float64) + 0.5
    s = np.asarray(sample, np.int64)
    k = int(round(np.sqrt(samples)))
    if k * k == samples:
        cx, cy, cells = s % k, s // k, k
    else:
        cx, cy, cells = s, (s * _lattice_step(samples)) % samples, samples
    key = ((row * (1 << 15) + col) * MAX_SAMPLES + s).astype(np.uint64) * np.uint64(2)
    jx, jy = _hash01(key), _hash01(key + np.uint64(1))
    return col + (cx + jx) / cells, row + (cy + jy) / cells


def project_points(cam: Camera, width: int, height: int, points: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`pixel_rays`: world points (N, 3) -> (px, py, depth), each (N,).

    depth is the distance in front of the camera along its view axis (-local z), in metres.
    For a perspective camera, points with depth <= 0 get px = py = NaN.
    """
    x0, y1, pix = _frame(cam, width, height)
    r, t = _pose(cam)
    local = (np.asarray(points, dtype=np.float64).reshape(-1, 3) - t) @ r
    depth = -local[:, 2]
    if cam.kind == "orthographic":
        xc, yc = local[:, 0], local[:, 1]
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.where(depth > 0, 1.0 / depth, np.nan)
        xc, yc = local[:, 0] * inv, local[:, 1] * inv
    return (xc - x0) / pix, (y1 - yc) / pix, depth
