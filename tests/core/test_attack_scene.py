"""Hostile scene input: the reader refuses what the tracer cannot carry (weights, knots,
integers, images), reads only regular files within a size cap, checks sizes from headers before
decoding, refuses quickly; and the tracer stays finite for scenes at the limits it accepts."""

import json
import os
import re
import struct
import threading
import time
import tracemalloc
import zlib

import numpy as np
import pytest

from riray.cli import main
from riray.geometry.knots import (MAX_WEIGHT_RATIO, MIN_KNOT_DOMAIN, MIN_SPAN_FRACTION,
                                  check_surface, insert_knot)
from riray.geometry.nurbs import evaluate, normals
from riray.geometry.primitives import sphere
from riray.imageio import MAX_IMAGE_SIDE, ImageError, decode_png
from riray.scene import io as scene_io
from riray.scene.io import SceneError, load_scene, look_at_matrix, save_scene, scene_to_dict
from riray.scene.model import Camera, ObjectMaterial, Patch, Scene, SpecularObject, World
from riray.scene.samples import build
from riray.trace.textures import eval_world


@pytest.fixture(scope="module")
def sphere_dict():
    return scene_to_dict(build("glass_sphere"))


def _write(tmp_path, d, name="s.json"):
    p = tmp_path / name
    p.write_text(json.dumps(d))
    return p


def _refused(capsys, argv):
    """The CLI's one error line for ``argv`` (exit status 2, no traceback)."""
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def _rays(tmp_path, o, d):
    p = tmp_path / "rays.npy"
    np.save(p, np.concatenate([o, d], axis=1))
    return p


# --------------------------------------------------------------------------- weights and knots
@pytest.mark.parametrize("tiny", [1e-300, 5e-324])
def test_tiny_weight_refused_naming_it(tiny, sphere_dict, tmp_path, capsys):
    d = json.loads(json.dumps(sphere_dict))
    d["object"]["patches"][0]["weights"][4][2] = tiny
    with pytest.raises(SceneError, match=r"^object\.patches\[0\]\.weights\[4\]\[2\]: weight "
                                         r".* more than 1e\+06 times smaller"):
        load_scene(_write(tmp_path, d))
    rays = _rays(tmp_path, np.array([[0.0, -2.0, 0.9]]), np.array([[0.0, 1.0, 0.0]]))
    line = _refused(capsys, ["trace-rays", str(tmp_path / "s.json"), "--rays", str(rays),
                             "--out", str(tmp_path / "o.npz"), "--quiet", "--workers", "1"])
    assert "object.patches[0].weights[4][2]" in line
    assert not (tmp_path / "o.npz").exists()


def test_uniformly_tiny_weights_refused(sphere_dict, tmp_path):
    d = json.loads(json.dumps(sphere_dict))
    p = d["object"]["patches"][0]
    p["weights"] = (np.asarray(p["weights"]) * 1e-310).tolist()      # subnormal floats
    with pytest.raises(SceneError, match=r"^object\.patches\[0\]\.weights\[\d\]\[\d\]: weight "
                                         r".* is below 1e-12"):
        load_scene(_write(tmp_path, d))


def test_scaled_knots_refused(sphere_dict, tmp_path):
    d = json.loads(json.dumps(sphere_dict))
    p = d["object"]["patches"][0]
    p["knots_u"] = [k * 1e-300 for k in p["knots_u"]]
    with pytest.raises(SceneError, match=r"^object\.patches\[0\]\.knots_u: domain length .* is "
                                         r"below 1e-12"):
        load_scene(_write(tmp_path, d))


def test_tiny_knot_span_refused(sphere_dict, tmp_path):
    d = json.loads(json.dumps(sphere_dict))
    p = d["object"]["patches"][0]
    ku = p["knots_u"]                     # [0, 0, 0, .25, .25, .5, ...]: C0 double knots
    ku[4] = ku[3] + 1e-12
    with pytest.raises(SceneError, match=r"^object\.patches\[0\]\.knots_u\[4\]: span "
                                         r"\[0\.25, 0\.250000000001\] is shorter than 1e-09"):
        load_scene(_write(tmp_path, d))


