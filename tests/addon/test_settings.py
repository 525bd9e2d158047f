"""riray settings survive save -> reopen: every scene / object / material / world / view-layer
setting, in this Blender and from a file saved by an older one (4.2 LTS, where registered
properties share the custom-property storage); riray settings written as custom properties
by scripts without the add-on are adopted."""

import importlib.util
import json
import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
# The interpreter of the older Blender for the cross-version test (make test builds it).
OLD_BPY_PYTHON = Path(os.environ.get("RIRAY_OLD_BPY_PYTHON",
                                     ROOT / ".venv-bpy42" / "bin" / "python"))


@pytest.fixture(scope="module")
def roundtrip():
    spec = importlib.util.spec_from_file_location(
        "riray_settings_roundtrip", Path(__file__).with_name("settings_roundtrip.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _same(got, want, where=""):
    """Equal, floats to float32 precision."""
    if isinstance(want, dict):
        assert set(got) == set(want), where
        for k in want:
            _same(got[k], want[k], f"{where}.{k}")
    elif isinstance(want, list):
        assert len(got) == len(want), where
        for i, (g, w) in enumerate(zip(got, want)):
            _same(g, w, f"{where}[{i}]")
    elif isinstance(want, float):
        assert got == pytest.approx(want, rel=1e-6), where
    else:
        assert got == want, where


def _reopen(bpy, path):
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=str(path))


@pytest.mark.filterwarnings("error::RuntimeWarning")     # e.g. "//" paths not declared relative
def test_every_setting_survives_save_and_reopen(bl, roundtrip, tmp_path):
    bpy = bl.bpy
    want = roundtrip.fill(bpy)
    path = tmp_path / "settings.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.read_homefile(use_empty=True)
    fresh = {"scene": bpy.context.scene.riray, "view_layer": bpy.context.view_layer.riray}
    for kind, group in fresh.items():           # fill() really changed every setting
        for key, value in want[kind].items():
            assert getattr(group, key) != value, f"{kind}.{key}"
    bpy.ops.wm.open_mainfile(filepath=str(path))
    _same(roundtrip.read(bpy), want)
    # ... and again after saving the reopened file
    bpy.ops.wm.save_mainfile()
    _reopen(bpy, path)
    _same(roundtrip.read(bpy), want)


def test_settings_from_a_file_saved_by_blender_4_2(bl, roundtrip, extension_zip, tmp_path):
    """A .blend saved with the add-on by the bpy 4.2 wheel opens here with every setting.
    (The other direction does not exist: 4.x cannot read files saved by 5.0.)"""
    bpy = bl.bpy
    if bpy.app.version < (5, 0, 0):
        pytest.skip("this Blender is the old one; Blender 4.x cannot open files saved by 5.0")
    if not OLD_BPY_PYTHON.exists():
        pytest.skip(f"no Blender 4.2 interpreter at {OLD_BPY_PYTHON} (make test builds it)")
    blend, out = tmp_path / "from42.blend", tmp_path / "from42.json"
    res = subprocess.run([str(OLD_BPY_PYTHON), str(Path(__file__).with_name(
        "settings_roundtrip.py")), str(extension_zip.path), str(blend), str(out)],
        capture_output=True, text=True, timeout=180, env={**os.environ, "RIRAY_WORKERS": "1"})
    assert res.returncode == 0, res.stdout + res.stderr
    saved = json.loads(out.read_text())
    assert saved["version"][0] == 4
    _reopen(bpy, blend)
    _same(roundtrip.read(bpy), saved["settings"])


def test_custom_property_settings_adopted(bl, tmp_path):
    """Settings a script wrote as ``id["riray"]`` dicts, with an enum item by name and an
    integral float, become the add-on's settings when the file is opened."""
    bpy = bl.bpy
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=0.5)
    obj = bpy.context.active_object
    obj["riray"] = {"policy": "RAYTREE", "tolerance_deg": 2, "viewpoint_depth": 3,
                    "spline_groups": [{"group": 4}]}
    bpy.context.scene["riray"] = {"target": obj, "max_events": 5}
    path = tmp_path / "legacy.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    name = obj.name
    _reopen(bpy, path)
    obj = bpy.data.objects[name]
    scene = bpy.context.scene
    assert scene.riray.target == obj and scene.riray.max_events == 5
    p = obj.riray
    assert (p.policy, p.tolerance_deg, p.viewpoint_depth) == ("RAYTREE", 2.0, 3)
    assert [g.group for g in p.spline_groups] == [4]
    assert bl.properties.adopt_custom_properties() == 0          # nothing left to adopt


