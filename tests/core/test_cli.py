"""The `riray` command line (docs/cli.md): every sub-command answers --help, render writes the
documented files, trace-rays writes the documented arrays, bad input gives exit 2 and one line."""

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from riray.cli import build_parser, main
from riray.imageio import read_png
from riray.scene.io import load_scene, save_scene
from riray.scene.samples import GLASS_SPHERE_RADIUS, build

SUMMARY_KEYS = {"scene", "camera", "width", "height", "mode", "rays_traced", "object_pixels",
                "object_only_cpu_s", "total_cpu_s", "wall_s", "build_s", "object_rays_per_cpu_s",
                "peak_rss_mib", "shares"}
COUNT_KEYS = {"camera_rays", "object_candidates", "object_hits", "events", "object_cpu_s",
              "object_wall_s", "total_cpu_s", "total_wall_s", "output_rays", "null_rays", "pairs",
              "newton_iters", "fallback_pairs"}
# name -> (dtype kind, trailing shape) of the trace-rays output arrays (docs/cli.md)
TRACE_ARRAYS = {"hit": ("b", ()), "null": ("b", ()), "out_origin": ("f", (3,)),
                "out_dir": ("f", (3,)), "t_first": ("f", ()), "point": ("f", (3,)),
                "normal": ("f", (3,)), "patch": ("i", ()), "cls": ("i", ()), "events": ("i", ()),
                "refl_dir": ("f", (3,)), "fresnel": ("f", ()), "tree": ("u", ()),
                "uv": ("f", (2,))}


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A small glass sphere scene (24 x 24) saved with save_scene, and a max_events = 1 copy
    (every ray that enters the sphere is still hitting it after one event: null)."""
    d = tmp_path_factory.mktemp("cli")
    scene = build("glass_sphere")
    scene.render.width = scene.render.height = 24
    save_scene(scene, d / "sphere.json")
    scene.render.max_events = 1
    save_scene(scene, d / "sphere_null.json")
    return d


def _sphere_centre():
    obj = build("glass_sphere").object.patches[0].surface.points.reshape(-1, 3)
    return (obj.min(axis=0) + obj.max(axis=0)) / 2


def _one_line_error(err: str, cmd: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"riray {cmd}: error: "), err
    assert "Traceback" not in err


def _subcommands():
    ap = build_parser()
    sub = next(a for a in ap._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices


def test_help_of_every_subcommand_names_its_options(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    top = capsys.readouterr().out
    subs = _subcommands()
    assert {"render", "trace-rays", "validate", "demo", "bench-exact"} <= set(subs)
    for name, parser in subs.items():
        assert name in top
        with pytest.raises(SystemExit) as e:
            main([name, "--help"])
        assert e.value.code == 0, name
        out = capsys.readouterr().out
        for action in parser._actions:
            for opt in action.option_strings:
                if opt.startswith("--"):
                    assert opt in out, (name, opt)


def test_console_script_entry_point(files):
    exe = Path(sys.executable).parent / "riray"
    assert exe.exists(), "the console script is not installed next to the interpreter"
    r = subprocess.run([str(exe), "validate", str(files / "sphere.json")], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "ok" in r.stdout
    r = subprocess.run([str(exe), "validate", str(files / "missing.json")], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2
    _one_line_error(r.stderr, "validate")


def test_render_writes_png_npy_json(files, tmp_path, capsys):
    stem = tmp_path / "out" / "img"
    rc = main(["render", str(files / "sphere.json"), "--out", str(stem) + ".png", "--camera",
               "close", "--width", "32", "--height", "24", "--workers", "1", "--quiet"])
    assert rc == 0
    printed = json.loads(capsys.readouterr().out)
    assert len(printed["written"]) == 3
    img = np.load(stem.with_suffix(".npy"))
    assert img.shape == (24, 32, 3) and np.isfinite(img).all()
    assert read_png(stem.with_suffix(".png")).shape[:2] == (24, 32)
    stats = json.loads(stem.with_suffix(".json").read_text())
    assert SUMMARY_KEYS <= set(stats["summary"])
    assert COUNT_KEYS <= set(stats["counts"])
    s = stats["summary"]
    assert (s["width"], s["height"], s["camera"], s["mode"]) == (32, 24, "close", "exact")
    assert 0 < s["object_pixels"] <= s["rays_traced"] <= 32 * 24


def test_render_sample_name_and_defaults(tmp_path, capsys):
    assert main(["render", "vase_mirror", "--out", str(tmp_path / "v"), "--width", "16",
                 "--height", "16", "--workers", "2", "--quiet"]) == 0
    assert np.isfinite(np.load(tmp_path / "v.npy")).all()
    capsys.readouterr()


def test_render_peak_memory_is_its_own(files, tmp_path):
    """riray render started by a process holding much more memory (as Blender would) reports
    its own peak RSS, not its parent's: the parent's 600 MiB stay out of the child's figure."""
    held = np.ones(600 * 2**20 // 8)          # touched: resident in this process
    res = subprocess.run([sys.executable, "-m", "riray.cli", "render", str(files / "sphere.json"),
                          "--out", str(tmp_path / "img"), "--workers", "1", "--quiet"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    peak = json.loads(res.stdout)["peak_rss_mib"]
    assert 0 < peak < held.nbytes / 2**20 / 2, peak


def _crafted_rays():
    c = _sphere_centre()
    r = GLASS_SPHERE_RADIUS
    return np.array([
        [*(c + (0, -1.0, 0)), 0, 3.0, 0],                 # through the centre, non-unit dir
        [*(c + (0.3 * r, -1.0, 0.2 * r)), 0, 1, 0],       # off-centre hit
        [*(c + (0, -1.0, 0)), 0, -1, 0],                  # pointing away: miss
        [*(c + (2 * r, -1.0, 0)), 0, 0.5, 0],             # passes beside: miss
        [*(c + (0, 0, -0.5)), 0.01, 0.0, 1.0],            # from below, nearly along z
    ])


def test_trace_rays_arrays(files, tmp_path, capsys):
    rays = _crafted_rays()
    np.save(tmp_path / "rays.npy", rays)
    assert main(["trace-rays", str(files / "sphere.json"), "--rays", str(tmp_path / "rays.npy"),
                 "--out", str(tmp_path / "out"), "--workers", "1", "--quiet"]) == 0
    assert "5 rays" in capsys.readouterr().out
    z = np.load(tmp_path / "out.npz")           # the suffix is added
    assert set(z.files) == set(TRACE_ARRAYS)
    for name, (kind, tail) in TRACE_ARRAYS.items():
        assert z[name].dtype.kind == kind, name
        assert z[name].shape == (5, *tail), name
    u = rays[:, 3:] / np.linalg.norm(rays[:, 3:], axis=1)[:, None]
    assert z["hit"].tolist() == [True, True, False, False, True]
    assert not z["null"].any()
    assert np.allclose(np.linalg.norm(z["out_dir"], axis=1), 1.0, atol=1e-12)
    miss = ~z["hit"]
    assert np.array_equal(z["out_origin"][miss], rays[miss, :3])
    assert np.allclose(z["out_dir"][miss], u[miss], atol=1e-15)
    assert np.isinf(z["t_first"][miss]).all() and (z["patch"][miss] == -1).all()
    assert (z["events"][miss] == 0).all() and (z["tree"][miss] == 0).all()
    # through the centre: straight through, leaving on the far side
    assert np.allclose(z["out_dir"][0], (0, 1, 0), atol=1e-9)
    assert np.isclose(z["t_first"][0], 1.0 - GLASS_SPHERE_RADIUS, atol=1e-9)
    assert np.allclose(z["out_origin"][0], _sphere_centre() + (0, GLASS_SPHERE_RADIUS, 0),
                       atol=1e-9)
    hit = z["hit"]
    assert (z["events"][hit] == 2).all()
    # normals are unit and face the incoming ray
    assert np.allclose(np.linalg.norm(z["normal"][hit], axis=1), 1.0)
    assert (np.einsum("ij,ij->i", z["normal"][hit], u[hit]) < 0).all()
    for name in z.files:
        if z[name].dtype.kind == "f":
            assert not np.isnan(z[name]).any(), name


def test_trace_rays_null_rays_have_zero_direction(files, tmp_path, capsys):
    np.save(tmp_path / "rays.npy", _crafted_rays())
    assert main(["trace-rays", str(files / "sphere_null.json"), "--rays",
                 str(tmp_path / "rays.npy"), "--out", str(tmp_path / "o.npz"), "--quiet"]) == 0
    capsys.readouterr()
    z = np.load(tmp_path / "o.npz")
    assert np.array_equal(z["null"], z["hit"]) and z["null"].sum() == 3
    assert (z["out_dir"][z["null"]] == 0).all()
    ln = np.linalg.norm(z["out_dir"], axis=1)
    assert np.allclose(ln[~z["null"]], 1.0)


def test_trace_rays_inside(files, tmp_path, capsys):
    """--inside: rays from inside the glass sphere leave it at the first hit by Snell's law
    (n = 1.5 -> 1), or are trapped by total internal reflection beyond the critical angle
    (null after max_events); without it the same rows are taken as entering the glass."""
    c, r, ior = _sphere_centre(), GLASS_SPHERE_RADIUS, 1.5
    theta = np.radians([20.0, 60.0])                   # incidence; critical angle 41.8 deg
    rays = np.array([[*(c + (0, 0, r * np.sin(a))), 1.0, 0, 0] for a in theta])
    np.save(tmp_path / "in.npy", rays)
    argv = ["trace-rays", str(files / "sphere.json"), "--rays", str(tmp_path / "in.npy"),
            "--workers", "1", "--quiet"]
    assert main([*argv, "--out", str(tmp_path / "in.npz"), "--inside"]) == 0
    assert main([*argv, "--out", str(tmp_path / "out.npz")]) == 0
    capsys.readouterr()
    z, z_out = np.load(tmp_path / "in.npz"), np.load(tmp_path / "out.npz")
    n = np.array([np.cos(theta[0]), 0, np.sin(theta[0])])           # outward normal at the hit
    cos_t = np.sqrt(1 - ior ** 2 * np.sin(theta[0]) ** 2)
    want = ior * np.array([1.0, 0, 0]) + (cos_t - ior * np.cos(theta[0])) * n
    assert z["events"][0] == 1 and not z["null"][0]
    assert np.allclose(z["out_origin"][0], c + r * n, atol=1e-9)
    assert np.allclose(z["out_dir"][0], want, atol=1e-9)
    assert z["null"][1] and z["events"][1] == load_scene(files / "sphere.json").render.max_events
    assert not np.allclose(z_out["out_dir"][0], want, atol=1e-3)
    rc = main([*argv, "--out", str(tmp_path / "t.npz"), "--inside", "--tree", "x.rit"])
    assert rc == 2
    _one_line_error(capsys.readouterr().err, "trace-rays")


def _bad_rays(tmp_path):
    ok = _crafted_rays()
    nan = ok.copy()
    nan[2, 1] = np.nan
    inf = ok.copy()
    inf[0, 4] = np.inf
    zero = ok.copy()
    zero[3, 3:] = 0.0
    far = ok.copy()
    far[1, 2] = 1e300
    out = {"shape": ok[:, :5], "1d": ok.ravel(), "nan": nan, "inf": inf, "zero_dir": zero,
           "strings": np.array([["a"] * 6]), "far_origin": far}
    paths = {}
    for k, v in out.items():
        paths[k] = tmp_path / f"{k}.npy"
        np.save(paths[k], v)
    paths["empty"] = tmp_path / "empty.npy"
    paths["empty"].write_bytes(b"")
    # a valid header claiming 1e12 rows (48 TB) over one row of data
    paths["huge_header"] = tmp_path / "huge.npy"
    with open(paths["huge_header"], "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": "<f8", "fortran_order": False, "shape": (10 ** 12, 6)})
        f.write(ok[0].tobytes())
    paths["npz"] = tmp_path / "x.npz"
    np.savez(paths["npz"], rays=ok)
    paths["text"] = tmp_path / "text.npy"
    paths["text"].write_text("1 2 3 4 5 6\n")
    paths["missing"] = tmp_path / "missing.npy"
    return paths


def test_trace_rays_bad_input_exit_2_one_line(files, tmp_path, capsys):
    for name, path in _bad_rays(tmp_path).items():
        rc = main(["trace-rays", str(files / "sphere.json"), "--rays", str(path), "--out",
                   str(tmp_path / "o.npz"), "--quiet"])
        cap = capsys.readouterr()
        assert rc == 2, name
        _one_line_error(cap.err, "trace-rays")
        assert not (tmp_path / "o.npz").exists(), name
    # the messages say what is wrong and where
    paths = _bad_rays(tmp_path)
    main(["trace-rays", str(files / "sphere.json"), "--rays", str(paths["nan"]), "--out",
          str(tmp_path / "o.npz")])
    assert "row 2 column 1" in capsys.readouterr().err
    main(["trace-rays", str(files / "sphere.json"), "--rays", str(paths["zero_dir"]), "--out",
          str(tmp_path / "o.npz")])
    assert "row 3 is zero" in capsys.readouterr().err
    main(["trace-rays", str(files / "sphere.json"), "--rays", str(paths["huge_header"]), "--out",
          str(tmp_path / "o.npz")])
    assert "truncated: the header says 1000000000000 rows" in capsys.readouterr().err
    main(["trace-rays", str(files / "sphere.json"), "--rays", str(paths["far_origin"]), "--out",
          str(tmp_path / "o.npz")])
    assert "row 1 column 2: origin coordinate 1e+300 is outside" in capsys.readouterr().err


def test_trace_rays_directions_of_any_size(files, tmp_path, capsys):
    """Directions are normalized without overflow or underflow: 1e300 and 1e-300 components
    give the unit direction (a miss passes it through unchanged, a hit goes on from it)."""
    rays = _crafted_rays()[[0, 2, 3]]                  # a hit through the centre, two misses
    want = rays[:, 3:] / np.linalg.norm(rays[:, 3:], axis=1)[:, None]
    for scale in (1e300, 1e-300):
        scaled = rays.copy()
        scaled[:, 3:] *= scale
        np.save(tmp_path / "r.npy", scaled)
        assert main(["trace-rays", str(files / "sphere.json"), "--rays", str(tmp_path / "r.npy"),
                     "--out", str(tmp_path / "o.npz"), "--workers", "1", "--quiet"]) == 0
        capsys.readouterr()
        z = np.load(tmp_path / "o.npz")
        assert z["hit"].tolist() == [True, False, False]
        assert np.allclose(z["out_dir"][1:], want[1:], atol=1e-15)
        assert np.allclose(z["out_dir"][0], (0, 1, 0), atol=1e-9)


def test_validate_good_and_bad(files, tmp_path, capsys):
    assert main(["validate", str(files / "sphere.json")]) == 0
    assert "ok" in capsys.readouterr().out
    d = json.loads((files / "sphere.json").read_text())
    d["object"]["patches"][0]["degree_u"] = 0
    (tmp_path / "bad.json").write_text(json.dumps(d))
    assert main(["validate", str(tmp_path / "bad.json")]) == 2
    err = capsys.readouterr().err
    _one_line_error(err, "validate")
    assert "object.patches[0].degree_u" in err
    (tmp_path / "empty.json").write_text("")
    assert main(["validate", str(tmp_path / "empty.json")]) == 2
    _one_line_error(capsys.readouterr().err, "validate")


def test_render_bad_arguments(files, tmp_path, capsys):
    for extra, what in ((["--camera", "nope"], "no camera named 'nope'"),
                        (["--width", "0"], "image size")):
        rc = main(["render", str(files / "sphere.json"), "--out", str(tmp_path / "x"),
                   "--quiet", *extra])
        err = capsys.readouterr().err
        assert rc == 2, extra
        _one_line_error(err, "render")
        assert what in err
    assert main(["render", "no_such_scene.json", "--out", str(tmp_path / "x")]) == 2
    _one_line_error(capsys.readouterr().err, "render")


def test_image_sizes_and_workers_checked_first(files, tmp_path, capsys, monkeypatch):
    """Every size flag has the scene format's limit (1..16384), every --workers is >= 1 and a
    bad RIRAY_WORKERS is named: one line, exit 2, before any work (nothing written)."""
    sphere = str(files / "sphere.json")
    out = str(tmp_path / "x")
    cases = [(["render", sphere, "--out", out, "--width", "100000", "--height", "100000"],
              "--width: image size must be 1..16384 pixels (got 100000)"),
             (["render", sphere, "--out", out, "--height", "16385"], "--height: image size"),
             (["demo", "--out", out, "--size", "20000"], "--size: image size"),
             (["bench-exact", "--size", "0", "--out", out + ".json"], "--size: image size"),
             (["bench", "--size", "16385", "--out", out], "--size: image size")]
    for cmd in (["render", sphere, "--out", out], ["bake", sphere, "--out", out + ".rit"],
                ["trace-rays", sphere, "--rays", out + ".npy", "--out", out + ".npz"],
                ["bench-exact", "--out", out + ".json"], ["demo", "--out", out]):
        cases += [(cmd + ["--workers", w], f"--workers must be >= 1 (got {w})")
                  for w in ("0", "-2")]
    for argv, msg in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        _one_line_error(err, argv[0])
        assert msg in err, (argv, err)
    monkeypatch.setenv("RIRAY_WORKERS", "abc")
    assert main(["render", sphere, "--out", out]) == 2
    err = capsys.readouterr().err
    _one_line_error(err, "render")
    assert "RIRAY_WORKERS must be a positive integer (got 'abc')" in err
    assert list(tmp_path.iterdir()) == []


def test_ctrl_c_during_bake(files, tmp_path, default_sigint):
    """SIGINT to the whole process group (a terminal's Ctrl-C) mid-bake, with worker processes:
    one line, exit 130, no traceback from the parent or the workers; the old cache is intact."""
    old = tmp_path / "tree.rit"
    old.write_bytes(b"the previous cache")
    exe = Path(sys.executable).parent / "riray"
    p = subprocess.Popen([str(exe), "bake", str(files / "sphere.json"), "--out", str(old),
                          "--full", "--viewpoint-depth", "3", "--direction-depth", "5",
                          "--workers", "2"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                         start_new_session=True, preexec_fn=default_sigint)
    seen = b""
    while b"bake:" not in seen:                          # the progress bar: baking has begun
        ch = p.stderr.read(1)
        assert ch, seen
        seen += ch
    time.sleep(0.3)
    os.killpg(p.pid, signal.SIGINT)
    try:                                 # stderr closes only when no worker is left holding it
        rest = p.communicate(timeout=120)[1]
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        pytest.fail("a process of the interrupted bake was still running after 120 s")
    err = (seen + rest).decode()
    assert p.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert err.splitlines()[-1] == "riray bake: interrupted", err
    assert old.read_bytes() == b"the previous cache"
    assert [f.name for f in tmp_path.iterdir()] == ["tree.rit"]          # no temporary left


def test_bench_exact_plumbing(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert main(["bench-exact", "--scenes", "glass_sphere", "--size", "12", "--workers", "1",
                 "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "| glass_sphere |" in printed and "object rays/s" in printed
    res = json.loads(out.read_text())
    row, = res["rows"]
    assert row["scene"] == "glass_sphere" and row["size"] == 12
    for key in ("build_s", "wall_s", "object_cpu_s", "total_cpu_s", "object_rays",
                "object_rays_per_s", "pairs_per_ray", "newton_iters_per_ray"):
        assert np.isfinite(row[key]) and row[key] >= 0, key
    assert res["machine"]["cpu_count"] >= 1 and res["settings"]["workers"] == 1


def test_saved_scene_round_trips(files):
    # the fixture's file is a real scene file (guards the tests above against a silent fallback)
    assert load_scene(files / "sphere.json").render.width == 24


def test_outputs_and_parameters_checked_before_any_work(files, tmp_path, capsys, monkeypatch):
    """An output that cannot be written (missing folder, a file in the way, a folder where a
    file goes) or a bad bake / query parameter: exit 2 and one line before the scene is even
    loaded (so before any bake or render), nothing written."""
    import riray.cli as cli
    import riray.scene.samples as samples

    def no_work(*a, **k):
        raise AssertionError("the slow work started")

    monkeypatch.setattr(cli, "_load", no_work)
    monkeypatch.setattr(samples, "build", no_work)
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    missing = tmp_path / "missing" / "x.rit"
    sphere = str(files / "sphere.json")
    cases = [
        (["bake", sphere, "--out", str(missing)], f"the folder {missing.parent} does not exist"),
        (["bake", sphere, "--out", str(a_file / "x.rit")], f"{a_file} is a file, not a folder"),
        (["bake", sphere, "--out", str(tmp_path)], "is a folder"),
        (["bake", sphere, "--out", str(tmp_path / "t.rit"), "--tolerance", "-1"],
         "tolerance_deg must be > 0"),
        (["bake", sphere, "--out", str(tmp_path / "t.rit"), "--viewpoint-depth", "9"],
         "viewpoint_depth + viewpoint_refine <= 10"),
        (["render", sphere, "--out", str(a_file / "sub" / "img")], "is a file, not a folder"),
        (["render", sphere, "--tree", "t.rit", "--out", str(a_file)], "is a file, not a folder"),
        (["render", sphere, "--tree", "t.rit", "--out", str(tmp_path / "r"),
          "--extrapolation", "-1"], "extrapolation must be None or a finite number >= 0"),
        (["trace-rays", sphere, "--rays", "r.npy", "--out", str(tmp_path / "no" / "o")],
         "does not exist"),
        (["demo", "--out", str(a_file)], "is a file, not a folder"),
        (["demo", "--out", str(tmp_path / "d"), "--search-steps", "99"], "search_steps"),
        (["bench-exact", "--out", str(tmp_path)], "is a folder"),
        (["bench", "--out", str(a_file / "b")], "is a file, not a folder"),
    ]
    for argv, msg in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        _one_line_error(err, argv[0])
        assert msg in err, (argv, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def _read_only_folder(tmp_path):
    """A folder this process cannot create files in: a mode 0o555 folder, or (root ignores
    modes) /sys on Linux; None if there is none."""
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    for folder in (ro, Path("/sys")):
        try:
            with tempfile.TemporaryFile(dir=folder):
                pass
        except OSError:
            return folder
    return None


def test_read_only_output_folder_refused_first(files, tmp_path, capsys, monkeypatch):
    import riray.cli as cli
    monkeypatch.setattr(cli, "_load", lambda *a: pytest.fail("the slow work started"))
    ro = _read_only_folder(tmp_path)
    try:
        if ro is None:
            pytest.skip("no read-only folder available")
        assert main(["bake", str(files / "sphere.json"), "--out", str(ro / "x.rit")]) == 2
        err = capsys.readouterr().err
        _one_line_error(err, "bake")
        assert f"cannot write in {ro}" in err
    finally:
        (tmp_path / "ro").chmod(0o755)


def test_mirror_rays_options():
    """--mirror-rays picks the mirror rule: newton (the default: exact hits), reflect (the
    interpolated normal) or interpolate (the paper's blend); other values are refused."""
    from riray.cli import _query_options, build_parser
    from riray.ritree.query import QueryOptions
    got = {}
    for mode in (None, "reflect", "newton", "interpolate"):
        argv = ["render", "teapot", "--tree", "t.rit", "--out", "x"]
        args = build_parser().parse_args(argv + ([] if mode is None else ["--mirror-rays", mode]))
        opt = _query_options(args)
        got[mode] = opt.mirror_rays
    assert got == {None: "newton", "reflect": "reflect", "newton": "newton",
                   "interpolate": "interpolate"}
    with pytest.raises(ValueError, match="mirror_rays must be one of"):
        QueryOptions(mirror_rays="blend").validate()


def test_bake_quality_presets():
    """--quality picks a preset's depths, viewpoint refinement and tolerance (default: default,
    BakeParams' defaults, the add-on's Default); a depth, refinement or tolerance flag takes
    over the preset's value; bake and demo parse them alike."""
    from riray.cli import _bake_params
    from riray.ritree.tree import BakeParams

    def params(*argv, cmd=("bake", "teapot", "--out", "t.rit")):
        p = _bake_params(build_parser().parse_args([*cmd, *argv]))
        return p.viewpoint_depth, p.direction_depth, p.viewpoint_refine, p.tolerance_deg

    assert _bake_params(build_parser().parse_args(["bake", "teapot", "--out", "t.rit"])) == \
        BakeParams()
    assert params() == params("--quality", "default") == (5, 6, 2, 0.5)
    assert params("--quality", "fast") == (4, 5, 2, 0.5)
    assert params("--quality", "draft") == (3, 4, 1, 1.0)
    assert params("--quality", "fast", "--viewpoint-depth", "2") == (2, 5, 2, 0.5)
    assert params("--quality", "draft", "--direction-depth", "7", "--viewpoint-refine", "0",
                  "--tolerance", "0.25") == (3, 7, 0, 0.25)
    assert params("--direction-depth", "3") == (5, 3, 2, 0.5)
    assert params("--quality", "fast", cmd=("demo",)) == (4, 5, 2, 0.5)


def test_query_defaults_are_query_options():
    """Without flags, render / trace-rays / demo answer through QueryOptions' defaults (the
    add-on's render-time defaults are the same: tests/addon/test_settings.py)."""
    from riray.cli import _query_options
    from riray.ritree.query import QueryOptions
    for argv in (["render", "teapot", "--tree", "t.rit", "--out", "x"],
                 ["trace-rays", "teapot", "--rays", "r.npy", "--out", "x"], ["demo"]):
        assert _query_options(build_parser().parse_args(argv)) == QueryOptions(), argv


def test_path_and_class_flags_reach_query_options():
    """--solve-paths off and --many-classes trace reach QueryOptions (solve_paths False,
    many_classes "trace"); each flag alone changes only its field."""
    from dataclasses import replace
    from riray.cli import _query_options
    from riray.ritree.query import QueryOptions

    def opts(*flags, cmd=("render", "teapot", "--tree", "t.rit", "--out", "x")):
        return _query_options(build_parser().parse_args([*cmd, *flags]))
    assert opts("--solve-paths", "off") == replace(QueryOptions(), solve_paths=False)
    assert opts("--solve-paths", "on") == QueryOptions()
    assert opts("--many-classes", "trace") == replace(QueryOptions(), many_classes="trace")
    assert opts("--many-classes", "first-hit") == QueryOptions()
    both = opts("--solve-paths", "off", "--many-classes", "trace",
                cmd=("trace-rays", "teapot", "--rays", "r.npy", "--out", "x"))
    assert (both.solve_paths, both.many_classes) == (False, "trace")
    assert opts("--solve-paths", "off", cmd=("demo",)).solve_paths is False
