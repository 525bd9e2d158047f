"""The sample scenes built as .blend files (sample_scenes/build_blend.py): the exported object
equals core's sample (patches, classes, material) and Blender's own evaluated surfaces; the
environment, lights, world and cameras come back; a .blend written without the add-on opens
with it; and the engine's render matches core's render of the sample."""

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from riray.render.exact import render_exact
from riray.scene.camera import Shot
from riray.trace.scene_tracer import SceneTracer
from riray.scene import samples

ROOT = Path(__file__).resolve().parents[2]


def _load_script(name: str):
    """sample_scenes/<name>.py imported as a module (riray_<name>)."""
    spec = importlib.util.spec_from_file_location(f"riray_{name}",
                                                  ROOT / "sample_scenes" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def build_blend(blender):
    return _load_script("build_blend")


def _norm(k):
    k = np.asarray(k, dtype=np.float64)
    return (k - k[0]) / (k[-1] - k[0])


def _export(bl, obj):
    return bl.export.export_scene(bl.bpy.context.evaluated_depsgraph_get(), obj,
                                  bl.report.Report())


@pytest.mark.parametrize("name", samples.SAMPLES)
def test_sample_blend_exports_the_core_sample(blender, build_blend, name):
    bl = blender
    bpy = bl.bpy
    ref = samples.build(name)
    obj = build_blend.build_scene(name, ref)
    got = _export(bl, obj)
    # -- the object, patch by patch; glass turned outwards (Cycles needs it) by reversing u
    refractive = ref.object.material.kind != "mirror"
    volume = build_blend.signed_volume(obj)
    assert volume > 0 or not refractive
    assert len(got.object.patches) == len(ref.object.patches)
    turned = []
    for a, b in zip(got.object.patches, ref.object.patches):
        sa, sb = a.surface, b.surface
        rev = bool(np.abs(sa.points - sb.points).max() > 1e-6)
        turned.append(rev)
        pb, wb = (sb.points[::-1], sb.weights[::-1]) if rev else (sb.points, sb.weights)
        kb = 1.0 - _norm(sb.knots_u)[::-1] if rev else _norm(sb.knots_u)
        assert (sa.degree_u, sa.degree_v) == (sb.degree_u, sb.degree_v)
        assert np.allclose(_norm(sa.knots_u), kb, atol=1e-12)
        assert np.allclose(_norm(sa.knots_v), _norm(sb.knots_v), atol=1e-12)
        assert np.abs(sa.points - pb).max() < 1e-6                 # float32 control points
        assert np.abs(sa.weights - wb).max() < 1e-7
        assert a.class_id == b.class_id
    assert not any(turned) or (refractive and all(turned))
    om, rm = got.object.material, ref.object.material
    assert om.kind == rm.kind and om.ior == pytest.approx(rm.ior)
    assert np.allclose(om.tint, rm.tint) and om.specular == pytest.approx(rm.specular)
    # -- Blender's evaluated mesh lies on the exported surfaces
    dg = bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(dg)
    me = ev.to_mesh()
    co = np.empty(len(me.vertices) * 3)
    me.vertices.foreach_get("co", co)
    ev.to_mesh_clear()
    from riray.geometry.nurbs import evaluate
    pts = []
    for sp, patch in zip(obj.data.splines, got.object.patches):
        u, v = bl.export.blender_sample_params(sp, patch.surface)
        uu, vv = np.meshgrid(u, v, indexing="ij")
        pts.append(evaluate(patch.surface, uu.ravel(), vv.ravel(), derivatives=0)[0])
    assert np.abs(np.concatenate(pts) - co.reshape(-1, 3)).max() < 1e-5
    # -- environment, lights, world, cameras, render settings
    assert sorted(m.name for m in got.meshes) == sorted(m.name for m in ref.meshes)
    for m in ref.meshes:
        g = [x for x in got.meshes if x.name == m.name][0]
        assert len(g.triangles) == len(m.triangles)
        tg, tr = got.materials[g.material].color, ref.materials[m.material].color
        assert (tg.kind, tg.coords) == (tr.kind, tr.coords if tr.kind != "constant" else tg.coords)
        assert np.allclose(tg.color, tr.color) and np.allclose(tg.color2, tr.color2)
        if tr.kind != "constant":
            assert tg.scale == pytest.approx(tr.scale)
        if tr.kind in ("stripes", "gradient"):
            assert tg.axis == tr.axis
        if tr.kind == "gradient":
            assert (tg.start, tg.end) == (pytest.approx(tr.start), pytest.approx(tr.end))
        assert g.smooth == m.smooth
    assert [(li.kind, li.power) for li in got.lights] == \
        [(li.kind, pytest.approx(li.power)) for li in ref.lights]
    assert got.world.kind == ref.world.kind
    assert np.allclose(got.world.zenith, ref.world.zenith)
    assert got.world.ambient == pytest.approx(ref.world.ambient)
    assert [c.name for c in got.cameras] == [c.name for c in ref.cameras][:1] + sorted(
        c.name for c in ref.cameras[1:])
    for c in ref.cameras:
        g = [x for x in got.cameras if x.name == c.name][0]
        assert np.abs(np.asarray(g.matrix_world) - c.matrix_world).max() < 1e-6
        assert g.lens == pytest.approx(c.lens)
    assert (got.render.width, got.render.height, got.render.max_events) == (300, 300, 8)


@pytest.fixture(scope="module")
def bowl_blend(tmp_path_factory):
    """build_blend.py run as a script by plain Python with the bpy module (add-on not
    installed in that process)."""
    out = tmp_path_factory.mktemp("blends")
    res = subprocess.run([sys.executable, str(ROOT / "sample_scenes" / "build_blend.py"),
                          "bowl", "--out", str(out)], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    return out / "bowl.blend"


def test_blend_without_addon_opens_with_it(blender, bowl_blend):
    """The riray settings build_blend stored as custom properties are adopted on load."""
    bpy = blender.bpy
    bpy.ops.wm.open_mainfile(filepath=str(bowl_blend))
    scene = bpy.context.scene
    obj = scene.riray.target
    assert obj is not None and obj.name == "bowl"
    assert [g.group for g in obj.riray.spline_groups] == [0, 1, 2]
    assert scene.world.riray.ambient == pytest.approx(0.6)
    got = _export(blender, obj)
    assert [p.class_id for p in got.object.patches] == [0, 1, 2]


def test_engine_render_matches_core_sample(blender, build_blend, tmp_path):
    """F12 on the glass sphere .blend (small frame) against core's render of the sample."""
    bpy = blender.bpy
    ref = samples.build("glass_sphere")
    build_blend.build_scene("glass_sphere", ref)
    scene = bpy.context.scene
    scene.render.resolution_percentage = 10                 # 30 x 30
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = str(tmp_path / "sphere.exr")
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    got = blender.engine.LAST_RENDER["image"]
    want = render_exact(SceneTracer(ref), Shot(camera=scene.camera.name, width=30, height=30), workers=1).image
    err = np.abs(got - want)
    # float32 scene data in Blender: identical but for a few pixels on edges / silhouettes
    assert np.mean(err > 1e-3) < 0.02 and np.median(err) < 1e-5


def test_headless_workflow(extension_zip, bowl_blend, tmp_path):
    """sample_scenes/headless_render.py: open the .blend, bake (small tree), render 2 frames."""
    import shutil
    blend = tmp_path / "bowl.blend"
    shutil.copy(bowl_blend, blend)
    res = subprocess.run(
        [sys.executable, str(ROOT / "sample_scenes" / "headless_render.py"), str(blend),
         "--frames", "1-2", "--percentage", "5", "--viewpoint-depth", "1",
         "--direction-depth", "1", "--save", "--out", str(tmp_path / "out" / "bowl_"),
         "--zip", str(extension_zip.path)],
        capture_output=True, text=True, timeout=300,
        env={**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "bl_user")})
    log = res.stdout + res.stderr
    assert res.returncode == 0, log
    assert "baked in" in log and "rendered 2 frame(s)" in log
    assert (tmp_path / "bowl.bowl.rit").is_file()                   # cache beside the .blend
    for f in (1, 2):
        assert (tmp_path / "out" / f"bowl_{f:04d}.png").is_file()


@pytest.mark.parametrize("args, message", [
    (["--frames", "5-2"], "--frames 5-2: the range ends (2) before it starts (5)"),
    (["--frames", "abc"], "--frames 'abc': expected a frame N or a range A-B"),
    (["--viewpoint-depth", "30"], "--viewpoint-depth 30: must be in 1..9"),
    (["--percentage", "-5"], "--percentage -5: must be in 1..32767"),
    (["--camera", "nope"], "--camera: no camera named 'nope'"),
    ("missing", "missing.blend: no such file"),
])
def test_headless_bad_input(extension_zip, bowl_blend, tmp_path, args, message):
    """Bad input to headless_render.py: one line naming it, exit status 2, before any bake."""
    blend = str(tmp_path / "missing.blend") if args == "missing" else str(bowl_blend)
    res = subprocess.run(
        [sys.executable, str(ROOT / "sample_scenes" / "headless_render.py"), blend,
         *([] if args == "missing" else args), "--zip", str(extension_zip.path)],
        capture_output=True, text=True, timeout=120,
        env={**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "bl_user")})
    assert res.returncode == 2, res.stdout + res.stderr
    assert "Traceback" not in res.stderr and "baking" not in res.stdout
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("headless_render.py: error: ") and message in last, res.stderr


