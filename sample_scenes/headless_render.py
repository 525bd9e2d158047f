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
                        always, or never; tree options: --quality draft|fast|default (the
                        add-on's presets, riray bake's), then --viewpoint-depth, --direction-depth,
                        --tolerance (degrees) override the preset's values
  --save                save the .blend after baking (records the bake in the file)
  --zip PATH            extension zip to install when the add-on is not enabled (default:
                        dist/riray-*.zip, built on the fly from this checkout if missing)

With the bpy module the extension is installed into a private BLENDER_USER_RESOURCES folder
(a temporary one unless you set it), never into your Blender configuration. With a real Blender
the installed + enabled extension is used; if it is missing the zip is installed into the
user_default repository (as Blender's "Install from Disk" would).

Bad input (a missing file, a frame range or option value out of range, bake settings the
add-on refuses) is one line on stderr and exit status 2, checked before any slow work; a bake
or render that fails is one line and exit status 1.
"""

from __future__ import annotations

import argparse
import glob
import importlib
import importlib.util
import os
import re
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


class UsageError(Exception):
    """Bad input: one line on stderr, exit status 2."""


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
    ap.add_argument("--quality", default="", choices=["draft", "fast", "default"])
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


def _installed() -> bool:
    try:
        return importlib.util.find_spec(EXT_MODULE) is not None
    except ModuleNotFoundError:
        return False


def ensure_addon(zip_path: str):
    """The enabled add-on package (bl_ext.user_default.riray.riray_addon)."""
    if not hasattr(bpy.types, "RIRAY_OT_bake") and _installed():
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
def parse_frames(spec: str) -> list[int] | None:
    """``N`` or ``A-B`` (A <= B, within Blender's frame range) as a list; None for ''."""
    if not spec:
        return None
    m = re.fullmatch(r"(-?\d+)(?:-(-?\d+))?", spec.strip())
    if m is None:
        raise UsageError(f"--frames {spec!r}: expected a frame N or a range A-B, e.g. 1-24")
    a = int(m[1])
    b = a if m[2] is None else int(m[2])
    if b < a:
        raise UsageError(f"--frames {spec}: the range ends ({b}) before it starts ({a})")
    rna = bpy.types.Scene.bl_rna.properties["frame_start"]
    if a < rna.hard_min or b > rna.hard_max:
        raise UsageError(f"--frames {spec}: frames must be in {rna.hard_min}..{rna.hard_max}")
    return list(range(a, b + 1))


def check_range(flag: str, value, rna) -> None:
    """UsageError unless ``value`` lies in the hard range of the RNA property ``rna``."""
    if not rna.hard_min <= value <= rna.hard_max:
        raise UsageError(f"{flag} {value:g}: must be in {rna.hard_min:g}..{rna.hard_max:g}")


def run(args) -> int:
    frames = parse_frames(args.frames)
    if not _IN_BLENDER and not os.path.isfile(args.blend):
        raise UsageError(f"{args.blend}: no such file")
    if args.percentage:
        check_range("--percentage", args.percentage,
                    bpy.types.RenderSettings.bl_rna.properties["resolution_percentage"])
    addon = ensure_addon(args.zip)
    cache = importlib.import_module(f"{addon.__name__}.cache")
    engine = importlib.import_module(f"{addon.__name__}.engine")
    operators = importlib.import_module(f"{addon.__name__}.operators")
    properties = importlib.import_module(f"{addon.__name__}.properties")
    opts = {"viewpoint_depth": args.viewpoint_depth, "direction_depth": args.direction_depth,
            "tolerance_deg": args.tolerance}
    opts = {k: v for k, v in opts.items() if v}
    props = properties.RIRAY_PG_object.bl_rna.properties
    for key, value in opts.items():
        check_range(f"--{key.replace('_deg', '').replace('_', '-')}", value, props[key])
    if not _IN_BLENDER:
        try:
            bpy.ops.wm.open_mainfile(filepath=os.path.abspath(args.blend))
        except RuntimeError as exc:
            raise UsageError(f"{args.blend}: cannot open: {str(exc).splitlines()[0]}") from None
    scene = bpy.context.scene
    obj = bpy.data.objects.get(args.object) if args.object else scene.riray.target
    if obj is None:
        raise UsageError("no object: pass --object NAME or set the RI-Tree object "
                         "(scene.riray.target)")
    cam = None
    if args.camera:
        cam = bpy.data.objects.get(args.camera)
        if cam is None or cam.type != "CAMERA":
            raise UsageError(f"--camera: no camera named {args.camera!r}")
    scene.riray.target = obj

    # -- bake
    status = cache.tree_status(obj, bpy.context.evaluated_depsgraph_get(), memo=False)
    print(f"riray: {obj.name}: {status['message']}")
    if args.bake == "always" or (args.bake == "auto" and status["state"] != "fresh"):
        if args.quality:
            obj.riray.quality = args.quality.upper()
        for key, value in opts.items():
            setattr(obj.riray, key, value)
        try:
            operators.checked_params(obj)
        except ValueError as exc:          # the add-on's ExportError
            raise UsageError(str(exc)) from None
        t0 = time.time()
        try:
            res = bpy.ops.riray.bake(object=obj.name, wait=True)
        except RuntimeError as exc:
            raise SystemExit(f"riray: {str(exc).splitlines()[0]}") from None
        if res != {"FINISHED"}:
            raise SystemExit("riray: the bake did not finish")
        print(f"riray: baked in {time.time() - t0:.1f} s -> {cache.cache_path(obj)}")
        if args.save:
            bpy.ops.wm.save_mainfile()

    # -- render
    if cam is not None:
        scene.camera = cam
    scene.render.engine = "RIRAY"
    scene.view_settings.view_transform = "Standard"
    scene.render.image_settings.file_format = args.format
    if args.percentage:
        scene.render.resolution_percentage = args.percentage
    scene.render.filepath = args.out or f"//render/{bpy.path.clean_name(scene.name)}_"
    frames = frames or [scene.frame_current]
    t0 = time.time()
    try:
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
    except RuntimeError as exc:
        raise SystemExit(f"riray: render failed: {str(exc).splitlines()[0]}") from None
    st = engine.LAST_RENDER.get("stats", {})
    print(f"riray: rendered {len(frames)} frame(s) in {time.time() - t0:.1f} s; last frame: "
          f"traced {100 * st.get('traced_fraction', 0):.1f}% of {st.get('object_pixels', 0)} "
          f"object pixels ({st.get('mode', '?')})")
    for p in written:
        print(f"riray: wrote {p}")
    return 0


def main(argv=None) -> int:
    try:
        return run(parse(script_args(sys.argv) if argv is None else argv))
    except UsageError as exc:
        print(f"headless_render.py: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    code = main()
    if code or not _IN_BLENDER:
        sys.exit(code)