def _extreme_sphere():
    """The unit sphere at the origin at every limit at once: weight ratio 0.9 MAX_WEIGHT_RATIO
    (each quarter arc reparametrized by w_i -> w_i c^i, an exact Moebius change that leaves
    the surface a sphere), knot domains 1.5 MIN_KNOT_DOMAIN away from 0, and in each direction
    one span 2 MIN_SPAN_FRACTION of the domain (knot insertion: the same surface)."""
    s = sphere((0.0, 0.0, 0.0), 1.0)
    c = np.sqrt(0.9 * MAX_WEIGHT_RATIO * s.weights.min() / s.weights.max())
    s.weights = s.weights * np.array([1, c, c * c, c, 1, c, c * c, c, 1])[:, None]
    length = 1.5 * MIN_KNOT_DOMAIN
    s.knots_u = 7 * length + s.knots_u * length
    s.knots_v = -3 * length + s.knots_v * length
    s = insert_knot(s, "u", s.knots_u[3] + 2 * MIN_SPAN_FRACTION * length, 1)
    s = insert_knot(s, "v", s.knots_v[3] - 2 * MIN_SPAN_FRACTION * length, 1)
    check_surface(s)
    assert s.weights.max() / s.weights.min() > 0.5 * MAX_WEIGHT_RATIO
    return s


def test_extreme_valid_surface_normals_are_the_spheres():
    s = _extreme_sphere()
    u0, u1, v0, v1 = s.domain
    eps = MIN_SPAN_FRACTION * (u1 - u0)
    uu = np.concatenate([np.linspace(u0, u1, 41), s.knots_u[3:6], s.knots_u[4:6] - eps])
    vv = np.concatenate([np.linspace(v0, v1, 41), s.knots_v[2:5], s.knots_v[3:5] + eps])
    u, v = (a.ravel() for a in np.meshgrid(uu, vv))
    (p,) = evaluate(s, u, v, derivatives=0)
    n = normals(s, u, v)                 # poles and the short spans included
    assert np.isfinite(n).all()
    np.testing.assert_allclose(np.linalg.norm(p, axis=1), 1.0, atol=1e-12)
    assert np.abs(np.abs(np.einsum("ij,ij->i", n, p)) - 1.0).max() < 1e-6


def test_extreme_valid_scene_traces_finite(tmp_path, capsys):
    scene = Scene(objects=[SpecularObject("ball", [Patch("s", 0, surface=_extreme_sphere())],
                                         ObjectMaterial(kind="glass", ior=1.5))])
    save_scene(scene, tmp_path / "x.json")          # validates
    rng = np.random.default_rng(5)
    tgt = rng.uniform(-1.0, 1.0, (600, 3))
    tgt[:100] = (0, 0, 1) + rng.normal(0, 1e-7, (100, 3))     # at the poles
    tgt[100:200] = (0, 0, -1) + rng.normal(0, 1e-7, (100, 3))
    org = rng.normal(0, 1, (600, 3))
    org = 3 * org / np.linalg.norm(org, axis=1)[:, None]
    d = (tgt - org) / np.linalg.norm(tgt - org, axis=1)[:, None]
    assert main(["trace-rays", str(tmp_path / "x.json"), "--rays",
                 str(_rays(tmp_path, org, d)), "--out", str(tmp_path / "o.npz"), "--quiet",
                 "--workers", "1"]) == 0
    out = np.load(tmp_path / "o.npz")
    hit = out["hit"]
    assert hit.sum() > 300
    for k in ("out_origin", "out_dir", "point", "normal", "refl_dir", "fresnel", "uv"):
        assert np.isfinite(out[k]).all(), k
    assert np.isfinite(out["t_first"][hit]).all()
    np.testing.assert_allclose(np.linalg.norm(out["point"][hit], axis=1), 1.0, atol=1e-9)
    radial = np.abs(np.einsum("ij,ij->i", out["normal"][hit], out["point"][hit]))
    assert np.abs(radial - 1.0).max() < 1e-6