@pytest.mark.parametrize("script", ["blender_bench.py", "animation_bench.py", "factory_bench.py",
                                    "suzanne_bench.py"])
def test_bench_scripts_start(script, tmp_path):
    """The Blender benchmark scripts import what they use (every import runs before --help)
    and answer --help."""
    res = subprocess.run([sys.executable, str(ROOT / "sample_scenes" / script), "--help"],
                         capture_output=True, text=True, timeout=120,
                         env={**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "bl_user")})
    assert res.returncode == 0 and "usage:" in res.stdout, res.stdout + res.stderr


@pytest.fixture(scope="module")
def blender_bench(blender):
    return _load_script("blender_bench")


def test_blender_bench_sizes_and_quality(blender_bench):
    """blender_bench.py --size N is N x N pixels, --size WxH is W wide and H high; its tree is
    baked at the product's default settings (BakeParams' defaults, the paper's depths 5 / 6)
    unless --quality names another preset (fast: depths 4 / 5)."""
    from riray.ritree.params import BakeParams
    parse = blender_bench.parse_args
    assert parse(["--size", "300"]).size == (300, 300)
    assert parse(["--size", "1920x1080"]).size == (1920, 1080)
    assert parse(["--size", "64X48"]).size == (64, 48)
    default = parse([])
    assert default.size == (300, 300) and default.quality == "default"
    assert default.params == BakeParams()
    assert (default.params.viewpoint_depth, default.params.direction_depth) == (5, 6)
    fast = parse(["--quality", "fast"]).params
    assert (fast.viewpoint_depth, fast.direction_depth) == (4, 5)


