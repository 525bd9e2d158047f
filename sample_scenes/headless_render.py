"""Headless riray workflow: open a .blend, bake the RI-Tree (when needed), render frames with
the "RI-Tree Preview" engine.

    python sample_scenes/headless_render.py FILE.blend [options]              (bpy module)
    blender -b FILE.blend --python-exit-code 1 --python sample_scenes/headless_render.py -- [options]

Options:
  --out PATH            output path prefix (default: //render/<scene>_ ; #### = frame number)
  --frames A-B | N      frames to render (default: the current frame); a range renders an
                        animation, written as PATH####.<ext>
  --percentage P        resolution percentage (default: the file's)
  --format PNG|OPEN_EXR image format (default PNG, view transform Standard)
  --object NAME         the specular object (default: scene.riray.target, set by build_blend)
  --camera NAME         render from this camera (default: the scene camera)
  --bake auto|always|never   bake when the tree is missing or stale (auto, the default),
                        always, or never; tree options: --viewpoint-depth, --direction-depth,
                        --tolerance (degrees)
  --save                save the .blend after baking (records the bake in the file)
  --zip PATH            extension zip to install when the add-on is not enabled (default:
                        dist/riray-*.zip, built on the fly from this checkout if missing)

With the bpy module the extension is installed into a private BLENDER_USER_RESOURCES folder
(a temporary one unless you set it), never into your Blender configuration. With a real Blender
the installed + enabled extension is used; if it is missing the zip is installed into the
user_default repository (as Blender's "Install from Disk" would).
"""

from __future__ import annotations

import argparse
import glob
import importlib
import os
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
EXT_MODULE = "bl_ext.user_default.riray"

_IN_BLENDER = "bpy" in sys.modules          # run by a real Blender (--python)
if not _IN_BLENDER and "BLENDER_USER_RESOURCES" not in os.environ:
    # must be set before bpy is imported: keeps the extension install private
    os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="riray_headless_")

import bpy  # noqa: E402


def script_args(argv: list[str]) -> list[str]:
    if "--" in argv:
        return argv[argv.index("--") + 1:]
    return [] if _IN_BLENDER else argv[1:]


def parse(argv):
    ap = argparse.ArgumentParser(description="Open a .blend, bake the RI-Tree, render frames.")
    if not _IN_BLENDER:
        ap.add_argument("blend", help=".blend file to open")
    ap.add_argument("--out", default="", help="output path prefix")
    ap.add_argument("--frames", default="", help="A-B or N (default: current frame)")
    ap.add_argument("--percentage", type=int, default=0)
    ap.add_argument("--format", default="PNG", choices=["PNG", "OPEN_EXR"])
    ap.add_argument("--object", default="")
    ap.add_argument("--camera", default="", help="camera object to render from")
    ap.add_argument("--bake", default="auto", choices=["auto", "always", "never"])
    ap.add_argument("--viewpoint-depth", type=int, default=0)
    ap.add_argument("--direction-depth", type=int, default=0)
    ap.add_argument("--tolerance", type=float, default=0.0)
    ap.add_argument("--save", action="store_true")
    ap.add_argument("--zip", default="")
    return ap.parse_args(argv)


# --------------------------------------------------------------------------- the add-on
def _find_zip(explicit: str) -> str:
    if explicit:
        return explicit
    found = sorted(glob.glob(os.path.join(ROOT, "dist", "riray-*.zip")))
    if found:
        return found[-1]
    spec = importlib.util.spec_from_file_location(
        "riray_build_extension", os.path.join(ROOT, "riray_addon", "build_extension.py"))
    build = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(build)
    out = tempfile.mkdtemp(prefix="riray_dist_")
    return str(build.build(build.Path(out), build.find_blender_ext(),
                           stage_dir=build.Path(out) / "stage"))


