"""The ``riray`` command line: thin sub-commands that parse, call the engine and report."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from . import __version__


def _progress(label):
    """A progress callback printing a one-line bar with ETA to stderr."""
    start = time.perf_counter()

    def report(frac):
        el = time.perf_counter() - start
        eta = el / frac - el if frac > 0 else 0.0
        print(f"\r{label}: {100 * frac:5.1f}%  elapsed {el:6.1f}s  eta {eta:6.1f}s",
              end="" if frac < 1 else "\n", file=sys.stderr, flush=True)
    return report


def _load(path):
    from .scene.io import load_scene
    from .scene.samples import SAMPLES, build
    if path in SAMPLES and not Path(path).exists():
        return build(path)
    return load_scene(path)


def cmd_render(args):
    from .render.exact import render_exact, save_render
    scene = _load(args.scene)
    res = render_exact(scene, camera=args.camera, width=args.width, height=args.height,
                       workers=args.workers, progress=None if args.quiet else _progress("render"))
    paths = save_render(res, args.out)
    print(json.dumps({"written": [str(p) for p in paths], **res.stats["summary"]}, indent=2))
    return 0


def cmd_trace_rays(args):
    from .render.exact import SceneTracer
    scene = _load(args.scene)
    rays = np.load(args.rays)
    if rays.ndim != 2 or rays.shape[1] != 6 or not np.all(np.isfinite(rays)):
        raise SystemExit(f"{args.rays}: expected a finite N x 6 array (origin, direction), "
                         f"got shape {rays.shape}")
    d = rays[:, 3:]
    ln = np.linalg.norm(d, axis=1)
    if np.any(ln == 0):
        raise SystemExit(f"{args.rays}: direction of row {int(np.argmin(ln))} is zero")
    st = SceneTracer(scene)
    out = st.object_function(rays[:, :3], d / ln[:, None])
    np.savez_compressed(args.out, **{k: v for k, v in out.__dict__.items()})
    print(f"{args.out}: {len(rays)} rays, {int(out.hit.sum())} hit the object, "
          f"{int(out.null.sum())} null")
    return 0


def cmd_validate(args):
    from .scene.io import load_scene
    scene = load_scene(args.scene)
    print(f"{args.scene}: ok — {len(scene.object.patches)} patches, {len(scene.meshes)} meshes, "
          f"{len(scene.lights)} lights, cameras {[c.name for c in scene.cameras]}")
    return 0


def cmd_demo(args):
    from .render.exact import render_exact, save_render
    from .scene.samples import build
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = build(args.scene)
    res = render_exact(scene, camera=args.camera, width=args.size, height=args.size,
                       workers=args.workers, progress=_progress(f"exact render of {args.scene}"))
    paths = save_render(res, out / "exact")
    print(f"demo: {args.scene} / camera {args.camera} at {args.size}x{args.size}")
    for p in paths:
        print(f"  wrote {p}")
    print(json.dumps(res.stats["summary"], indent=2))
    print(f"demo output folder: {out.resolve()}")
    return 0


def build_parser():
    ap = argparse.ArgumentParser(prog="riray", description=__doc__)
    ap.add_argument("--version", action="version", version=f"riray {__version__}")
    sub = ap.add_subparsers(dest="cmd", required=True)

    def scene_arg(p):
        p.add_argument("scene", help="scene file (.json) or a sample name (teapot, vase_glass, ...)")

    p = sub.add_parser("render", help="render a camera's view exactly")
    scene_arg(p)
    p.add_argument("--out", required=True, help="output path stem: writes STEM.png, STEM.npy, "
                   "STEM.json (a trailing .png is stripped)")
    p.add_argument("--camera", default=None, help="camera name (default: the first)")
    p.add_argument("--width", type=int, default=None, help="pixels (default: the scene's)")
    p.add_argument("--height", type=int, default=None, help="pixels (default: the scene's)")
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(fn=cmd_render)

    p = sub.add_parser("trace-rays", help="apply the object function f to a batch of rays",
                       description="Input: an N x 6 float64 .npy (origin xyz, direction xyz). "
                       "Output .npz arrays: hit, null, out_origin, out_dir, t_first, point, "
                       "normal, patch, cls, events, refl_dir, fresnel (see docs/cli.md).")
    scene_arg(p)
    p.add_argument("--rays", required=True)
    p.add_argument("--out", required=True)
    p.set_defaults(fn=cmd_trace_rays)

    p = sub.add_parser("validate", help="load and validate a scene file")
    p.add_argument("scene")
    p.set_defaults(fn=cmd_validate)

    p = sub.add_parser("demo", help="render a bundled sample scene into a folder")
    p.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    p.add_argument("--scene", default="glass_sphere", help="sample scene name")
    p.add_argument("--camera", default="close")
    p.add_argument("--size", type=int, default=300)
    p.add_argument("--workers", type=int, default=None)
    p.set_defaults(fn=cmd_demo)
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.fn(args)
    except (ValueError, OSError) as e:
        print(f"riray {args.cmd}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
