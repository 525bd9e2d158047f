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
"""

from __future__ import annotations

import numpy as np

from .io import MAX_IMAGE_SIDE
from .model import Camera


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


def camera_rays(cam: Camera, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """One ray through every pixel centre, row-major with the top row first: (H*W, 3) each.
    Sizes are 1..MAX_IMAGE_SIDE pixels, however they arrive (scene file, flag or API)."""
    for name, v in (("width", width), ("height", height)):
        if not 1 <= int(v) <= MAX_IMAGE_SIDE:
            raise ValueError(f"image {name} must be 1..{MAX_IMAGE_SIDE} pixels (got {v})")
    py, px = np.mgrid[0:height, 0:width].astype(np.float64) + 0.5
    return pixel_rays(cam, width, height, px, py)


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