def ensure_addon(zip_path: str):
    """The enabled add-on package (bl_ext.user_default.riray.riray_addon)."""
    if not hasattr(bpy.types, "RIRAY_OT_bake"):
        try:
            bpy.ops.preferences.addon_enable(module=EXT_MODULE)
        except (RuntimeError, ModuleNotFoundError, ImportError):
            pass
    if not hasattr(bpy.types, "RIRAY_OT_bake"):
        path = _find_zip(zip_path)
        print(f"riray: installing {path}")
        res = bpy.ops.extensions.package_install_files(filepath=path, repo="user_default",
                                                       enable_on_install=True)
        if res != {"FINISHED"} or not hasattr(bpy.types, "RIRAY_OT_bake"):
            raise SystemExit(f"riray: could not install / enable the extension from {path}")
    return importlib.import_module(f"{EXT_MODULE}.riray_addon")


# --------------------------------------------------------------------------- workflow
def frames_of(spec: str, scene) -> list[int]:
    if not spec:
        return [scene.frame_current]
    if "-" in spec:
        a, b = spec.split("-", 1)
        return list(range(int(a), int(b) + 1))
    return [int(spec)]


def run(args) -> int:
    addon = ensure_addon(args.zip)
    cache = importlib.import_module(f"{addon.__name__}.cache")
    engine = importlib.import_module(f"{addon.__name__}.engine")
    if not _IN_BLENDER:
        bpy.ops.wm.open_mainfile(filepath=os.path.abspath(args.blend))
    scene = bpy.context.scene
    obj = bpy.data.objects.get(args.object) if args.object else scene.riray.target
    if obj is None:
        raise SystemExit("riray: no object: pass --object NAME or set the RI-Tree object "
                         "(scene.riray.target)")
    scene.riray.target = obj

    # -- bake
    status = cache.tree_status(obj, bpy.context.evaluated_depsgraph_get(), memo=False)
    print(f"riray: {obj.name}: {status['message']}")
    if args.bake == "always" or (args.bake == "auto" and status["state"] != "fresh"):
        opts = {}
        if args.viewpoint_depth:
            opts["viewpoint_depth"] = args.viewpoint_depth
        if args.direction_depth:
            opts["direction_depth"] = args.direction_depth
        if args.tolerance:
            opts["tolerance_deg"] = args.tolerance
        t0 = time.time()
        res = bpy.ops.riray.bake(object=obj.name, wait=True, **opts)
        if res != {"FINISHED"}:
            raise SystemExit("riray: the bake did not finish")
        print(f"riray: baked in {time.time() - t0:.1f} s -> {cache.cache_path(obj)}")
        if args.save:
            bpy.ops.wm.save_mainfile()

    # -- render
    if args.camera:
        cam = bpy.data.objects.get(args.camera)
        if cam is None or cam.type != "CAMERA":
            raise SystemExit(f"riray: no camera named {args.camera!r}")
        scene.camera = cam
    scene.render.engine = "RIRAY"
    scene.view_settings.view_transform = "Standard"
    scene.render.image_settings.file_format = args.format
    if args.percentage:
        scene.render.resolution_percentage = args.percentage
    scene.render.filepath = args.out or f"//render/{bpy.path.clean_name(scene.name)}_"
    frames = frames_of(args.frames, scene)
    t0 = time.time()
    if len(frames) > 1:
        scene.frame_start, scene.frame_end = frames[0], frames[-1]
        bpy.ops.render.render(animation=True)
        written = [scene.render.frame_path(frame=f) for f in frames]
    else:
        scene.frame_set(frames[0])
        path = scene.render.frame_path(frame=frames[0])
        scene.render.filepath = path
        bpy.ops.render.render(write_still=True)
        written = [path]
    st = engine.LAST_RENDER.get("stats", {})
    print(f"riray: rendered {len(frames)} frame(s) in {time.time() - t0:.1f} s; last frame: "
          f"traced {100 * st.get('traced_fraction', 0):.1f}% of {st.get('object_pixels', 0)} "
          f"object pixels ({st.get('mode', '?')})")
    for p in written:
        print(f"riray: wrote {p}")
    return 0


def main(argv=None) -> int:
    return run(parse(script_args(sys.argv) if argv is None else argv))


if __name__ == "__main__":
    code = main()
    if not _IN_BLENDER:
        sys.exit(code)
