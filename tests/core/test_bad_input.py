"""Bad input gives a clear error naming the field (SceneError from load_scene, exit 2 and one
line from the CLI), never a traceback; a camera inside the object is refused; f never returns
NaN for finite rays, including rays starting on the surface and rays through the vase's poles."""

import json

import numpy as np
import pytest

from riray.cli import main
from riray.render.exact import render_exact
from riray.scene.camera import Shot
from riray.trace.scene_tracer import SceneTracer, point_inside
from riray.scene.io import SceneError, load_scene, look_at_matrix, scene_to_dict
from riray.scene.model import Camera
from riray.scene.samples import GLASS_SPHERE_RADIUS, SAMPLES, build, sample_points


@pytest.fixture(scope="module")
def sphere_dict():
    return scene_to_dict(build("glass_sphere"))


def _patch(d):
    return d["object"]["patches"][0]


def _set(path, value):
    def edit(d):
        *head, last = path
        node = d
        for k in head:
            node = node[k]
        node[last] = value
    return edit


def _drop_knot(d):
    _patch(d)["knots_u"].pop()


def _decreasing(d):
    k = _patch(d)["knots_v"]
    k[3], k[4] = 0.9, 0.1


def _points_to(make):
    """Every control point of the sphere replaced: make(n) -> (n, 3) new positions."""
    def edit(d):
        pts = np.asarray(_patch(d)["points"], float)
        _patch(d)["points"] = make(pts[..., 0].size).reshape(pts.shape).tolist()
    return edit


ONE_POINT_2M = _points_to(lambda n: np.tile([2.0, 0.0, 0.0], (n, 1)))
ON_A_LINE = _points_to(lambda n: np.outer(np.linspace(-1.0, 1.0, n), [0.3, -0.2, 0.9]))


P0 = ("object", "patches", 0)
# name -> (edit of the scene dict, the field the message must name, a word of the problem)
CASES = {
    "wrong version": (_set(("version",), 2), "version", "unsupported version"),
    "wrong format": (_set(("format",), "blend"), "format", "not a riray scene"),
    "zero weight": (_set(P0 + ("weights", 1, 2), 0.0), "object.patches[0].weights[1][2]", "> 0"),
    "negative weight": (_set(P0 + ("weights", 0, 0), -1.0), "object.patches[0].weights[0][0]",
                        "> 0"),
    "knots wrong length": (_drop_knot, "object.patches[0].knots_u", "knots"),
    "knots decreasing": (_decreasing, "object.patches[0].knots_v[4]", "non-decreasing"),
    "NaN point": (_set(P0 + ("points", 2, 1, 0), float("nan")),
                  "object.patches[0].points[2][1][0]", "finite"),
    "inf point": (_set(P0 + ("points", 0, 0, 2), float("inf")),
                  "object.patches[0].points[0][0][2]", "finite"),
    "NaN mesh vertex": (_set(("environment", "meshes", 0, "vertices", 1, 1), float("nan")),
                        "environment.meshes[0].vertices[1][1]", "finite"),
    "NaN camera": (_set(("cameras", 1, "matrix_world", 0, 3), float("nan")),
                   "cameras[1].matrix_world[0][3]", "finite"),
    "unknown object material kind": (_set(("object", "material", "kind"), "metal"),
                                     "object.material.kind", "unknown kind 'metal'"),
    "unknown material kind": (_set(("materials", 0, "kind"), "plastic"), "materials[0].kind",
                              "unknown kind 'plastic'"),
    "string where a number goes": (_set(P0 + ("degree_u",), "2"), "object.patches[0].degree_u",
                                   "integer"),
    "no patches": (_set(("object", "patches"), []), "object.patches", "at least one patch"),
    "class id beyond 64 bits": (_set(P0 + ("class_id",), 2 ** 70), "object.patches[0].class_id",
                                "must be <= 2147483647"),
    "control point at 1e250": (_set(P0 + ("points", 4, 2, 1), 1e250),
                               "object.patches[0].points[4][2][1]", "magnitude must be <= 100000"),
    "control point moved 1e9 m": (_set(P0 + ("points", 3, 2, 0), 1e9),
                                  "object.patches[0].points[3][2][0]", "magnitude"),
    "control points at one point 2 m out": (ONE_POINT_2M, "object.patches",
                                            "degenerate (all its control points coincide)"),
    "control points on one line": (ON_A_LINE, "object.patches",
                                   "degenerate (all its control points lie on one line"),
    "light power 1e308": (_set(("lights", 0, "power"), 1e308), "lights[0].power",
                          "magnitude must be <= 1e+12"),
}


