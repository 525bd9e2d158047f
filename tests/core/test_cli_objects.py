"""The `riray` command line on a scene of several specular objects (docs/cli.md): bake needs
--object, render takes one --tree OBJECT=PATH per object and refuses a tree baked for another
object, each with exit 2 and one line before any slow work; a scene of one object keeps its
bare --tree PATH."""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from riray.cli import main
from riray.imageio import read_float_image
from riray.scene.camera import camera_rays
from riray.scene.io import save_scene

# the two mirrors and their closed form, from the test next to this file (pytest runs with
# --import-mode=importlib: tests/core is not on sys.path)
_spec = importlib.util.spec_from_file_location(
    "riray_tests_several_objects", Path(__file__).with_name("test_several_objects.py"))
_two = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_two)
reference, two_mirrors = _two.reference, _two.two_mirrors

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

SIZE = 16
SMALL = ["--viewpoint-depth", "2", "--viewpoint-refine", "0", "--direction-depth", "3",
         "--workers", "1"]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The two mirrors at SIZE x SIZE, the sphere alone in the older single-object form, and a
    small tree of each mirror baked through the command line."""
    d = tmp_path_factory.mktemp("objects")
    scene = two_mirrors()
    scene.render.width = scene.render.height = SIZE
    save_scene(scene, d / "two.json")
    save_scene(scene.view(0), d / "ball.json")
    for name in ("ball", "floor"):
        assert main(["bake", str(d / "two.json"), "--object", name, "--out",
                     str(d / f"{name}.rit"), *SMALL]) == 0
    return d


def _one_line_error(capsys, cmd, pattern):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"riray {cmd}: error: "), err
    assert pattern in err[0], err


def test_bake_needs_object(files, capsys, tmp_path):
    out = tmp_path / "t.rit"
    assert main(["bake", str(files / "two.json"), "--out", str(out), *SMALL]) == 2
    _one_line_error(capsys, "bake", "2 specular objects ('ball', 'floor'): choose one with "
                                    "--object NAME")
    assert main(["bake", str(files / "two.json"), "--object", "lamp", "--out", str(out),
                 *SMALL]) == 2
    _one_line_error(capsys, "bake", "no specular object named 'lamp'")
    assert not out.exists()


@pytest.mark.parametrize("trees,pattern", [
    (["{d}/ball.rit"], "give --tree OBJECT=PATH"),
    (["ball={d}/floor.rit"], "baked for the object 'floor', not 'ball'"),
    (["ball={d}/ball.rit", "ball={d}/ball.rit"], "two trees for the object 'ball'"),
])
def test_render_refuses_trees_it_cannot_place(files, capsys, tmp_path, trees, pattern):
    args = [a for t in trees for a in ("--tree", t.format(d=files))]
    assert main(["render", str(files / "two.json"), "--out", str(tmp_path / "r"), "--quiet",
                 "--workers", "1", *args]) == 2
    _one_line_error(capsys, "render", pattern)


def test_render_through_each_objects_tree(files, capsys, tmp_path):
    """One tree per object: the image is the closed form's (within interpolation error) and
    the summary gives each object's pixels and traced share; with one tree left out that
    object is traced, with a warning."""
    out = tmp_path / "r"
    assert main(["render", str(files / "two.json"), "--out", str(out), "--quiet", "--workers",
                 "1", "--tree", f"ball={files}/ball.rit", "--tree",
                 f"floor={files}/floor.rit"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert set(summary["objects"]) == {"ball", "floor"}
    assert all(o["through"] == "tree" and o["object_pixels"] > 0
               for o in summary["objects"].values())
    scene = two_mirrors()
    want = np.array([reference(a, b)[0] for a, b in zip(*camera_rays(scene.cameras[0], SIZE,
                                                                        SIZE))])
    got = read_float_image(out / "interpolated.npy").reshape(-1, 3)
    assert np.mean(np.abs(got - want).max(axis=1) < 0.02) > 0.95
    assert main(["render", str(files / "two.json"), "--out", str(tmp_path / "s"), "--quiet",
                 "--workers", "1", "--no-reference", "--tree", f"floor={files}/floor.rit"]) == 0
    cap = capsys.readouterr()
    assert "no --tree for the object 'ball': it is traced exactly" in cap.err
    assert json.loads(cap.out)["objects"]["ball"]["through"] == "exact"


def test_one_object_scene_keeps_bare_tree(files, capsys, tmp_path):
    """The older file with one "object" renders through a bare --tree PATH (the ball's tree,
    baked from the two-object scene, is that object's)."""
    assert main(["render", str(files / "ball.json"), "--out", str(tmp_path / "b"), "--quiet",
                 "--workers", "1", "--no-reference", "--tree", str(files / "ball.rit")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["object_pixels"] > 0 and "objects" not in summary
    assert main(["render", str(files / "ball.json"), "--out", str(tmp_path / "c"), "--quiet",
                 "--workers", "1", "--no-reference", "--tree", str(files / "floor.rit")]) == 2
    _one_line_error(capsys, "render", "stale tree")


def test_exact_render_and_validate_see_both(files, capsys, tmp_path):
    assert main(["validate", str(files / "two.json")]) == 0
    assert "2 specular objects ('ball': 1, 'floor': 1 patches)" in capsys.readouterr().out
    assert main(["render", str(files / "two.json"), "--out", str(tmp_path / "e"), "--quiet",
                 "--workers", "1"]) == 0
    capsys.readouterr()
    got = read_float_image(tmp_path / "e.npy").reshape(-1, 3)
    rows = [reference(a, b) for a, b in zip(*camera_rays(two_mirrors().cameras[0], SIZE, SIZE))]
    ok = ~np.array([r[1] for r in rows])
    want = np.array([r[0] for r in rows])
    assert np.abs(got[ok] - want[ok]).max() < 1e-5      # float32 file