# --------------------------------------------------------------------------- integers
def test_max_events_range(sphere_dict, tmp_path, capsys):
    d = json.loads(json.dumps(sphere_dict))
    d["render"]["max_events"] = 2 ** 63
    line = _refused(capsys, ["validate", str(_write(tmp_path, d))])
    assert re.search(r"render\.max_events: must be <= 1000 \(got 9223372036854775808\)", line)
    d["render"]["max_events"] = 1000
    assert load_scene(_write(tmp_path, d)).render.max_events == 1000


def test_degree_range(sphere_dict, tmp_path):
    d = json.loads(json.dumps(sphere_dict))
    d["object"]["patches"][0]["degree_u"] = 2 ** 70
    with pytest.raises(SceneError, match=r"^object\.patches\[0\]\.degree_u: must be <= 5"):
        load_scene(_write(tmp_path, d))


def test_hundred_thousand_digit_integer_named(sphere_dict, tmp_path, capsys):
    d = json.loads(json.dumps(sphere_dict))
    d["object"]["patches"][0]["class_id"] = 987654321
    text = json.dumps(d)
    assert text.count("987654321") == 1
    p = tmp_path / "s.json"
    p.write_text(text.replace("987654321", "-" + "9" * 100000))
    with pytest.raises(SceneError, match=r"s\.json: object\.patches\[0\]\.class_id: integer "
                                         r"of 100000 digits is out of range"):
        load_scene(p)
    assert "class_id" in _refused(capsys, ["validate", str(p)])


# --------------------------------------------------------------------------- the JSON reader
def _many_keys(n, duplicate):
    keys = ", ".join(f'"k{i}": {i}' for i in range(n))
    return '{"format": "riray-scene", "version": 1, "object": {' + keys + \
        (', "k0": 1' if duplicate else "") + "}}"


@pytest.mark.parametrize("duplicate", [True, False])
def test_forty_thousand_keys_refused_fast(tmp_path, duplicate):
    p = tmp_path / "keys.json"
    p.write_text(_many_keys(40000, duplicate))
    t0 = time.perf_counter()
    with pytest.raises(SceneError, match="duplicate key 'k0'" if duplicate else
                       r"^object: unknown key 'k0'"):
        load_scene(p)
    assert time.perf_counter() - t0 < 3.0        # quadratic: ~10 s


def test_device_is_not_a_scene():
    t0 = time.perf_counter()
    with pytest.raises(SceneError, match="/dev/zero: not a regular file"):
        load_scene("/dev/zero")
    assert time.perf_counter() - t0 < 5.0


def _no_hang(fn):
    """fn()'s exception (it must raise), or fail if it blocks (a FIFO without a writer)."""
    box = {}

    def run():
        try:
            fn()
        except Exception as e:        # noqa: BLE001 (handed back to the test)
            box["e"] = e
    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(20.0)
    assert not t.is_alive(), "blocked reading a FIFO"
    return box.get("e")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_fifo_scene_and_image_refused(tmp_path, sphere_dict):
    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)
    e = _no_hang(lambda: load_scene(fifo))
    assert isinstance(e, SceneError) and "not a regular file" in str(e)
    os.mkfifo(tmp_path / "sky.npy")
    d = json.loads(json.dumps(sphere_dict))
    d["world"] = {"kind": "image", "path": "sky.npy"}
    e = _no_hang(lambda: load_scene(_write(tmp_path, d)))
    assert isinstance(e, SceneError) and re.match(r"world\.path: .*sky\.npy: not a regular "
                                                  r"file", str(e)), e


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
@pytest.mark.parametrize("cmd", [["info", "{fifo}"],
                                 ["trace-rays", "glass_sphere", "--rays", "{fifo}", "--out",
                                  "{tmp}/o.npz"],
                                 ["render", "glass_sphere", "--tree", "{fifo}", "--out",
                                  "{tmp}/r", "--quiet"]])
def test_fifo_tree_and_rays_refused(tmp_path, capsys, cmd):
    """A FIFO named as the RI-Tree or the rays file is refused at once, in one line."""
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    argv = [a.format(fifo=fifo, tmp=tmp_path) for a in cmd]
    box = {}
    t = threading.Thread(target=lambda: box.update(rc=main(argv)), daemon=True)
    t.start()
    t.join(20.0)
    assert not t.is_alive(), "blocked reading a FIFO"
    err = capsys.readouterr().err.strip().splitlines()
    assert box["rc"] == 2 and err[-1].endswith("pipe: not a regular file"), err


