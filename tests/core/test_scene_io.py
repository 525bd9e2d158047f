"""Scene file format: exact round trip, convenience forms, and one clear error per rule."""

import copy
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from riray.imageio import write_float_image, write_png_u8
from riray.scene.io import SceneError, load_scene, save_scene, scene_from_dict, scene_to_dict


def bilinear_patch(name="p0", class_id=0):
    return {"kind": "nurbs", "name": name, "class_id": class_id, "degree_u": 1, "degree_v": 1,
            "knots_u": [0, 0, 1, 1], "knots_v": [0.0, 0.0, 1.0, 1.0],
            "points": [[[0, 0, 0], [0, 1, 0]], [[1, 0, 0], [1, 1, 0.5]]],
            "weights": [[1.0, 1.0], [1.0, 2.0]]}


def minimal():
    return {
        "format": "riray-scene", "version": 1, "name": "t",
        "render": {"width": 64, "height": 48, "max_events": 4},
        "object": {"name": "obj", "material": {"kind": "glass", "ior": 1.45},
                   "patches": [bilinear_patch(),
                               {"kind": "mesh", "name": "tri", "class_id": 1,
                                "vertices": [[0, 0, 1], [1, 0, 1], [0, 1, 1]],
                                "triangles": [[0, 1, 2]]}]},
        "environment": {"meshes": [
            {"name": "floor", "material": "chk", "vertices": [[-1, -1, 0], [1, -1, 0], [1, 1, 0],
                                                               [-1, 1, 0]],
             "quads": [[0, 1, 2, 3]], "uvs": [[0, 0], [1, 0], [1, 1], [0, 1]]}]},
        "materials": [{"name": "chk", "color": {"kind": "checker", "coords": "uv", "scale": 4}},
                      {"name": "lamp", "kind": "emission", "color": [1, 0.5, 0.25],
                       "strength": 2}],
        "lights": [{"name": "L", "position": [0, 0, 3], "power": 500},
                   {"name": "S", "kind": "sun", "direction": [0, 0, -2], "strength": 2.5}],
        "world": {"kind": "gradient", "color": [0.1, 0.1, 0.1], "zenith": [0.2, 0.3, 0.9]},
        "cameras": [{"name": "cam", "location": [0, -5, 1], "look_at": [0, 0, 1]},
                    {"name": "top", "kind": "orthographic", "ortho_scale": 3.0,
                     "matrix_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 10], [0, 0, 0, 1]]}],
    }


def errmsg(d, **kw):
    with pytest.raises(SceneError) as e:
        scene_from_dict(d, **kw)
    return str(e.value)


def test_load_builds_model_and_conveniences():
    s = scene_from_dict(minimal())
    assert s.render.width == 64 and s.object.material.ior == 1.45
    assert s.object.patches[0].surface.weights[1, 1] == 2.0
    assert s.object.patches[1].is_mesh and s.object.patches[1].triangles.dtype == np.int64
    floor = s.meshes[0]
    assert floor.triangles.tolist() == [[0, 1, 2], [0, 2, 3]]     # quad split on load
    assert s.materials["lamp"].color.kind == "constant" and s.materials["lamp"].color.color[2] == 0.25
    assert s.lights[1].direction == (0.0, 0.0, -1.0)                 # normalized on load
    m = s.cameras[0].matrix_world                                     # look_at form
    assert np.allclose(m[:3, 3], [0, -5, 1])
    assert np.allclose(-m[:3, 2], [0, 1, 0]) and np.allclose(m[:3, 1], [0, 0, 1])
    assert s.cameras[1].kind == "orthographic"


def test_polygons_fan_triangulated():
    d = minimal()
    del d["environment"]["meshes"][0]["quads"]
    d["environment"]["meshes"][0]["polygons"] = [[0, 1, 2, 3], [0, 2, 3]]
    tris = scene_from_dict(d).meshes[0].triangles
    assert tris.tolist() == [[0, 1, 2], [0, 2, 3], [0, 2, 3]]


def test_save_load_round_trip_exact(tmp_path):
    d = minimal()
    d["object"]["patches"][0]["points"][0][0] = [0.1, 1 / 3, math.pi]    # needs repr precision
    s = scene_from_dict(d)
    p = tmp_path / "s.json"
    save_scene(s, p)
    s2 = load_scene(p)
    assert scene_to_dict(s2) == scene_to_dict(s)
    assert s2.object.patches[0].surface.points[0, 0, 1] == 1 / 3
    np.testing.assert_array_equal(s2.cameras[0].matrix_world, s.cameras[0].matrix_world)
    save_scene(s2, p)                                                 # idempotent text
    text = p.read_text()
    save_scene(load_scene(p), p)
    assert p.read_text() == text
    assert [x.name for x in tmp_path.iterdir()] == ["s.json"]         # no temp files left


def test_images_load_relative_to_scene_file(tmp_path):
    (tmp_path / "tex").mkdir()
    write_png_u8(tmp_path / "tex" / "a.png", np.full((2, 3, 3), 255, np.uint8))
    write_float_image(tmp_path / "sky.npy", np.full((4, 8, 3), 0.5))
    d = minimal()
    d["materials"][0]["color"] = {"kind": "image", "path": "tex/a.png"}
    d["world"] = {"kind": "image", "path": "sky.npy", "strength": 2}
    p = tmp_path / "s.json"
    p.write_text(json.dumps(d))
    s = load_scene(p)
    assert s.materials["chk"].color.image.shape == (2, 3, 3)
    assert s.materials["chk"].color.coords == "uv"                    # image default coords
    assert np.all(s.world.image == 0.5)
    d["world"]["path"] = "missing.npy"
    p.write_text(json.dumps(d))
    with pytest.raises(SceneError, match=r"^world\.path: image file not found"):
        load_scene(p)


def test_invalid_json_and_duplicate_keys(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text('{"format": "riray-scene",\n "version": 1,,}')
    with pytest.raises(SceneError, match="line 2 column"):
        load_scene(p)
    p.write_text('{"format": "riray-scene", "version": 1, "version": 1}')
    with pytest.raises(SceneError, match="duplicate key 'version'"):
        load_scene(p)


def mutate(path, value):
    """minimal() with the field at ``path`` (a list of keys) set to ``value`` (None deletes)."""
    d = copy.deepcopy(minimal())
    node = d
    for k in path[:-1]:
        node = node[k]
    if value is None:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return d


PATCH = ["object", "patches", 0]
MESH = ["environment", "meshes", 0]
CAM = ["cameras", 1]
CASES = [
    (["format"], "scene", r"^format: expected 'riray-scene'"),
    (["version"], 2, r"^version: unsupported version 2"),
    (["lihgts"], [], r"^top level: unknown key 'lihgts'; did you mean 'lights'\?"),
    (["object"], None, r"^top level: missing required key 'objects'"),
    (PATCH + ["weights", 1, 1], -1.0, r"^object\.patches\[0\]\.weights\[1\]\[1\]: weight must be > 0 \(got -1\.0\)"),
    (PATCH + ["weights", 0, 1], float("nan"), r"^object\.patches\[0\]\.weights\[0\]\[1\]: must be finite"),
    (PATCH + ["points", 1, 0, 2], float("inf"), r"^object\.patches\[0\]\.points\[1\]\[0\]\[2\]: must be finite"),
    (PATCH + ["points", 1, 0, 2], "0", r"^object\.patches\[0\]\.points\[1\]\[0\]\[2\]: expected a number"),
    (PATCH + ["points", 1, 1], [1, 1], r"^object\.patches\[0\]\.points\[1\]\[1\]: expected 3 entries"),
    (PATCH + ["knots_u"], [0, 0, 1], r"^object\.patches\[0\]\.knots_u: expected n_u \+ degree_u \+ 1 = 2 \+ 1 \+ 1 = 4 knots \(got 3\)"),
    (PATCH + ["knots_v"], [0, 1, 0.5, 1], r"^object\.patches\[0\]\.knots_v\[2\]: knots must be non-decreasing"),
    (PATCH + ["degree_u"], 1.0, r"^object\.patches\[0\]\.degree_u: expected an integer"),
    (PATCH + ["degree_u"], 2, r"^object\.patches\[0\]\.points: 2 control points along u; need at least"),
    (PATCH + ["kind"], "bezier", r"^object\.patches\[0\]\.kind: unknown kind 'bezier'"),
    (PATCH + ["wieghts"], [], r"^object\.patches\[0\]: unknown key 'wieghts' for a nurbs patch; did you mean 'weights'"),
    (PATCH + ["class_id"], -1, r"^object\.patches\[0\]\.class_id: must be >= 0"),
    (["object", "patches"], [], r"^object\.patches: the specular object needs at least one patch"),
    (["object", "material", "ior"], 0, r"^object\.material\.ior: must be >= 0\.01 \(got 0\.0\)"),
    (["object", "material", "ior"], 1e3, r"^object\.material\.ior: must be <= 100"),
    # the supported range (docs/scene-format.md)
    (PATCH + ["points", 1, 0, 2], 1e200, r"^object\.patches\[0\]\.points\[1\]\[0\]\[2\]: magnitude must be <= 100000 \(got 1e\+200\)"),
    (PATCH + ["points", 1, 0, 2], 1e9, r"^object\.patches\[0\]\.points\[1\]\[0\]\[2\]: magnitude must be <= 100000"),
    (PATCH + ["weights", 0, 1], 1e300, r"^object\.patches\[0\]\.weights\[0\]\[1\]: magnitude must be <= 1e\+12"),
    (PATCH + ["class_id"], 2 ** 70, r"^object\.patches\[0\]\.class_id: must be <= 2147483647"),
    (["object", "patches", 1, "vertices", 2, 1], -2e5, r"^object\.patches\[1\]\.vertices\[2\]\[1\]: magnitude must be <= 100000"),
    (MESH + ["vertices", 0, 0], 3e5, r"^environment\.meshes\[0\]\.vertices\[0\]\[0\]: magnitude must be <= 100000"),
    (["lights", 0, "power"], 1e308, r"^lights\[0\]\.power: magnitude must be <= 1e\+12 \(got 1e\+308\)"),
    (["lights", 0, "position"], [0, 0, 1e6], r"^lights\[0\]\.position\[2\]: magnitude must be <= 100000"),
    (["lights", 1, "strength"], 1e13, r"^lights\[1\]\.strength: magnitude must be <= 1e\+12"),
    (["materials", 1, "color", 0], 1e300, r"^materials\[1\]\.color\[0\]: magnitude must be <= 1e\+12"),
    (["cameras", 0, "location"], [0, -2e5, 1], r"^cameras\[0\]\.location\[1\]: magnitude must be <= 100000"),
    (CAM + ["matrix_world", 2, 3], 2e5, r"^cameras\[1\]\.matrix_world\[2\]\[3\]: magnitude must be <= 100000"),
    (["object", "material", "kind"], "metal", r"^object\.material\.kind: unknown kind 'metal'"),
    (MESH + ["quads", 0, 3], 4, r"^environment\.meshes\[0\]\.quads\[0\]\[3\]: vertex index 4 out of range"),
    (MESH + ["material"], "wal", r"^environment\.meshes\[0\]\.material: material 'wal' is not defined"),
    (MESH + ["uvs"], None, r"^environment\.meshes\[0\]: material 'chk' has a uv-mapped texture but"),
    (MESH + ["uvs"], [[0, 0]], r"^environment\.meshes\[0\]\.uvs: expected 4 entries"),
    (MESH + ["quads"], None, r"^environment\.meshes\[0\]: missing faces"),
    (MESH + ["quads"], [], r"^environment\.meshes\[0\]: the mesh has no faces"),
    (["object", "patches", 1, "triangles", 0, 0], -1, r"^object\.patches\[1\]\.triangles\[0\]\[0\]: vertex index -1"),
    (["materials", 0, "color", "axis"], 1, r"^materials\[0\]\.color: unknown key 'axis' for texture kind 'checker'"),
    (["materials", 0, "color", "kind"], "noise", r"^materials\[0\]\.color\.kind: unknown kind 'noise'"),
    (["materials", 0, "color", "scale"], 0, r"^materials\[0\]\.color\.scale: must be > 0"),
    (["materials", 1, "color", 1], -0.5, r"^materials\[1\]\.color\[1\]: colour components must be >= 0"),
    (["materials", 1, "name"], "chk", r"^materials\[1\]\.name: duplicate material name 'chk'"),
    (["lights", 0, "direction"], [0, 0, 1], r"^lights\[0\]: unknown key 'direction' for light kind 'point'"),
    (["lights", 1, "direction"], [0, 0, 0], r"^lights\[1\]\.direction: must not be the zero vector"),
    (["world", "kind"], "sky", r"^world\.kind: unknown kind 'sky'"),
    (["render", "width"], 0, r"^render\.width: must be >= 1 \(got 0\)"),
    (["render", "height"], 16385, r"^render\.height: must be <= 16384"),
    (["render", "max_events"], 0, r"^render\.max_events: must be >= 1"),
    (CAM + ["lens"], -50, r"^cameras\[1\]\.lens: must be > 0"),
    (CAM + ["sensor_fit"], "auto", r"^cameras\[1\]\.sensor_fit: unknown sensor_fit 'auto'"),
    (CAM + ["matrix_world", 0, 0], 2.0, r"^cameras\[1\]\.matrix_world: not rigid: rotation part is not orthonormal"),
    (CAM + ["matrix_world", 0], [-1, 0, 0, 0], r"^cameras\[1\]\.matrix_world: not rigid: rotation part is a reflection"),
    (CAM + ["matrix_world", 3], [0, 0, 1, 1], r"^cameras\[1\]\.matrix_world\[3\]: bottom row must be"),
    (CAM + ["location"], [0, 0, 0], r"^cameras\[1\]: unknown key 'location'"),
    (["cameras", 0, "look_at"], [0, -5, 1], r"^cameras\[0\]: look_at equals location"),
    (["cameras", 0, "up"], [0, 1, 0], r"^cameras\[0\]: up is zero or parallel"),
    (["cameras", 1, "name"], "cam", r"^cameras\[1\]\.name: duplicate camera name 'cam'"),
]


@pytest.mark.parametrize("path,value,pattern", CASES, ids=[str(c[0]) + "=" + repr(c[1]) for c in CASES])
def test_validation_names_field_and_problem(path, value, pattern):
    msg = errmsg(mutate(path, value))
    assert re.search(pattern, msg), msg


def test_integers_beyond_float_range():
    assert re.search(r"^object\.patches\[0\]\.points: number out of range",
                     errmsg(mutate(PATCH + ["points", 1, 0, 2], 10 ** 400)))
    assert re.search(r"^lights\[0\]\.power: must be finite", errmsg(mutate(["lights", 0, "power"],
                                                                          10 ** 400)))


def test_object_far_from_the_origin_for_its_size():
    """The object (box diagonal D = sqrt(3) here) may lie up to 1e4 D from the origin: 5e3 m
    loads, 5e4 m (within the +-1e5 m coordinate range) is refused, naming the patch."""
    for shift, ok in ((5e3, True), (5e4, False)):
        d = minimal()
        for p in d["object"]["patches"]:
            key = "points" if p["kind"] == "nurbs" else "vertices"
            p[key] = (np.asarray(p[key], float) + shift).tolist()
        if ok:
            scene_from_dict(d)
        else:
            assert re.search(r"^object\.patches\[\d\]\.(points|vertices): the object lies "
                             r"5e\+04 m from the origin, more than 10000 times its size",
                             errmsg(d))


def test_degenerate_object_refused_flat_and_thin_ones_load():
    """An object whose points all coincide, or lie on one line (no area), is refused naming
    what is wrong, for NURBS control points and mesh vertices alike, wherever it lies; a flat
    object, and a ribbon 1e-6 of its length wide, load."""
    rng = np.random.default_rng(3)
    u = np.array([2.0, -1.0, 0.5]) / np.linalg.norm([2.0, -1.0, 0.5])
    w = np.cross(u, [0.0, 0.0, 1.0])
    w /= np.linalg.norm(w)

    def with_points(place):
        """minimal()'s object with every point placed by place(k) for k points, shape (k, 3)."""
        d = minimal()
        for p in d["object"]["patches"]:
            key = "points" if p["kind"] == "nurbs" else "vertices"
            shape = np.shape(p[key])
            p[key] = place(int(np.prod(shape[:-1]))).reshape(shape).tolist()
        return d

    along = lambda k: 3.0 + rng.uniform(-1, 1, (k, 1)) * u             # noqa: E731
    cases = {"coincide": lambda k: np.tile([40.0, 2.0, -7.0], (k, 1)),
             "lie on one line": along}
    for words, place in cases.items():
        msg = errmsg(with_points(place))
        assert msg.startswith("object.patches: the object is degenerate (all its control points "
                              f"and vertices {words}"), msg
        assert "from the origin" not in msg
    for kind in ("nurbs", "mesh"):
        d = with_points(along)
        d["object"]["patches"] = [p for p in d["object"]["patches"] if p["kind"] == kind]
        what = "control points" if kind == "nurbs" else "vertices"
        assert f"(all its {what} lie on one line" in errmsg(d)
    flat = lambda k: along(k) + rng.uniform(-1, 1, (k, 1)) * w         # noqa: E731
    ribbon = lambda k: along(k) + rng.uniform(-1e-6, 1e-6, (k, 1)) * w  # noqa: E731
    for place in (flat, ribbon):
        assert len(scene_from_dict(with_points(place)).object.patches) == 2


def test_tolerates_near_rigid_camera():
    c = 1 / math.sqrt(2)
    d = mutate(CAM + ["matrix_world"], [[c, -c, 0, 1], [c, c + 1e-8, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    assert scene_from_dict(d).cameras[1].matrix_world[1, 3] == 2


def test_save_rejects_invalid_scene_and_keeps_old_file(tmp_path):
    s = scene_from_dict(minimal())
    p = tmp_path / "s.json"
    save_scene(s, p)
    before = p.read_text()
    s.object.patches[0].surface.weights[0, 0] = 0.0
    with pytest.raises(SceneError, match=r"weights\[0\]\[0\]: weight must be > 0"):
        save_scene(s, p)
    assert p.read_text() == before


def test_documented_example_loads():
    doc = (Path(__file__).resolve().parents[2] / "docs" / "scene-format.md").read_text()
    example = re.search(r"```json\n(.*?)```", doc, re.S).group(1)
    s = scene_from_dict(json.loads(example))
    assert s.name == "tiny" and len(s.meshes[0].triangles) == 2 and s.cameras[0].lens == 35.0
