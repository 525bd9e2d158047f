"""Packaging: the extension zip (built + validated by Blender's own tools in the fixture) holds
exactly the add-on and the engine, installs into bpy, enables, and registers its classes."""

import subprocess
import sys
import zipfile


def test_zip_contents(extension_zip):
    names = zipfile.ZipFile(extension_zip.path).namelist()
    assert extension_zip.path.name == "riray-0.1.0.zip"
    assert "blender_manifest.toml" in names and "__init__.py" in names
    assert "riray_addon/__init__.py" in names and "core/render/exact.py" in names
    tops = {n.split("/")[0] for n in names}
    assert tops == {"blender_manifest.toml", "__init__.py", "riray_addon", "core"}, tops
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]
    assert "riray_addon/build_extension.py" not in names     # a build tool, not the add-on
    assert "core/cli.py" not in names


def test_validator_accepts_zip(extension_zip):
    tags = extension_zip.build.valid_tags_file(extension_zip.blender_ext)
    res = subprocess.run([sys.executable, str(extension_zip.blender_ext), "validate",
                          str(extension_zip.path), f"--valid-tags={tags}"],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def _checkout_files(root) -> set[str]:
    """Every path under the checkout (ignored ones included), but git's and the venvs'."""
    import os
    out = set()
    for top, dirs, files in os.walk(root):
        dirs[:] = [d for d in dirs if d != ".git" and not d.startswith(".venv")]
        rel = os.path.relpath(top, root)
        out.update(os.path.normpath(os.path.join(rel, n)) for n in dirs + files)
    return out


def test_build_leaves_the_checkout_untouched(tmp_path):
    """`build_extension.py --out DIR`, as make extension runs it, writes the zip into DIR and
    nothing into the checkout (it stages in a temporary folder outside it)."""
    import importlib.util
    from pathlib import Path
    root = Path(__file__).resolve().parents[2]
    script = root / "riray_addon" / "build_extension.py"
    spec = importlib.util.spec_from_file_location("riray_build_extension_check", script)
    build = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(build)
    if build.find_blender_ext() is None:
        import pytest
        pytest.skip("Blender's extension tool (blender_ext.py, in the bpy wheel) is not here")
    before = _checkout_files(root)
    res = subprocess.run([sys.executable, str(script), "--out", str(tmp_path / "out"),
                          "--validate"], cwd=root, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["riray-0.1.0.zip"]
    after = _checkout_files(root)
    assert after == before, (sorted(after - before), sorted(before - after))


def test_installed_and_enabled(blender):
    bpy = blender.bpy
    assert "bl_ext.user_default.riray" in bpy.context.preferences.addons.keys()
    assert blender.addon.__name__ == "bl_ext.user_default.riray.riray_addon"


def test_classes_registered(blender):
    t = blender.bpy.types
    for name in ("RIRAY_OT_bake", "RIRAY_OT_bake_cancel", "RIRAY_OT_bake_clear",
                 "RIRAY_OT_bake_estimate", "RIRAY_OT_export_scene", "RIRAY_PT_bake_object",
                 "RIRAY_PT_bake_view3d", "RIRAY_PT_render", "RIRAY_PT_passes"):
        assert hasattr(t, name), name
    assert t.RIRAY_PT_bake_object.bl_label == "Bake RI-Tree"
    assert t.RIRAY_PT_bake_object.bl_context == "object"
    assert t.RIRAY_PT_bake_view3d.bl_space_type == "VIEW_3D"
    engine = blender.engine.RirayRenderEngine
    assert engine.bl_idname == "RIRAY" and engine.bl_label == "RI-Tree Preview"
    assert engine.is_registered
    scene = blender.bpy.context.scene
    scene.render.engine = "RIRAY"
    assert scene.render.engine == "RIRAY"
    for owner in (t.Scene, t.Object, t.Material, t.World, t.ViewLayer):
        assert hasattr(owner, "riray")


def test_worker_modules_do_not_import_bpy():
    """backend / jobs / worker / report run in the bake worker, which has no bpy."""
    import re
    from pathlib import Path
    root = Path(__file__).resolve().parents[2] / "riray_addon"
    for name in ("backend.py", "jobs.py", "worker.py", "report.py", "build_extension.py"):
        text = (root / name).read_text()
        assert not re.search(r"^\s*(import bpy|from bpy)", text, re.M), name