def _write(tmp_path, d, name="scene.json"):
    p = tmp_path / name
    p.write_text(json.dumps(d))            # json writes NaN / Infinity literals as Python does
    return p


def _cli_rejects(capsys, argv, cmd):
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2, argv
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"riray {cmd}: error: "), err
    assert "Traceback" not in err
    return lines[0]


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_scene_names_the_field(case, sphere_dict, tmp_path, capsys):
    edit, field, problem = CASES[case]
    d = json.loads(json.dumps(sphere_dict))
    edit(d)
    path = _write(tmp_path, d)
    with pytest.raises(SceneError) as e:
        load_scene(path)
    msg = str(e.value)
    assert msg.startswith(field + ":") or f" {field}:" in msg or msg.startswith(field), msg
    assert problem in msg, msg
    assert "\n" not in msg
    line = _cli_rejects(capsys, ["validate", str(path)], "validate")
    assert field in line
    line = _cli_rejects(capsys, ["render", str(path), "--out", str(tmp_path / "x"), "--quiet"],
                        "render")
    assert field in line
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize("text", ['{"format": "riray-scene", "version": 1,', "", "[1, 2",
                                  '{"format": "riray-scene", "format": "riray-scene"}',
                                  "\u00ff\u00fe not json", "[" * 100_000 + "]" * 100_000,
                                  '{"a":' * 100_000 + "1" + "}" * 100_000])
def test_malformed_json(text, tmp_path, capsys):
    path = tmp_path / "bad.json"
    path.write_text(text, encoding="latin-1")
    with pytest.raises(ValueError) as e:
        load_scene(path)
    assert "\n" not in str(e.value)
    assert str(e.value).startswith(str(path)), e.value
    _cli_rejects(capsys, ["validate", str(path)], "validate")
    _cli_rejects(capsys, ["trace-rays", str(path), "--rays", str(path), "--out",
                          str(tmp_path / "o.npz")], "trace-rays")


def test_missing_and_directory_scene(tmp_path, capsys):
    _cli_rejects(capsys, ["validate", str(tmp_path / "nope.json")], "validate")
    _cli_rejects(capsys, ["render", str(tmp_path), "--out", str(tmp_path / "x")], "render")


@pytest.mark.parametrize("w, h", [(100000, 100000), (16385, 8), (8, 0)])
def test_engine_refuses_image_sizes_the_flags_refuse(w, h):
    """Size limits hold for every way a size arrives: the engine API too, before allocating."""
    from riray.render.interpolated import render_tree
    scene = build("glass_sphere")
    with pytest.raises(ValueError, match="must be 1..16384 pixels"):
        render_exact(SceneTracer(scene), Shot(width=w, height=h), workers=1)
    with pytest.raises(ValueError, match="must be 1..16384 pixels"):
        render_tree(SceneTracer(scene), None, Shot(width=w, height=h), workers=1)


# --------------------------------------------------------------------------- camera inside
def _with_camera(scene, name, location, look_at):
    scene.cameras.append(Camera(name=name, matrix_world=look_at_matrix(location, look_at)))
    return scene


def _centre(scene):
    pts = np.concatenate([p.surface.points.reshape(-1, 3) for p in scene.object.patches])
    return (pts.min(axis=0) + pts.max(axis=0)) / 2


