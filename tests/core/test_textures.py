"""Texture and world evaluation against hand-computed values."""

import math

import numpy as np
import pytest

from riray.scene.model import Texture, World
from riray.trace.textures import eval_texture, eval_world

A, B = (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)


def test_constant():
    out = eval_texture(Texture(color=(0.1, 0.2, 0.3)), np.zeros((4, 3)), None)
    assert out.shape == (4, 3) and np.all(out == [0.1, 0.2, 0.3])


def test_checker_3d_world_and_2d_uv():
    t = Texture(kind="checker", color=A, color2=B, scale=2.0)
    p = np.array([[0.1, 0.1, 0.1], [0.6, 0.1, 0.1], [0.6, 0.6, 0.1], [0.6, 0.6, 0.6],
                  [-0.1, 0.1, 0.1], [0.3, 0.3, -1e-13]])   # last: a floor at z = 0 hit just below
    np.testing.assert_array_equal(eval_texture(t, p, None), [A, B, A, B, B, A])
    t.coords = "uv"
    uv = np.array([[0.1, 0.1], [0.6, 0.1], [0.6, 0.6], [-0.3, 0.2]])
    np.testing.assert_array_equal(eval_texture(t, np.zeros((4, 3)), uv), [A, B, A, B])
    with pytest.raises(ValueError, match="needs mesh UVs"):
        eval_texture(t, np.zeros((1, 3)), None)


def test_stripes_along_axis():
    t = Texture(kind="stripes", color=A, color2=B, scale=4.0, axis=0)     # bands 0.25 wide
    p = np.array([[0.1, 5.0, 5.0], [0.3, 0.0, 0.0], [0.55, 0.0, 0.0], [-0.1, 0.0, 0.0]])
    np.testing.assert_array_equal(eval_texture(t, p, None), [A, B, A, B])


def test_gradient_clamped():
    t = Texture(kind="gradient", color=(0.0, 0.0, 0.0), color2=(1.0, 2.0, 4.0), axis=2,
                start=1.0, end=3.0)
    p = np.array([[0, 0, 0.0], [0, 0, 1.5], [0, 0, 3.0], [0, 0, 9.0]])
    np.testing.assert_allclose(eval_texture(t, p, None),
                               [[0, 0, 0], [0.25, 0.5, 1.0], [1, 2, 4], [1, 2, 4]])
    t.coords, t.axis = "uv", 1
    np.testing.assert_allclose(eval_texture(t, np.zeros((1, 3)), np.array([[7.0, 2.0]])),
                               [[0.5, 1.0, 2.0]])


def test_image_bilinear_v_up_repeat():
    img = np.zeros((2, 4, 3))
    img[0, :, 0] = [0, 1, 2, 3]          # top row: red = column index
    img[1, :, 0] = [10, 11, 12, 13]      # bottom row
    img[:, :, 1] = 5.0
    t = Texture(kind="image", coords="uv", image=img)
    uv = np.array([[0.125, 0.25],        # centre of bottom-left pixel
                   [0.875, 0.75],        # centre of top-right pixel
                   [0.25, 0.5],          # between columns 0/1 and rows: (0+1+10+11)/4
                   [1.125, -0.75],       # repeats to (0.125, 0.25)
                   [0.0, 0.25]])         # wraps horizontally: (10 + 13) / 2
    out = eval_texture(t, np.zeros((5, 3)), uv)
    np.testing.assert_allclose(out[:, 0], [10, 3, 5.5, 10, 11.5], atol=1e-12)
    np.testing.assert_allclose(out[:, 1], 5.0)
    t.scale = 2.0
    np.testing.assert_allclose(eval_texture(t, np.zeros((1, 3)), np.array([[0.0625, 0.125]]))[:, 0], [10])


def test_world_color_and_gradient():
    w = World(kind="color", color=(0.1, 0.2, 0.3), strength=2.0)
    np.testing.assert_allclose(eval_world(w, np.array([[0, 0, 1.0]])), [[0.2, 0.4, 0.6]])
    w = World(kind="gradient", color=(1.0, 1.0, 1.0), zenith=(0.0, 0.0, 1.0), strength=1.0)
    s = math.sqrt(0.75)
    d = np.array([[0, 0, 1.0], [s, 0, 0.5], [1.0, 0, 0], [0, 0, -1.0]])
    np.testing.assert_allclose(eval_world(w, d),
                               [[0, 0, 1], [0.5, 0.5, 1], [1, 1, 1], [1, 1, 1]], atol=1e-15)


def test_world_equirect_blender_mapping():
    h, w = 4, 8
    img = np.zeros((h, w, 3))
    img[:, :, 0] = np.arange(w)[None, :]        # red = column
    img[:, :, 1] = np.arange(h)[:, None]        # green = row (0 = top)
    world = World(kind="image", image=img, strength=1.0)
    d = np.array([[1.0, 0, 0],    # +X -> u = 0.5 (between columns 3 and 4), horizon v = 0.5
                  [0, 1.0, 0],    # +Y -> u = 0.25 (column centre 1.5)
                  [0, -1.0, 0],   # -Y -> u = 0.75
                  [0, 0, 1.0],    # zenith -> v = 1: clamped to the top row
                  [0, 0, -1.0]])  # nadir -> bottom row
    out = eval_world(world, d)
    np.testing.assert_allclose(out[:3, 0], [3.5, 1.5, 5.5], atol=1e-12)
    np.testing.assert_allclose(out[:3, 1], 1.5, atol=1e-12)
    np.testing.assert_allclose(out[3:, 1], [0.0, 3.0], atol=1e-12)
    # direction at 45 deg elevation towards -X: u = 0 (wraps: columns 7 and 0), v = 0.75
    q = eval_world(world, np.array([[-1.0, -1e-12, 1.0]]) / math.sqrt(2))
    np.testing.assert_allclose(q[0, :2], [3.5, 0.5], atol=1e-9)
