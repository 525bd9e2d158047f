"""The README's install-and-use path in Blender, followed step by step on the bpy wheel:
build the zip with the command the README gives (the Makefile's `extension` recipe, into a
temporary folder; the checkout gains no file), install it as *Install from Disk…* does, then
select a glass NURBS object, bake it with the operator behind the *Bake RI-Tree* panel's
**Bake** button, pick the *RI-Tree Preview* engine and render (F12). The object's pixels must
come through the tree. The README's words are read here, so the two cannot drift apart.

Blender runs in a fresh process (its own BLENDER_USER_RESOURCES), so installing the zip again
does not touch the extension the other add-on tests share."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

# What a user reads on the README's first screen, word for word.
README_WORDS = (
    "make extension",
    "dist/riray-<version>.zip",
    "Edit › Preferences › Get Extensions",
    "Install from Disk…",
    "Bake RI-Tree",
    "**Bake**",
    "RI-Tree Preview",
    "F12",
)

BLENDER_SCRIPT = r'''
import json, math, sys
import bpy

zip_path = sys.argv[1]
# Install from Disk… (Edit > Preferences > Get Extensions > drop-down)
res = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default",
                                                enable_on_install=True)
assert res == {"FINISHED"}, res
import importlib
pkg = "bl_ext.user_default.riray.riray_addon"
compat = importlib.import_module(pkg + ".compat")
engine = importlib.import_module(pkg + ".engine")
ui = importlib.import_module(pkg + ".ui")

bpy.ops.wm.read_homefile(use_empty=True)
scene = bpy.context.scene
scene.view_settings.view_transform = "Standard"
# a glass NURBS ball (Refraction BSDF, IOR 1.5) over a checker floor, a light, a camera
bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=0.8, location=(0, 0, 0.2))
ball = bpy.context.active_object
mat = compat.new_material("glass")
nt = mat.node_tree
out = next(n for n in nt.nodes if n.type == "OUTPUT_MATERIAL")
refr = nt.nodes.new("ShaderNodeBsdfRefraction")
refr.inputs["IOR"].default_value = 1.5
refr.inputs["Roughness"].default_value = 0.0
nt.links.new(refr.outputs["BSDF"], out.inputs["Surface"])
ball.data.materials.append(mat)
bpy.ops.mesh.primitive_plane_add(size=8, location=(0, 0, -0.7))
floor = bpy.context.active_object
fm = compat.new_material("floor")
chk = fm.node_tree.nodes.new("ShaderNodeTexChecker")
chk.inputs["Scale"].default_value = 4.0
fm.node_tree.links.new(chk.outputs["Color"],
                       fm.node_tree.nodes["Principled BSDF"].inputs["Base Color"])
floor.data.materials.append(fm)
bpy.ops.object.light_add(type="POINT", location=(2, -2, 3))
bpy.context.active_object.data.energy = 900.0
bpy.ops.object.camera_add(location=(0, -4, 1.0), rotation=(math.radians(82), 0, 0))
scene.camera = bpy.context.active_object
r = scene.render
r.resolution_x, r.resolution_y, r.resolution_percentage = 32, 32, 100

# 1. select the glass object
for o in bpy.context.view_layer.objects:
    o.select_set(False)
ball.select_set(True)
bpy.context.view_layer.objects.active = ball
# 2. Object properties > Bake RI-Tree > Bake (the Draft preset keeps this test short)
panel = bpy.types.RIRAY_PT_bake_object
ball.riray.quality = "DRAFT"
res = bpy.ops.riray.bake()
assert res == {"FINISHED"}, res
# 3. Render engine RI-Tree Preview, F12
scene.render.engine = engine.RirayRenderEngine.bl_idname
res = bpy.ops.render.render()
assert res == {"FINISHED"}, res
print("RESULT " + json.dumps({
    "panel": [panel.bl_label, panel.bl_context, panel.bl_space_type],
    "bake_op": bpy.types.RIRAY_OT_bake.bl_label,
    "engine": engine.RirayRenderEngine.bl_label,
    "stats": engine.LAST_RENDER["stats"],
    "traced_pixels_in_pass": float(engine.LAST_RENDER["traced"].sum()),
    "image_std": float(engine.LAST_RENDER["image"].std()),
}))
'''


def _readme() -> str:
    return (ROOT / "README.md").read_text(encoding="utf-8")


def _extension_recipe() -> list[str]:
    """The command `make extension` runs, from the Makefile's recipe."""
    text = (ROOT / "Makefile").read_text(encoding="utf-8")
    m = re.search(r"^extension:.*\n\t(.+)$", text, re.M)
    assert m, "the Makefile has an `extension` target"
    return shlex.split(m.group(1))