@pytest.mark.parametrize("args, message", [
    (["--size", "1920by1080"], "argument --size: '1920by1080': expected N or WIDTHxHEIGHT"),
    (["--size", "1920x1080x2"], "argument --size: '1920x1080x2': expected N or WIDTHxHEIGHT"),
    (["--size", "0x300"], "argument --size: '0x300': image width must be 1.."),
    (["--size", "300x99999"], "argument --size: '300x99999': image height must be 1.."),
    (["--quality", "best"], "argument --quality: invalid choice: 'best'"),
])
def test_blender_bench_bad_input(tmp_path, args, message):
    """Bad input to blender_bench.py: exit status 2 and one line naming it, before any work
    (no output folder, no render)."""
    res = subprocess.run([sys.executable, str(ROOT / "sample_scenes" / "blender_bench.py"),
                          *args, "--out", str(tmp_path / "out")],
                         capture_output=True, text=True, timeout=120,
                         env={**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "bl_user")})
    assert res.returncode == 2, res.stdout + res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("blender_bench.py: error: "), res.stderr
    assert message in lines[0], lines[0]
    assert not (tmp_path / "out").exists()


def test_animation_bench_refuses_one_frame(tmp_path):
    """animation_bench.py --frames 1: one line and exit status 2, before any build or bake."""
    res = subprocess.run([sys.executable, str(ROOT / "sample_scenes" / "animation_bench.py"),
                          "--frames", "1", "--work", str(tmp_path / "work")],
                         capture_output=True, text=True, timeout=120,
                         env={**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "bl_user")})
    assert res.returncode == 2, res.stdout + res.stderr
    assert res.stderr.strip().splitlines()[-1] == (
        "animation_bench: the camera must move over at least 2 frames (--frames minus --hold, "
        "--hold >= 0)")
    assert not (tmp_path / "work").exists()


def test_animation_bench_refuses_a_bad_size(tmp_path):
    """animation_bench.py --size 960by540: one line naming it and exit status 2."""
    res = subprocess.run([sys.executable, str(ROOT / "sample_scenes" / "animation_bench.py"),
                          "--size", "960by540", "--work", str(tmp_path / "work")],
                         capture_output=True, text=True, timeout=120,
                         env={**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "bl_user")})
    assert res.returncode == 2, res.stdout + res.stderr
    assert "--size 960by540: expected WIDTHxHEIGHT" in res.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "work").exists()
