"""Samples per pixel and the film: stratified sub-pixel positions, Cycles' Blackman-Harris pixel
filter, images developed share by share; one sample is today's one ray through each pixel
centre, unfiltered, bit for bit."""

import numpy as np
import pytest

from riray.cli import main
from riray.render.exact import render_exact
from riray.render.film import FILTER_WIDTH_PX, Film, blackman_harris
from riray.render.frame import ExactAnswerer, shade_share
from riray.render.interpolated import psnr
from riray.scene.camera import MAX_SAMPLES, Shot, camera_rays, sample_positions
from riray.scene.samples import build
from riray.trace.scene_tracer import SceneTracer


trapezoid = getattr(np, "trapezoid", None) or np.trapz     # numpy 2 / 1.26


@pytest.fixture(scope="module")
def sphere():
    return SceneTracer(build("glass_sphere"))


def test_filter_is_blackman_harris_and_integrates_to_one():
    x = np.linspace(-0.75, 0.75, 200001)
    w = blackman_harris(x)
    assert trapezoid(w, x) == pytest.approx(1.0, abs=1e-9)
    t = 2 * np.pi * (x / 1.5 + 0.5)                      # Cycles' filter_func_blackman_harris
    bh = 0.35875 - 0.48829 * np.cos(t) + 0.14128 * np.cos(2 * t) - 0.01168 * np.cos(3 * t)
    assert np.allclose(w * 0.35875 * 1.5, bh, rtol=0, atol=1e-15)
    assert FILTER_WIDTH_PX == 1.5 and blackman_harris(0.0) == w.max()
    assert np.all(blackman_harris(np.array([-0.76, 0.751, 3.0])) == 0.0)
    g = np.linspace(-0.75, 0.75, 1501)                    # the separable 2-D filter
    w2 = blackman_harris(g)[:, None] * blackman_harris(g)[None, :]
    assert trapezoid(trapezoid(w2, g), g) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("bad", [0, -1, MAX_SAMPLES + 1, 2.5, True, "4"])
def test_samples_validated(bad):
    with pytest.raises(ValueError, match=r"samples per pixel must be an integer 1\.\.4096"):
        Shot(samples=bad)
    assert Shot(samples=MAX_SAMPLES).samples == MAX_SAMPLES and Shot().samples == 1


def _positions(n, cols=7, rows=5):
    col, row, s = np.meshgrid(np.arange(cols) + 100, np.arange(rows) + 40, np.arange(n),
                              indexing="ij")
    px, py = sample_positions(col, row, s, n)
    return px - col, py - row          # offsets inside each pixel, (cols, rows, n)


@pytest.mark.parametrize("n", [4, 16, 64])
def test_square_counts_cover_each_grid_cell_once(n):
    k = int(np.sqrt(n))
    fx, fy = _positions(n)
    assert np.all((fx >= 0) & (fx < 1) & (fy >= 0) & (fy < 1))
    cell = np.floor(fx * k) * k + np.floor(fy * k)
    assert np.all(np.sort(cell, axis=-1) == np.arange(n))          # every k x k cell once


@pytest.mark.parametrize("n", [2, 3, 6, 8, 12])
def test_other_counts_are_n_rooks(n):
    fx, fy = _positions(n)
    assert np.all((fx >= 0) & (fx < 1) & (fy >= 0) & (fy < 1))
    assert np.all(np.sort(np.floor(fx * n), axis=-1) == np.arange(n))    # each column once
    assert np.all(np.sort(np.floor(fy * n), axis=-1) == np.arange(n))    # each row once


def test_positions_are_reproducible_and_jittered_per_pixel():
    a, b = _positions(16), _positions(16)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert len(np.unique(np.round(a[0][:, :, 5], 12))) == a[0][:, :, 5].size   # differ by pixel
    assert np.array_equal(sample_positions(np.array([3]), np.array([2]), np.array([0]), 1)[0],
                          [3.5])


def test_one_sample_is_the_pixel_centre_ray(sphere):
    cam = sphere.scene.camera("close")
    o, d = camera_rays(cam, 23, 17)
    film = Film(cam, 23, 17)
    for a, b in [(0, 23 * 17), (5, 90), (90, 391)]:
        fo, fd = film.rays(a, b)
        assert np.array_equal(fo, o[a:b]) and np.array_equal(fd, d[a:b])


def test_window_rays_are_the_frames_rays(sphere):
    """A region's rays are the same pixels' rays of the whole frame (border renders agree)."""
    cam = sphere.scene.camera("close")
    full, part = Film(cam, 20, 10, 9), Film(cam, 20, 10, 9, window=(4, 3, 5, 2))
    po, pd = part.rays(0, part.n_rays)
    rows = [(3 + r) * 20 + 4 for r in range(2)]
    fd = np.concatenate([full.rays(9 * p, 9 * (p + 5))[1] for p in rows])
    assert np.array_equal(pd, fd)


