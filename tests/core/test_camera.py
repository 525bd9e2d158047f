"""Camera rays against Blender's frame rules, computed by hand (tan of the half-angles)."""

import numpy as np
import pytest

from riray.scene.camera import camera_rays, pixel_rays, project_points
from riray.scene.io import look_at_matrix
from riray.scene.model import Camera


def cam(**kw):
    return Camera(name="c", matrix_world=kw.pop("matrix_world", np.eye(4)), **kw)


def tangents(c, w, h, px, py):
    """(x/-z, y/-z) of camera-space directions through pixel coordinates (identity pose)."""
    _, d = pixel_rays(c, w, h, np.atleast_1d(px), np.atleast_1d(py))
    return d[:, 0] / -d[:, 2], d[:, 1] / -d[:, 2]


def test_centre_ray_is_minus_z_and_layout_is_row_major_top_first():
    m = look_at_matrix((1.0, -4.0, 2.0), (0.0, 0.0, 1.0))
    c = cam(matrix_world=m)
    o, d = camera_rays(c, 5, 3)
    assert o.shape == d.shape == (15, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1, atol=1e-15)
    np.testing.assert_allclose(o, np.broadcast_to(m[:3, 3], (15, 3)))
    np.testing.assert_allclose(d[7], -m[:3, 2], atol=1e-15)            # centre pixel (row 1, col 2)
    local = d @ m[:3, :3]
    assert local[0, 0] < 0 < local[0, 1]                                 # first ray: top-left
    assert local[4, 0] > 0 and local[-1, 1] < 0                          # end of row 0 / last row
    assert np.all(np.diff(local[:5, 0]) > 0) and np.all(np.diff(local[::5, 1]) < 0)


@pytest.mark.parametrize("w,h,fit,sw,sh,tx,ty", [
    (300, 200, "AUTO", 36, 24, 18 / 50, 12 / 50),          # landscape: width gets sensor_width
    (200, 300, "AUTO", 36, 24, 12 / 50, 18 / 50),          # portrait: height gets sensor_width
    (200, 200, "AUTO", 36, 24, 18 / 50, 18 / 50),
    (200, 300, "HORIZONTAL", 36, 24, 18 / 50, 27 / 50),
    (300, 200, "VERTICAL", 36, 30, 22.5 / 50, 15 / 50),    # sensor_height on the height
    (300, 200, "HORIZONTAL", 20, 99, 10 / 50, 10 / 75),
])
def test_frame_edges_match_lens_and_sensor(w, h, fit, sw, sh, tx, ty):
    c = cam(lens=50.0, sensor_width=sw, sensor_height=sh, sensor_fit=fit)
    x, _ = tangents(c, w, h, [0.0, w], [h / 2, h / 2])
    np.testing.assert_allclose(x, [-tx, tx], rtol=1e-13)
    _, y = tangents(c, w, h, [w / 2, w / 2], [0.0, h])
    np.testing.assert_allclose(y, [ty, -ty], rtol=1e-13)
    # pixel centres: the first column centre sits half a pixel inside the edge
    x0, _ = tangents(c, w, h, 0.5, h / 2)
    np.testing.assert_allclose(x0, -tx + tx / w, rtol=1e-13)


def test_shift_is_in_units_of_the_fitted_side():
    for w, h in ((300, 200), (200, 300)):
        c = cam(lens=50.0, sensor_width=36.0, shift_x=0.1, shift_y=-0.25)
        x, y = tangents(c, w, h, w / 2, h / 2)
        np.testing.assert_allclose([x[0], y[0]], [0.1 * 36 / 50, -0.25 * 36 / 50], rtol=1e-13)
        xl, _ = tangents(c, w, h, 0.0, h / 2)                          # frame size unchanged
        np.testing.assert_allclose(x - xl, 0.5 * w * (36 / 50) / max(w, h), rtol=1e-13)


def test_orthographic_rays_start_on_camera_plane():
    m = look_at_matrix((0.0, -10.0, 3.0), (0.0, 0.0, 3.0))
    c = cam(kind="orthographic", ortho_scale=4.0, shift_x=0.25, matrix_world=m)
    o, d = pixel_rays(c, 300, 200, np.array([0.0, 300.0, 150.0]), np.array([100.0, 100.0, 0.0]))
    np.testing.assert_allclose(d, np.broadcast_to([0.0, 1.0, 0.0], (3, 3)), atol=1e-15)
    local = (o - m[:3, 3]) @ m[:3, :3]
    np.testing.assert_allclose(local, [[-2 + 1, 0, 0], [2 + 1, 0, 0], [1, 4 / 3, 0]], atol=1e-14)
    # portrait AUTO: ortho_scale spans the height
    o, _ = pixel_rays(c, 200, 300, np.array([100.0]), np.array([0.0]))
    np.testing.assert_allclose(((o - m[:3, 3]) @ m[:3, :3])[0, 1], 2.0, atol=1e-14)


@pytest.mark.parametrize("kind", ["perspective", "orthographic"])
def test_project_inverts_pixel_rays(kind):
    rng = np.random.default_rng(3)
    m = look_at_matrix((2.0, -3.0, 1.5), (0.0, 0.5, 0.2), up=(0.1, 0.0, 1.0))
    c = cam(kind=kind, lens=35.0, sensor_fit="VERTICAL", shift_x=-0.05, shift_y=0.1,
            ortho_scale=3.0, matrix_world=m)
    px, py = rng.uniform(-10, 330, 50), rng.uniform(-10, 250, 50)
    o, d = pixel_rays(c, 320, 240, px, py)
    t = rng.uniform(0.5, 20, 50)
    qx, qy, depth = project_points(c, 320, 240, o + t[:, None] * d)
    np.testing.assert_allclose(qx, px, atol=1e-9)
    np.testing.assert_allclose(qy, py, atol=1e-9)
    np.testing.assert_allclose(depth, t * -(d @ m[:3, 2]), rtol=1e-12)


def test_points_behind_perspective_camera_project_to_nan():
    px, py, depth = project_points(cam(), 10, 10, np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]))
    assert np.isnan(px[0]) and np.isnan(py[0]) and depth[0] == -1.0
    assert px[1] == 5.0 and py[1] == 5.0 and depth[1] == 1.0