def test_defaults_are_cores(bl):
    """A new object bakes and renders as `riray bake` / `riray render` do without options
    (tests/core/test_cli.py: BakeParams' and QueryOptions' defaults): every bake setting the
    add-on shares with BakeParams, the render-time rules (as QueryOptions), samples and max
    events default to core's values; the Quality menu holds core's presets, its default
    Default being BakeParams' defaults."""
    import importlib
    from dataclasses import asdict
    bpy = bl.bpy
    core = bl.addon.__name__.rpartition(".")[0] + ".core"
    params = importlib.import_module(core + ".ritree.params")
    query = importlib.import_module(core + ".ritree.query")
    model = importlib.import_module(core + ".scene.model")
    camera = importlib.import_module(core + ".scene.camera")
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=0.5)
    obj = bpy.context.active_object
    got = bl.properties.bake_params(obj)
    want = asdict(params.BakeParams())
    assert set(want) - set(got) == {"viewpoint_tolerance_deg", "pad"}     # not in the add-on
    _same({k: got[k] for k in want if k in got}, {k: v for k, v in want.items() if k in got})
    # every QueryOptions field but these is a setting, so its default is checked here too
    # (one_path: a rule of the tolerance that is always on in the add-on; certify_first_hits:
    # the same answers, only faster; fresnel_tree: a glass material's reflections at every
    # crossing, always on as Blender's renderers weigh them)
    assert set(asdict(query.QueryOptions())) - set(got["query"]) == \
        {"threshold_on", "threshold_leaves", "fallback_angle_deg", "one_path",
         "certify_first_hits", "fresnel_tree"}
    _same(asdict(query.QueryOptions(**got["query"])), asdict(query.QueryOptions()))
    assert bl.properties.QUALITY == {k.upper(): v for k, v in params.QUALITY_PRESETS.items()}
    assert {k: got[k] for k in params.QUALITY_PRESETS["default"]} == \
        params.QUALITY_PRESETS["default"]
    assert got["quality"] == "DEFAULT" and got["bake_for_cameras"]
    scene = bpy.context.scene.riray
    assert (scene.samples, scene.max_events) == \
        (camera.Shot().samples, model.RenderSettings().max_events)


def test_path_and_class_rules_reach_query_options(bl):
    """"Solve along sample paths" and "More than two classes" reach QueryOptions (solve_paths,
    many_classes), each without changing the other rules."""
    import importlib
    from dataclasses import asdict
    bpy = bl.bpy
    query = importlib.import_module(bl.addon.__name__.rpartition(".")[0] + ".core.ritree.query")
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=0.5)
    obj = bpy.context.active_object
    p = obj.riray

    def options():
        return asdict(query.QueryOptions(**bl.properties.query_options(obj)).validate())
    default = options()
    assert (default["solve_paths"], default["many_classes"]) == (True, "first_hit")
    p.use_solve_paths = False
    assert options() == {**default, "solve_paths": False}
    p.many_classes = "TRACE"
    assert options() == {**default, "solve_paths": False, "many_classes": "trace"}
    p.use_solve_paths = True
    p.many_classes = "FIRST_HIT"
    assert options() == default


def test_quality_numbers_of_older_files(bl):
    """The .blend stores the Quality item's number: a file saved when 1 was Default at depths
    4 / 5 and 2 was Paper at 5 / 6 opens as Fast and Default, whose depths those are."""
    bpy = bl.bpy
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=0.5)
    p = bpy.context.active_object.riray
    p.search_steps = 5                          # the object now has stored settings
    stored = bl.compat.registered_storage(bpy.context.active_object, "riray")
    for number, item, depths in ((0, "DRAFT", (3, 4)), (1, "FAST", (4, 5)),
                                 (2, "DEFAULT", (5, 6)), (3, "CUSTOM", None)):
        stored["quality"] = number
        assert p.quality == item
        if depths:
            preset = bl.properties.QUALITY[item]
            assert (preset["viewpoint_depth"], preset["direction_depth"]) == depths