def test_scene_size_cap(tmp_path, sphere_dict, monkeypatch):
    p = _write(tmp_path, sphere_dict)
    monkeypatch.setattr(scene_io, "MAX_SCENE_BYTES", 1000)
    with pytest.raises(SceneError, match=r"s\.json: \d+ bytes, more than the 1000"):
        load_scene(p)


# --------------------------------------------------------------------------- images
def _world_npy(tmp_path, sphere_dict, arr):
    np.save(tmp_path / "sky.npy", arr)
    d = json.loads(json.dumps(sphere_dict))
    d["world"] = {"kind": "image", "path": "sky.npy"}
    return _write(tmp_path, d)


@pytest.mark.parametrize("shape", [(0, 0, 3), (0, 5), (4, 0, 3)])
def test_empty_world_image_refused(tmp_path, sphere_dict, shape):
    p = _world_npy(tmp_path, sphere_dict, np.zeros(shape, np.float32))
    with pytest.raises(SceneError, match=r"^world\.path: .*sky\.npy: \d+ x \d+ pixels: an "
                                         r"image needs 1\.\.16384 on a side"):
        load_scene(p)


def test_empty_world_image_is_a_value_error_at_evaluation():
    w = World(kind="image", path="sky.npy", image=np.zeros((0, 0, 3)))
    with pytest.raises(ValueError, match="no pixels"):
        eval_world(w, np.array([[0.0, 0.0, 1.0]]))


@pytest.mark.parametrize("bad", [-0.25, np.nan, np.inf])
def test_world_image_values_refused(tmp_path, sphere_dict, bad):
    img = np.full((4, 8, 3), 0.5)
    img[2, 5, 1] = bad
    p = _world_npy(tmp_path, sphere_dict, img)
    want = r"negative values \(-0\.25 at row 2 column 5 channel 1\)" if bad == -0.25 else \
        "NaN/inf"
    with pytest.raises(SceneError, match=r"^world\.path: image .*sky\.npy .*" + want):
        load_scene(p)


def _chunk(kind, data):
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png(width, height, raw):
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(raw, 9))
            + _chunk(b"IEND", b""))


def test_png_size_checked_from_ihdr_before_decoding():
    with pytest.raises(ImageError, match=f"20000 x 3 pixels: larger than {MAX_IMAGE_SIDE}"):
        decode_png(_png(20000, 3, bytes(10)))


def test_png_inflates_no_further_than_its_ihdr():
    data = _png(1, 1, bytes(64 << 20))        # 1 x 1 grey, 64 MiB of zeros behind it
    tracemalloc.start()
    try:
        samples, _ = decode_png(data)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert samples.shape == (1, 1, 1)
    assert peak < 8 << 20


def test_png_world_image_too_large_refused_cheaply(tmp_path, sphere_dict):
    (tmp_path / "sky.png").write_bytes(_png(20000, 20000, bytes(1000)))
    d = json.loads(json.dumps(sphere_dict))
    d["world"] = {"kind": "image", "path": "sky.png"}
    with pytest.raises(SceneError, match=r"^world\.path: .*sky\.png: 20000 x 20000 pixels: "
                                         "larger than 16384"):
        load_scene(_write(tmp_path, d))


# --------------------------------------------------------------------------- validate
def test_validate_refuses_camera_inside_the_object(tmp_path, capsys):
    scene = build("glass_sphere")
    pts = scene.object.patches[0].surface.points.reshape(-1, 3)
    c = (pts.min(axis=0) + pts.max(axis=0)) / 2
    scene.cameras.append(Camera(name="inside", matrix_world=look_at_matrix(c + (0.02, 0, 0),
                                                                            c + (0, 1, 0))))
    save_scene(scene, tmp_path / "s.json")
    line = _refused(capsys, ["validate", str(tmp_path / "s.json")])
    assert "camera 'inside' is inside the object 'glass_sphere'" in line