def _develop(film, values, share):
    """Develop per-ray ``values(px, py)`` (n, 3) through the film in shares of ``share``."""
    parts = []
    c0, r0, w, _ = film.window
    for a in range(0, film.n_rays, share):
        b = min(a + share, film.n_rays)
        p, s = np.arange(a, b) // film.samples, np.arange(a, b) % film.samples
        px, py = sample_positions(c0 + p % w, r0 + p // w, s, film.samples)
        parts.append(film.develop(a, b, {"c": values(px, py)}, {"one": np.ones(b - a)}))
    return film.join(parts)


@pytest.mark.parametrize("n", [1, 4, 5])
def test_constant_colour_stays_constant(sphere, n):
    film = Film(sphere.scene.camera("close"), 13, 9, n)
    c = np.array([0.3, 0.5, 0.7])
    dev = _develop(film, lambda px, py: np.tile(c, (len(px), 1)), share=37)
    assert np.abs(dev.images["c"] - c).max() < 1e-15
    assert np.all(dev.box["one"] == n) and np.all(dev.fraction("one") == (n == 1 or 1.0))


def _filtered_coverage(cx, cy, inside):
    """The Blackman-Harris-filtered coverage of the pixel centred (cx, cy), by quadrature."""
    g = np.linspace(-0.75, 0.75, 601)
    x, y = np.meshgrid(cx + g, cy + g, indexing="ij")
    wt = blackman_harris(g)[:, None] * blackman_harris(g)[None, :]
    return float(np.sum(wt * inside(x, y)) / np.sum(wt))


def test_edge_renders_to_its_filtered_coverage(sphere):
    """A slanted half-plane edge at 64 samples per pixel: every pixel is the filter-weighted
    coverage of the half-plane (what Cycles converges to), within stratified sampling noise;
    one sample gives each pixel the bare in/out of its centre."""
    def inside(x, y):
        return (0.6 * x - 0.8 * y > 0.6 * 6.3 - 0.8 * 5.2).astype(float)
    film = Film(sphere.scene.camera("close"), 12, 10, 64)
    dev = _develop(film, lambda px, py: np.repeat(inside(px, py)[:, None], 3, 1), share=1000)
    want = np.array([[_filtered_coverage(i + 0.5, j + 0.5, inside) for i in range(1, 11)]
                     for j in range(1, 9)])           # away from the frame's border
    got = dev.images["c"][1:9, 1:11, 0]
    assert np.abs(got - want).max() < 0.06 and np.sqrt(np.mean((got - want) ** 2)) < 0.012
    assert 0.05 < got[np.abs(want - 0.5) < 0.45].min()          # a soft edge, not a step
    one = _develop(Film(film.cam, 12, 10, 1), lambda px, py: np.repeat(
        inside(px, py)[:, None], 3, 1), share=7).images["c"][..., 0]
    assert set(np.unique(one)) == {0.0, 1.0}


def test_one_sample_render_is_todays_image(sphere):
    """render_exact at one sample: one ray through each pixel centre, no filter - the colours of
    shade_share over camera_rays, bit for bit; the object mask stays bool."""
    cam = sphere.scene.camera("close")
    res = render_exact(sphere, Shot("close", 14, 11), workers=2)
    want = shade_share(sphere, *camera_rays(cam, 14, 11), ExactAnswerer(sphere))
    assert np.array_equal(res.image, want.color.reshape(11, 14, 3))
    assert res.masks["object"].dtype == bool and res.masks["object"].sum() == len(want.hit)


def test_more_samples_converge(sphere):
    """Against a 64-sample render, 16 samples are much closer than one; the object mask is the
    fraction of each pixel's samples that hit it and the counts are rays."""
    shot = dict(camera="close", width=16, height=16)
    ref = render_exact(sphere, Shot(**shot, samples=64), workers=2)
    one = render_exact(sphere, Shot(**shot), workers=2)
    many = render_exact(sphere, Shot(**shot, samples=16), workers=2)
    assert psnr(many.image, ref.image) > psnr(one.image, ref.image) + 6
    cover = many.masks["object"]
    assert cover.dtype == np.float64 and 0 < np.sum((cover > 0) & (cover < 1))
    assert cover.sum() * 16 == many.stats["summary"]["object_pixels"]
    assert many.stats["counts"]["camera_rays"] == 16 * 16 * 16
    assert many.stats["summary"]["samples"] == 16


def test_cli_samples(tmp_path, capsys):
    out = tmp_path / "r"
    assert main(["render", "glass_sphere", "--camera", "close", "--width", "6", "--height", "5",
                 "--samples", "0", "--out", str(out), "--quiet"]) == 2
    assert "samples per pixel must be an integer 1..4096 (got 0)" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    assert main(["render", "glass_sphere", "--camera", "close", "--width", "6", "--height", "5",
                 "--samples", "4", "--out", str(out), "--quiet", "--workers", "1"]) == 0
    import json
    summary = json.loads((tmp_path / "r.json").read_text())["summary"]
    assert summary["samples"] == 4 and np.load(tmp_path / "r.npy").shape == (5, 6, 3)
