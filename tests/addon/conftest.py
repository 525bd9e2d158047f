"""Fixtures for the add-on tests: the bpy module is imported once per test run, after the
extension zip was built (Blender's builder), validated and pointed at a temporary
BLENDER_USER_RESOURCES; the zip is then installed into bpy and enabled.

Every test here is skipped (not failed) when the bpy wheel is not installed; `make test`
installs it.
"""

from __future__ import annotations

import importlib.util
import os
import tempfile
from pathlib import Path
from types import SimpleNamespace

import pytest

ROOT = Path(__file__).resolve().parents[2]
# RIRAY_SKIP_BPY=1 skips these tests even where bpy is installed (quick core-only runs).
HAVE_BPY = importlib.util.find_spec("bpy") is not None and not os.environ.get("RIRAY_SKIP_BPY")
EXT_PKG = "bl_ext.user_default.riray"
# Add-on tests that never import bpy (add-on modules without bpy): they run everywhere.
BPY_FREE = {"test_reuse.py"}


def pytest_collection_modifyitems(config, items):
    if HAVE_BPY:
        return
    skip = pytest.mark.skip(reason="the bpy module is not installed (pip install bpy==5.0.1; "
                                   "`make test` installs it)")
    for item in items:
        path = Path(str(item.fspath)).resolve()
        if path.is_relative_to(Path(__file__).parent) and path.name not in BPY_FREE:
            item.add_marker(skip)


def _load_build_script():
    spec = importlib.util.spec_from_file_location("riray_build_extension",
                                                  ROOT / "riray_addon" / "build_extension.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="session")
def extension_zip(tmp_path_factory):
    """dist zip built by Blender's builder into a temporary folder (and validated)."""
    build = _load_build_script()
    out = tmp_path_factory.mktemp("dist")
    stage = tmp_path_factory.mktemp("stage") / "extension"
    blender_ext = build.find_blender_ext()
    assert blender_ext is not None, "the bpy wheel ships blender_ext.py"
    path = build.build(out, blender_ext, validate=True, stage_dir=stage)
    return SimpleNamespace(path=path, blender_ext=blender_ext, build=build)


@pytest.fixture(scope="session")
def blender(extension_zip, tmp_path_factory):
    """bpy with the riray extension installed from the zip and enabled.

    Returns a namespace: bpy, the add-on package (``addon``: bl_ext...riray.riray_addon),
    its modules, and ``reset()`` which empties the current file."""
    resources = tempfile.mkdtemp(prefix="riray_bl_user_")
    os.environ["BLENDER_USER_RESOURCES"] = resources
    os.environ.setdefault("RIRAY_WORKERS", "1")
    import bpy
    res = bpy.ops.extensions.package_install_files(
        filepath=str(extension_zip.path), repo="user_default", enable_on_install=True)
    assert res == {"FINISHED"}, res
    import importlib
    addon = importlib.import_module(f"{EXT_PKG}.riray_addon")
    mods = {name: importlib.import_module(f"{EXT_PKG}.riray_addon.{name}")
            for name in ("export", "materials", "engine", "operators", "backend", "jobs",
                         "cache", "report", "properties", "worker", "ui", "compat")}

    def reset():
        """Empty file, factory scene settings kept minimal (the add-on stays enabled)."""
        bpy.ops.wm.read_homefile(use_empty=True)
        scene = bpy.context.scene
        scene.render.engine = "RIRAY"
        scene.view_settings.view_transform = "Standard"
        return scene

    ns = SimpleNamespace(bpy=bpy, addon=addon, reset=reset, resources=resources,
                         zip=extension_zip.path, **mods)
    yield ns
    for job in list(mods["jobs"].JOBS.values()) + list(mods["jobs"].ESTIMATES.values()):
        if job.running:
            job.cancel()
            job.wait(timeout=10)


@pytest.fixture
def bl(blender):
    """``blender`` with an empty file loaded first."""
    blender.reset()
    return blender