def _checkout_listing() -> set[str]:
    """Every path git reports as new or ignored (untracked files included, one by one)."""
    res = subprocess.run(["git", "status", "--porcelain", "--ignored", "--untracked-files=all"],
                         cwd=ROOT, capture_output=True, text=True, check=True)
    return {line[3:] for line in res.stdout.splitlines() if line[:2] in ("??", "!!")}


def test_readme_names_the_steps():
    text = _readme()
    for words in README_WORDS:
        assert words in text, words
    # the Blender install, then the three steps, come first (before the command line)
    first = text[:text.index("## Install and use from the command line")]
    install = first.index("## Install in Blender")
    use = first.index("## Use it in Blender")
    assert install < use
    for words in ("make extension", "dist/riray-<version>.zip", "Install from Disk…"):
        assert install < first.index(words) < use, words
    steps = first[use:]
    for words in ("Bake RI-Tree", "**Bake**", "RI-Tree Preview", "F12"):
        assert words in steps, words
    ui = (ROOT / "riray_addon" / "ui.py").read_text(encoding="utf-8")
    assert 'operator("riray.bake", text="Bake"' in ui     # the panel's **Bake** button


def test_readme_path_in_blender(tmp_path):
    # -- build the zip with `make extension`'s own command, into a temporary folder
    cmd = _extension_recipe()
    assert "make extension" in _readme()
    assert cmd[0] == "$(BIN)/python" and cmd[1] == "riray_addon/build_extension.py", cmd
    assert cmd[cmd.index("--out") + 1] == "dist"
    out = tmp_path / "dist"
    cmd = [sys.executable, cmd[1]] + cmd[2:]
    cmd[cmd.index("--out") + 1] = str(out)
    before = _checkout_listing()
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    created = _checkout_listing() - before
    assert not created, f"the build wrote into the checkout: {sorted(created)}"
    with open(ROOT / "blender_manifest.toml", "rb") as fh:
        version = tomllib.load(fh)["version"]
    zip_path = out / f"riray-{version}.zip"          # dist/riray-<version>.zip
    assert zip_path.is_file() and sorted(os.listdir(out)) == [zip_path.name]

    # -- Blender: install from disk, select, bake, render
    script = tmp_path / "readme_path.py"
    script.write_text(BLENDER_SCRIPT, encoding="utf-8")
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "blender_user"),
               RIRAY_WORKERS="1")
    res = subprocess.run([sys.executable, str(script), str(zip_path)], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=240)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-4000:]
    line = [x for x in res.stdout.splitlines() if x.startswith("RESULT ")]
    assert line, res.stdout[-4000:] + res.stderr[-4000:]
    got = json.loads(line[-1][len("RESULT "):])
    readme = _readme()
    assert got["panel"] == ["Bake RI-Tree", "object", "PROPERTIES"]
    assert got["engine"] == "RI-Tree Preview" and got["engine"] in readme
    assert got["bake_op"] == "Bake RI-Tree" and got["bake_op"] in readme
    st = got["stats"]
    # the object's pixels went through the baked tree: most interpolated, the rest traced
    assert st["mode"] == "tree" and st["tree"] == "fresh", st
    assert st["object_pixels"] > 50, st
    assert 0.0 <= st["traced_fraction"] < 0.9, st
    assert got["traced_pixels_in_pass"] == st["traced_pixels"]
    assert got["image_std"] > 0.02                     # a picture, not a flat frame