def test_camera_inside_the_object_is_refused(tmp_path, capsys):
    scene = build("glass_sphere")
    c = _centre(scene)
    _with_camera(scene, "inside", c + (0.02, -0.01, 0.03), c + (0, 1, 0))
    with pytest.raises(ValueError, match="camera 'inside' is inside the object 'glass_sphere'"):
        render_exact(SceneTracer(scene), Shot(camera="inside", width=8, height=8), workers=1)
    from riray.scene.io import save_scene
    save_scene(scene, tmp_path / "s.json")
    line = _cli_rejects(capsys, ["render", str(tmp_path / "s.json"), "--camera", "inside",
                                 "--out", str(tmp_path / "x"), "--quiet"], "render")
    assert "is inside the object" in line


def test_inside_test_parity():
    sphere = build("glass_sphere")
    st = SceneTracer(sphere)
    c = _centre(sphere)
    r = GLASS_SPHERE_RADIUS
    assert point_inside(st, c)
    assert point_inside(st, c + 0.99 * r * np.array([0.6, 0.0, 0.8]))
    # in the bounding box, outside the ball (a corner of the box); far away
    assert not point_inside(st, c + 0.95 * r * np.ones(3))
    assert not point_inside(st, c + (0, 0, 3))
    # the vase: the solid's wall/base is inside, the open cavity (the vase's mouth) is not
    vase = build("vase_mirror")
    st = SceneTracer(vase)
    lo = st.tracer.lo
    vc = _centre(vase)
    assert point_inside(st, (vc[0], vc[1], lo[2] + 0.01))
    assert not point_inside(st, vc)


def test_camera_in_the_vase_mouth_renders(tmp_path):
    # inside the bounding box but outside the solid: a legal (if odd) viewpoint
    scene = build("vase_mirror")
    c = _centre(scene)
    _with_camera(scene, "mouth", c, c + (0.05, 0, -1))
    res = render_exact(SceneTracer(scene), Shot(camera="mouth", width=6, height=6), workers=1)
    assert np.isfinite(res.image).all()


# --------------------------------------------------------------------------- no NaN from f
def _finite_outputs(res):
    for name, v in res.__dict__.items():
        if v.dtype.kind == "f":
            vals = v[res.hit] if name == "t_first" else v
            assert np.isfinite(vals).all(), name
    ln = np.linalg.norm(res.out_dir, axis=1)
    assert np.allclose(ln[~res.null], 1.0, atol=1e-9)
    assert (ln[res.null] == 0).all()
    assert np.allclose(np.linalg.norm(res.normal[res.hit], axis=1), 1.0, atol=1e-9)


@pytest.mark.parametrize("name,material", [(n, None) for n in SAMPLES]
                         + [("vase_glass", "dielectric")])
def test_no_nan_from_f(name, material):
    rng = np.random.default_rng(7)
    scene = build(name, material=material)
    st = SceneTracer(scene)
    lo, hi = st.tracer.lo, st.tracer.hi
    size = float(np.linalg.norm(hi - lo))
    # random rays aimed at random points of the box, from anywhere around it
    n = 600
    o = (lo + hi) / 2 + rng.normal(size=(n, 3)) * size
    d = lo + rng.random((n, 3)) * (hi - lo) - o
    # rays starting on the surface, in random directions (either side)
    p = sample_points(scene.object.patches, 5)
    d2 = rng.normal(size=p.shape)
    # along the axis of revolution (x = y = 0 for every sample), through the poles, both ways,
    # exactly and 1e-12 off it
    zt, zb = hi[2] + 0.5, lo[2] - 0.5
    ao = np.array([[0, 0, zt], [0, 0, zb], [1e-12, 0, zt], [0, -1e-12, zb], [0, 0, (zt + zb) / 2],
                   [0, 0, (zt + zb) / 2]])
    ad = np.array([[0, 0, -1], [0, 0, 1], [0, 0, -1], [0, 0, 1], [0, 0, 1], [0, 0, -1.0]])
    O = np.concatenate([o, p, ao])
    D = np.concatenate([d, d2, ad])
    D /= np.linalg.norm(D, axis=1)[:, None]
    with np.errstate(all="ignore"):       # intermediate warnings are not the question here
        res = st.object_function(O, D)
    _finite_outputs(res)
    assert res.hit[-6:-2].all(), "axis rays from outside must hit the object"
