"""A scene as a new Blender user makes it, rendered by Cycles and by the "RI-Tree Preview"
engine (the bpy module; benchmark output, not a test).

    python sample_scenes/factory_bench.py [--size 320x240] [--spp 256] [--samples 4]
        [--workers 2] [--out bench_out/factory]

The scene: a NURBS sphere (radius 1 m) with a glass Principled BSDF (Transmission 1,
Roughness 0) on a 12 m floor plane with a Checker Texture (Principled, default coordinates),
a metallic torus beside it (Principled, Metallic 1, the default Roughness 0.5), a world
colour (Background, strength 1), one square Area light (1.5 m, 150 W) and a camera looking
at them. Nothing riray-specific is set but the engine and the specular object.

Cycles renders it at ``--spp`` samples (CPU, ``--workers`` threads, fixed seed, no adaptive
sampling, no denoising, its default light paths and 1.5 px filter); riray renders it with the
add-on's engine at ``--samples`` camera rays per pixel, tracing the object exactly (no tree is
baked). Both are written as linear EXR and compared as display-range linear RGB (PSNR, mean
value). Writes OUT/cycles.png, OUT/riray.png, OUT/side_by_side.png and OUT/factory.json.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import os
import platform
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import headless_render  # noqa: E402  (sets a private BLENDER_USER_RESOURCES before bpy)

import blender_bench  # noqa: E402
import bpy  # noqa: E402
import build_blend  # noqa: E402
import numpy as np  # noqa: E402

from riray.imageio import write_png  # noqa: E402
from riray.render.interpolated import psnr  # noqa: E402

SEED = 1
WORLD_COLOR = (0.42, 0.52, 0.70)
LIGHT_POWER_W = 150.0
LIGHT_SIZE_M = 1.5
LIGHT_AT = (1.5, -2.0, 4.0)
CAMERA_AT = (7.5, -6.5, 4.2)
LOOK_AT = (0.6, 0.2, 0.7)
GAP_PX = 8                       # between the two pictures of side_by_side.png


def _principled(name: str, **inputs):
    mat = build_blend.compat.new_material(name)
    node = next(n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
    for key, value in inputs.items():
        node.inputs[key].default_value = value
    return mat, node


def _look(obj, target) -> None:
    from mathutils import Vector
    d = Vector(target) - obj.location
    obj.rotation_euler = d.to_track_quat("-Z", "Y").to_euler()


def build_factory_scene(width: int, height: int):
    """The scene above in an empty file; returns the glass sphere."""
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    bpy.ops.mesh.primitive_plane_add(size=12.0, location=(0.0, 0.0, 0.0))
    floor = bpy.context.active_object
    mat, node = _principled("floor")
    checker = mat.node_tree.nodes.new("ShaderNodeTexChecker")
    mat.node_tree.links.new(checker.outputs["Color"], node.inputs["Base Color"])
    floor.data.materials.append(mat)

    bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=1.0, location=(0.0, 0.0, 1.0))
    sphere = bpy.context.active_object
    sphere.name = "glass_sphere"
    mat, _ = _principled("glass", **{"Transmission Weight": 1.0, "Roughness": 0.0})
    sphere.data.materials.append(mat)

    bpy.ops.mesh.primitive_torus_add(major_radius=0.7, minor_radius=0.25,
                                     location=(1.2, 1.9, 0.25))
    torus = bpy.context.active_object
    bpy.ops.object.shade_smooth()
    mat, _ = _principled("metal", **{"Base Color": (0.9, 0.75, 0.5, 1.0), "Metallic": 1.0})
    torus.data.materials.append(mat)

    world = build_blend.compat.new_world("world")
    bg = next(n for n in world.node_tree.nodes if n.type == "BACKGROUND")
    bg.inputs["Color"].default_value = (*WORLD_COLOR, 1.0)
    bg.inputs["Strength"].default_value = 1.0
    scene.world = world

    light = bpy.data.lights.new("area", "AREA")
    light.energy, light.size = LIGHT_POWER_W, LIGHT_SIZE_M
    lobj = bpy.data.objects.new("area", light)
    scene.collection.objects.link(lobj)
    lobj.location = LIGHT_AT
    _look(lobj, (0.5, 0.5, 0.0))

    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    scene.collection.objects.link(cam)
    cam.location = CAMERA_AT
    _look(cam, LOOK_AT)
    scene.camera = cam
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = width, height, 100
    scene.view_settings.view_transform = "Standard"
    return sphere


def render_cycles(scene, spp: int, threads: int, path: Path):
    scene.render.engine = "CYCLES"
    c = scene.cycles
    c.device, c.samples, c.seed = "CPU", spp, SEED
    c.use_adaptive_sampling = c.use_denoising = False
    scene.render.threads_mode, scene.render.threads = "FIXED", threads
    return blender_bench.render_to_array(scene, path)


def render_riray(scene, sphere, samples: int, workers: int, path: Path, engine_mod):
    scene.render.engine = "RIRAY"
    scene.riray.target = sphere
    scene.riray.samples = samples
    scene.riray.render_processes = workers
    img, wall = blender_bench.render_to_array(scene, path)
    return img, wall, dict(engine_mod.LAST_RENDER.get("stats", {}))


def side_by_side(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    gap = np.ones((a.shape[0], GAP_PX, 3))
    return np.concatenate([a, gap, b], axis=1)


def fresh_zip() -> str:
    """The extension zip built from this checkout now (never a stale dist/ zip)."""
    spec = importlib.util.spec_from_file_location(
        "riray_build_extension", HERE.parent / "riray_addon" / "build_extension.py")
    build = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(build)
    out = Path(tempfile.mkdtemp(prefix="riray_dist_"))
    return str(build.build(out, build.find_blender_ext(), stage_dir=out / "stage"))


def run(args, w: int, h: int) -> dict:
    addon = headless_render.ensure_addon(args.zip or fresh_zip())
    engine_mod = importlib.import_module(f"{addon.__name__}.engine")
    sphere = build_factory_scene(w, h)
    scene = bpy.context.scene
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="riray_factory_") as tmp:
        cyc, cyc_s = render_cycles(scene, args.spp, args.workers, Path(tmp) / "cycles.exr")
        rir, rir_s, stats = render_riray(scene, sphere, args.samples, args.workers,
                                         Path(tmp) / "riray.exr", engine_mod)
    write_png(out / "cycles.png", cyc)
    write_png(out / "riray.png", rir)
    write_png(out / "side_by_side.png", side_by_side(rir, cyc))
    mean = lambda img: float(np.clip(img, 0, 1).mean())
    return {"size": [w, h], "cycles_spp": args.spp, "riray_samples": args.samples,
            "psnr_db": psnr(rir, cyc), "cycles_s": cyc_s, "riray_s": rir_s,
            "mean_cycles": mean(cyc), "mean_riray": mean(rir),
            "riray_stats": {k: v for k, v in stats.items()
                            if isinstance(v, (int, float, str, bool))},
            "blender": bpy.app.version_string,
            "machine": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count()}


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, got {text!r}") from None
    if not (1 <= w <= 8192 and 1 <= h <= 8192):
        raise argparse.ArgumentTypeError(f"sides must be 1..8192, got {text!r}")
    return w, h


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=parse_size, default=(320, 240), help="WIDTHxHEIGHT")
    ap.add_argument("--spp", type=int, default=256, choices=range(1, 65537), metavar="N",
                    help="Cycles samples per pixel")
    ap.add_argument("--samples", type=int, default=4, choices=range(1, 4097), metavar="N",
                    help="riray camera rays per pixel")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                    choices=range(1, 257), metavar="N")
    ap.add_argument("--out", default="bench_out/factory")
    ap.add_argument("--zip", default="", help="extension zip (default: built from this checkout)")
    args = ap.parse_args(headless_render.script_args(sys.argv) if argv is None else argv)
    w, h = args.size
    res = run(args, w, h)
    out = Path(args.out)
    (out / "factory.json").write_text(json.dumps(res, indent=1) + "\n")
    print(f"factory scene {w} x {h}: riray {args.samples} samples/px {res['riray_s']:.2f} s, "
          f"Cycles {args.spp} spp {res['cycles_s']:.2f} s; PSNR {res['psnr_db']:.2f} dB; "
          f"mean {255 * res['mean_riray']:.0f}/255 (Cycles {255 * res['mean_cycles']:.0f}/255)")
    print(f"wrote {out / 'side_by_side.png'}, cycles.png, riray.png, factory.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
