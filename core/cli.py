"""The ``riray`` command line: thin sub-commands that parse, call the engine and report."""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from . import __version__
from .files import atomic_write, command_output, open_regular


_BAR = {"open": False}    # a progress bar is mid-line on stderr (an error message starts anew)


def _progress(label):
    """A progress callback printing a one-line bar with ETA to stderr."""
    start = time.perf_counter()

    def report(frac):
        el = time.perf_counter() - start
        eta = el / frac - el if frac > 0 else 0.0
        print(f"\r{label}: {100 * frac:5.1f}%  elapsed {el:6.1f}s  eta {eta:6.1f}s",
              end="" if frac < 1 else "\n", file=sys.stderr, flush=True)
        _BAR["open"] = frac < 1
    return report


def _load(path):
    from .scene.io import load_scene
    from .scene.samples import SAMPLES, build
    if path in SAMPLES and not Path(path).exists():
        return build(path)
    return load_scene(path)


def _query_options(args):
    from .ritree.query import QueryOptions
    return QueryOptions(policy=args.policy, extrapolation=args.extrapolation,
                        angle_deg=None if args.angle < 0 else args.angle,
                        distance=None if args.distance < 0 else args.distance,
                        threshold_on=args.threshold_on,
                        threshold_leaves=args.threshold_leaves,
                        null_interp=args.null_rays == "interpolate",
                        max_error_deg=None if args.max_error < 0 else args.max_error,
                        path_identity=args.path_identity,
                        mirror_rays=args.mirror_rays).validate()


def _tree_opts(p):
    from .ritree.query import DEFAULT_MAX_ERROR_DEG, MIRROR_RAYS, QueryOptions
    p.add_argument("--policy", choices=("ri", "raytree"), default="ri",
                   help="ri: the paper's heuristics; raytree: Bala et al.'s identical-ray-tree rule")
    p.add_argument("--extrapolation", type=float, default=None, metavar="T",
                   help="allow extrapolation up to barycentric distance T (default: off)")
    p.add_argument("--angle", type=float, default=-1.0, metavar="DEG",
                   help="the paper's pairwise angle threshold between interpolants in degrees "
                   "(-1: off, the default; the paper used 20)")
    p.add_argument("--distance", type=float, default=-1.0, metavar="REL",
                   help="pairwise output-origin distance threshold, relative to the object's "
                   "box diagonal (-1: off, the default)")
    p.add_argument("--threshold-on", choices=("samples", "intermediate"), default="samples",
                   help="apply the thresholds among all interpolated samples (the paper, the "
                   "default) or among the four viewpoints' intermediate rays")
    p.add_argument("--threshold-leaves", choices=("all", "unverified"), default="all",
                   help="with --threshold-on samples: compare the samples of all direction "
                   "leaves (the default) or only of leaves at the maximum depth (a shallower "
                   "leaf passed the bake's midpoint test; fewer mirror rays traced)")
    p.add_argument("--max-error", type=float, default=DEFAULT_MAX_ERROR_DEG, metavar="DEG",
                   help="interpolate a ray only where the errors the bake measured in everything "
                   "it blends (its four direction leaves and its viewpoint cell) are at most DEG "
                   f"degrees; trace the others (default {DEFAULT_MAX_ERROR_DEG:g}; -1: off; no "
                   "re-bake needed)")
    p.add_argument("--path-identity", action="store_true",
                   help="trace a ray whose usable samples differ in ray-tree hash (event "
                   "sequence) or whose leaves / viewpoint cell the bake saw change path")
    p.add_argument("--null-rays", choices=("interpolate", "trace"), default="trace",
                   help="a ray whose interpolants are all null (trapped) is traced (trace, the "
                   "default and the paper) or answered null (interpolate: faster, but a "
                   "trapped region can hide an exit no sample shows)")
    p.add_argument("--mirror-rays", choices=MIRROR_RAYS, default=QueryOptions.mirror_rays,
                   help="mirrors, policy ri: a ray whose usable samples all reflect once leaves "
                   "from the exact hit Newton finds on their patch from the interpolated patch "
                   "parameters, along the query direction reflected about its normal (newton, "
                   "the default, where those samples share one NURBS patch; else reflect); "
                   "from the interpolated hit, reflected about the interpolated normal "
                   "(reflect); or along the interpolated output ray (interpolate, the paper)")


def _bake_opts(p):
    from .ritree.tree import BakeParams
    d = BakeParams()
    p.add_argument("--viewpoint-depth", type=int, default=d.viewpoint_depth,
                   help=f"uniform viewpoint-tree depth (default {d.viewpoint_depth})")
    p.add_argument("--direction-depth", type=int, default=d.direction_depth,
                   help=f"maximum direction-tree depth (default {d.direction_depth})")
    p.add_argument("--viewpoint-refine", type=int, default=d.viewpoint_refine,
                   help="extra viewpoint levels where the cameras' rays lack interpolants "
                   f"(default {d.viewpoint_refine}; camera-region bakes only)")
    p.add_argument("--min-direction-depth", type=int, default=d.min_direction_depth,
                   help=f"direction trees split at least this deep (default {d.min_direction_depth})")
    p.add_argument("--tolerance", type=float, default=d.tolerance_deg, metavar="DEG",
                   help="bake angular tolerance (degrees)")
    p.add_argument("--tolerance-dist", type=float, default=d.tolerance_dist, metavar="REL",
                   help="bake distance tolerance, relative to the object's box diagonal")
    p.add_argument("--viewpoint-tolerance", type=float, default=d.viewpoint_tolerance_deg,
                   metavar="DEG", help="split viewpoint cells whose camera test rays, answered "
                   "through the tree, miss the exact ones by more than this (degrees; default "
                   f"{d.viewpoint_tolerance_deg}; camera-region bakes only)")
    p.add_argument("--finest-min-traced", type=int, default=d.finest_min_traced, metavar="N",
                   help="split cells to the finest viewpoint level only where at least N of the "
                   "cameras' rays would be traced at the 2-degree tolerance (default "
                   f"{d.finest_min_traced}: by the rule of the other levels; camera-region "
                   "bakes only)")
    p.add_argument("--search-steps", type=int, default=d.search_steps,
                   help="binary-search steps for the extra samples of two-class cells "
                   f"(default {d.search_steps})")
    p.add_argument("--full", action="store_true",
                   help="bake every viewpoint cell (default: only what the cameras need)")
    p.add_argument("--cameras", default=None,
                   help="comma-separated camera names to bake for (default: all)")


def _bake_params(args):
    from .ritree.tree import BakeParams
    return BakeParams(
        viewpoint_depth=args.viewpoint_depth, direction_depth=args.direction_depth,
        viewpoint_refine=args.viewpoint_refine,
        min_direction_depth=args.min_direction_depth, tolerance_deg=args.tolerance,
        tolerance_dist=args.tolerance_dist, viewpoint_tolerance_deg=args.viewpoint_tolerance,
        finest_min_traced=args.finest_min_traced, search_steps=args.search_steps).validate()


def _check_writable(path, folder=False):
    """ValueError unless ``path`` can be written: a file in an existing folder that takes new
    files, or (``folder``) a folder that exists or can be made. Checked before the slow work."""
    p = Path(path).absolute()
    if folder:
        probe = p
        while not probe.exists():              # the writer makes the missing folders
            probe = probe.parent
        if not probe.is_dir():
            raise ValueError(f"{path}: {probe} is a file, not a folder")
    else:
        if p.is_dir():
            raise ValueError(f"{path}: is a folder")
        probe = p.parent
        if not probe.is_dir():
            raise ValueError(f"{path}: {probe} is a file, not a folder" if probe.exists()
                             else f"{path}: the folder {probe} does not exist")
    try:
        with tempfile.TemporaryFile(dir=probe):
            pass
    except OSError as e:
        raise ValueError(f"{path}: cannot write in {probe} ({e.strerror})") from None


def _bake(scene, args, params, out, st, cluster=None):
    from .ritree import tree as ritree
    from .ritree.bake import bake
    from .ritree.region import region_for_cameras
    region = None
    if not args.full:
        names = args.cameras.split(",") if args.cameras else [c.name for c in scene.cameras]
        cams = [scene.camera(n) for n in names]
        region = region_for_cameras(st, params, cams, scene.render.width, scene.render.height)
        for name in region.unseen:
            _warn(args.cmd, f"camera {name!r} does not see the object {scene.object.name!r}; "
                  "the tree is baked for the other cameras")
    bar = _progress("bake")
    tree = bake(st, params, region, progress=lambda f, msg: bar(f), workers=args.workers,
                cluster=cluster)
    ritree.save(tree, out, progress=_progress("save (compressing)"))
    return tree


def _load_tree(args, scene):
    """The RI-Tree of ``args.tree`` for ``scene``; a tree without samples (its cameras saw
    nothing of the object) is used with a warning: every ray it meets is traced."""
    from .ritree import tree as ritree
    tree = ritree.load(args.tree, scene)
    if len(tree.samples) == 0:
        _warn(args.cmd, f"{args.tree}: the RI-Tree holds no samples; every ray is traced exactly")
    return tree


def _connect(spec):
    """The Dask cluster of ``--scheduler`` (before the slow work); its address and dashboard on
    stderr."""
    from .cluster import connect
    cluster = connect(spec)
    dash = cluster.dashboard
    print(f"dask: scheduler {cluster.address}, {cluster.threads()} worker threads"
          + (f", dashboard {dash}" if dash else ""), file=sys.stderr, flush=True)
    return cluster


def cmd_bake(args):
    from .trace.scene_tracer import SceneTracer
    params = _bake_params(args)
    _check_writable(args.out)
    cluster = _connect(args.scheduler) if args.scheduler else None
    try:
        scene = _load(args.scene)
        st = SceneTracer(scene)
        with command_output():
            tree = _bake(scene, args, params, args.out, st, cluster)
    finally:
        if cluster is not None:
            cluster.close()
    print(json.dumps({"written": args.out, **tree.meta}, indent=2))
    return 0


def cmd_info(args):
    from .ritree.cache import describe
    info = describe(args.tree)
    print(json.dumps(info, indent=2, default=str))
    return 0


def cmd_render(args):
    from .render.exact import render_exact, save_render
    from .scene.camera import Shot
    from .trace.scene_tracer import SceneTracer
    options = _query_options(args) if args.tree else None
    _check_writable(args.out if args.tree else Path(args.out).parent, folder=True)
    scene = _load(args.scene)
    shot = Shot(args.camera, args.width, args.height, args.samples)
    progress = None if args.quiet else _progress("render")
    if args.tree:
        from .render.interpolated import render_tree, save_tree_render
        tree = _load_tree(args, scene)
        res = render_tree(SceneTracer(scene), tree, shot, options=options,
                          reference=not args.no_reference, workers=args.workers,
                          progress=progress)
        with command_output():
            paths = save_tree_render(res, args.out)
        print(json.dumps({"written": [str(p) for p in paths], **res.stats["summary"]}, indent=2))
        return 0
    t0 = time.perf_counter()
    st = SceneTracer(scene)
    build_s = time.perf_counter() - t0
    res = render_exact(st, shot, workers=args.workers, progress=progress)
    res.stats["summary"]["build_s"] = round(build_s, 4)
    with command_output():
        paths = save_render(res, args.out)
    print(json.dumps({"written": [str(p) for p in paths], **res.stats["summary"]}, indent=2))
    return 0


RAY_CHUNK = 8192   # rays per trace-rays work chunk (progress granularity, memory bound)


def _check_npy_header(path):
    """ValueError unless the .npy file's header says N x 6 numeric and the file holds that much
    data: checked before any data is read (a truncated file or a header claiming more rows than
    the file holds is an error, not an allocation)."""
    fmt = np.lib.format
    with open_regular(path) as f:
        if f.read(4) == b"PK\x03\x04":
            raise ValueError(f"{path}: expected a .npy file holding one array (got an .npz "
                             "archive)")
        f.seek(0)
        try:
            version = fmt.read_magic(f)
            read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
            shape, _, dtype = read(f)
        except (ValueError, EOFError) as e:
            raise ValueError(f"{path}: not a .npy array file ({e})") from None
        data = os.fstat(f.fileno()).st_size - f.tell()
    if dtype.kind not in "fiu":
        raise ValueError(f"{path}: expected a numeric N x 6 array (got dtype {dtype})")
    if len(shape) != 2 or shape[1] != 6:
        raise ValueError(f"{path}: expected an N x 6 array (origin xyz, direction xyz), "
                         f"got shape {shape}")
    if data < shape[0] * 6 * dtype.itemsize:
        raise ValueError(f"{path}: truncated: the header says {shape[0]} rows "
                         f"({shape[0] * 6 * dtype.itemsize} bytes), the file holds {data} bytes")


def _load_rays(path):
    """(origins, unit directions) from an N x 6 .npy file; ValueError (one line) unless every
    row is finite, with an origin in the scene format's coordinate range and a non-zero
    direction (of any finite size: normalized without overflow)."""
    from .scene.io import MAX_COORD
    _check_npy_header(path)
    rays = np.load(path, allow_pickle=False).astype(np.float64)
    bad = ~np.isfinite(rays)
    if bad.any():
        i, j = (int(x) for x in np.argwhere(bad)[0])
        raise ValueError(f"{path}: row {i} column {j} is not finite ({rays[i, j]!r})")
    far = np.abs(rays[:, :3]) > MAX_COORD
    if far.any():
        i, j = (int(x) for x in np.argwhere(far)[0])
        raise ValueError(f"{path}: row {i} column {j}: origin coordinate {float(rays[i, j])!r} is "
                         f"outside the supported range +-{MAX_COORD:g} m")
    d = rays[:, 3:]
    big = np.abs(d).max(axis=1)
    zero = ~(big > 0)
    if zero.any():
        raise ValueError(f"{path}: direction of row {int(np.argmax(zero))} is zero")
    d = d / big[:, None]                    # largest component 1: the norm cannot overflow
    return rays[:, :3], d / np.linalg.norm(d, axis=1)[:, None]


def cmd_trace_rays(args):
    from .trace.scene_tracer import SceneTracer
    if args.inside and args.tree:
        raise ValueError("--inside cannot be combined with --tree (the RI-Tree answers rays "
                         "that enter the object from outside)")
    options = _query_options(args) if args.tree else None
    out_path = args.out if args.out.endswith(".npz") else args.out + ".npz"
    _check_writable(out_path)
    scene = _load(args.scene)
    o, u = _load_rays(args.rays)
    st = SceneTracer(scene)
    extra = {}
    if args.tree:
        from .ritree.query import TreeQuery
        tq = TreeQuery(_load_tree(args, scene), st, options)
        out, answers, why, _ = tq(o, u)
        extra = {"answer": answers, "traced_because": why}
    else:
        from .parallel import map_chunks
        from .trace.objectfn import ObjectRays, trace_object

        def f(a, b):
            if not args.inside:
                return st.object_function(o[a:b], u[a:b])
            return trace_object(st.tracer, scene.object.material, o[a:b], u[a:b],
                                scene.render.max_events, inside=np.ones(b - a, bool))

        parts = map_chunks(f, len(o), RAY_CHUNK, args.workers,
                           None if args.quiet else _progress("trace"))
        out = ObjectRays(**{k: np.concatenate([p.__dict__[k] for p in parts])
                            for k in parts[0].__dict__}) if parts else f(0, 0)
    with command_output():
        atomic_write(out_path, lambda f: np.savez_compressed(f, **out.__dict__, **extra))
    print(f"{args.out}: {len(o)} rays, {int(out.hit.sum())} hit the object, "
          f"{int(out.null.sum())} null")
    return 0


def cmd_validate(args):
    from .scene.io import load_scene
    from .trace.scene_tracer import SceneTracer, check_camera_outside
    scene = load_scene(args.scene)
    if scene.cameras:
        st = SceneTracer(scene)
        for cam in scene.cameras:
            check_camera_outside(st, cam)
    print(f"{args.scene}: ok — {len(scene.object.patches)} patches, {len(scene.meshes)} meshes, "
          f"{len(scene.lights)} lights, cameras {[c.name for c in scene.cameras]}")
    return 0


def cmd_demo(args):
    from .render.interpolated import render_tree, save_tree_render
    from .scene.camera import Shot
    from .scene.samples import build
    from .trace.scene_tracer import SceneTracer
    params, options = _bake_params(args), _query_options(args)
    out = Path(args.out)
    _check_writable(out, folder=True)
    out.mkdir(parents=True, exist_ok=True)
    scene = build(args.scene)
    scene.render.width = scene.render.height = args.size
    st = SceneTracer(scene)
    args.cameras = args.camera
    print(f"demo: {args.scene} / camera {args.camera} at {args.size}x{args.size}: "
          f"baking the RI-Tree (viewpoint depth {args.viewpoint_depth}, direction depth "
          f"{args.direction_depth}) for this camera")
    tree = _bake(scene, args, params, out / "tree.rit", st)
    res = render_tree(st, tree, Shot(args.camera), options=options, reference=True,
                      workers=args.workers, progress=_progress("interpolated + exact render"))
    res.stats["bake"] = tree.meta
    paths = save_tree_render(res, out)
    for p in [out / "tree.rit", *paths]:
        print(f"  wrote {p}")
    print(json.dumps({"bake": tree.meta, **res.stats["summary"]}, indent=2))
    print(f"demo output folder: {out.resolve()}")
    return 0


def cmd_bench_exact(args):
    from .bench.exact_bench import run, table
    if Path(args.out).is_dir():
        raise ValueError(f"{args.out}: is a folder")
    _check_writable(Path(args.out).parent, folder=True)
    res = run(args.scenes, size=args.size, camera=args.camera, workers=args.workers, out=args.out,
              progress_factory=None if args.quiet else _progress)
    print(f"{res['settings']['command']}  ({res['machine']['cpu_count']} cores, "
          f"{res['machine']['processor']}, numpy {res['machine']['numpy']})")
    print(table(res["rows"]))
    print(f"wrote {args.out}")
    return 0


def cmd_bench(args):
    from .bench.ritree_bench import config_from_args, replot, run
    if args.replot:
        res = replot(args.out)
        for p in res["written"]:
            print(f"wrote {p}")
        return 0
    _check_writable(args.out, folder=True)
    cfg = config_from_args(
        quick=args.quick, out=args.out, scenes=args.scenes, views=args.views, size=args.size,
        repeats=args.repeats, workers=args.workers, viewpoint_depth=args.viewpoint_depth,
        direction_depth=args.direction_depth, tolerance=args.tolerance, angle=args.angle,
        sweep_scenes=args.sweep_scenes, sweep_repeats=args.sweep_repeats,
        pareto_repeats=args.pareto_repeats,
        sweeps=False if args.no_sweeps else None, plots=False if args.no_plots else None,
        keep_trees=args.keep_trees or None)
    res = run(cfg, quiet=args.quiet)
    print(f"{res['command']}  ({res['machine']['cpu_count']} cores, "
          f"{res['machine']['processor']}, numpy {res['machine']['numpy']}; "
          f"{res['elapsed_s'] / 60:.1f} min)")
    print((Path(args.out) / "tables.md").read_text())
    for p in res["written"]:
        print(f"wrote {p}")
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
    p.add_argument("--samples", type=int, default=1, help="camera rays per pixel, 1..4096 "
                   "(default 1: the pixel centre; more: stratified, Blackman-Harris filtered)")
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--tree", default=None, help="render through this baked RI-Tree (.rit); "
                   "--out is then a folder (interpolated, exact, traced mask, error, stats)")
    p.add_argument("--no-reference", action="store_true",
                   help="with --tree: skip the exact reference render and error statistics")
    _tree_opts(p)
    p.set_defaults(fn=cmd_render)

    p = sub.add_parser("bake", help="bake the object's RI-Tree into a .rit cache file")
    scene_arg(p)
    p.add_argument("--out", required=True, help="the .rit file to write (atomically)")
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="bake the direction trees in shards on a Dask cluster: a running "
                   "scheduler's address (tcp://host:8786) or local:N (N worker processes on "
                   "this machine); needs riray[cluster] (docs/cluster.md)")
    _bake_opts(p)
    p.set_defaults(fn=cmd_bake)

    p = sub.add_parser("info", help="print a .rit file's parameters, region, counts and size")
    p.add_argument("tree")
    p.set_defaults(fn=cmd_info)

    p = sub.add_parser("trace-rays", help="apply the object function f to a batch of rays",
                       description="Input: an N x 6 float64 .npy (origin xyz, direction xyz). "
                       "Output .npz arrays: hit, null, out_origin, out_dir, t_first, point, "
                       "normal, patch, cls, events, refl_dir, fresnel, tree, uv (see "
                       "docs/cli.md).")
    scene_arg(p)
    p.add_argument("--rays", required=True, help="input .npy: N x 6 float64 rows (ox, oy, oz, "
                   "dx, dy, dz); directions need not be unit but must be non-zero")
    p.add_argument("--out", required=True, help="output .npz (the suffix is added if missing)")
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--inside", action="store_true",
                   help="every ray starts inside the object's glass (default: every ray starts "
                   "outside the object); refraction then leaves the glass first")
    p.add_argument("--tree", default=None, help="answer through this baked RI-Tree (.rit); "
                   "adds arrays 'answer' and 'traced_because'")
    _tree_opts(p)
    p.set_defaults(fn=cmd_trace_rays)

    from .scene.samples import SAMPLES
    p = sub.add_parser("bench-exact", help="benchmark the exact tracer on the sample scenes",
                       description="Exact render of each sample scene's view: build time, wall "
                       "time, object-only and total time, object rays/s, pairs and Newton "
                       "iterations per object ray. Prints a table; writes JSON.")
    p.add_argument("--scenes", nargs="+", choices=SAMPLES, default=list(SAMPLES), metavar="NAME",
                   help=f"sample scenes, any of {', '.join(SAMPLES)} (default: all)")
    p.add_argument("--size", type=int, default=300, help="image side in pixels (default: 300)")
    p.add_argument("--camera", default="close", help="camera name (default: close)")
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--out", default="bench_exact.json", help="JSON file to write "
                   "(default: bench_exact.json)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(fn=cmd_bench_exact)

    p = sub.add_parser("bench", help="RI-Tree benchmark: the paper's tables, parameter sweeps, "
                       "plots", description="Bakes each sample scene's view and measures exact, "
                       "interpolated (without and with the angle threshold) and raytree-policy "
                       "renders interleaved in the same processes (median of --repeats), then "
                       "sweeps depths, bake tolerance, thresholds and extrapolation. Writes "
                       "tables.csv, sweeps.csv, results.json, tables.md, sweeps.md and PNG plots "
                       "into --out (docs/benchmarks.md). Unset options take the full preset's "
                       "values, or --quick's.")
    p.add_argument("--quick", action="store_true",
                   help="smoke-check preset: 2 scenes x 2 views at 64 x 64, shallow trees, small "
                   "sweeps on glass_sphere (under two minutes on two cores)")
    p.add_argument("--out", default="bench_out", help="output folder (default: bench_out)")
    p.add_argument("--scenes", nargs="+", choices=SAMPLES, default=None, metavar="NAME",
                   help="table scenes (default: all five)")
    p.add_argument("--views", nargs="+", choices=("far", "close", "zoom"), default=None,
                   metavar="VIEW", help="table views (default: far close zoom)")
    p.add_argument("--size", type=int, default=None, help="image side in pixels (default 300)")
    p.add_argument("--repeats", type=int, default=None,
                   help="passes per interpolated configuration, median taken (default 3)")
    p.add_argument("--viewpoint-depth", type=int, default=None,
                   help="viewpoint depth of the table trees and the sweeps' base tree (default 4)")
    p.add_argument("--direction-depth", type=int, default=None,
                   help="direction depth of the table trees and the sweeps' base tree (default 5)")
    p.add_argument("--tolerance", type=float, default=None, metavar="DEG",
                   help="bake tolerance of the table trees (default 0.5)")
    p.add_argument("--angle", type=float, default=None, metavar="DEG",
                   help="angle threshold of the 'with threshold' rows (default 20)")
    p.add_argument("--sweep-scenes", nargs="+", choices=SAMPLES, default=None, metavar="NAME",
                   help="scenes swept (close view; default: glass_sphere vase_glass)")
    p.add_argument("--sweep-repeats", type=int, default=None,
                   help="passes per sweep point (default 1)")
    p.add_argument("--pareto-repeats", type=int, default=None,
                   help="passes per policy point of the Pareto curves, median taken "
                   "(default 3; --quick 1)")
    p.add_argument("--no-sweeps", action="store_true", help="tables only")
    p.add_argument("--no-plots", action="store_true", help="no PNG plots (no matplotlib needed)")
    p.add_argument("--keep-trees", action="store_true", help="keep the baked .rit files in "
                   "OUT/trees")
    p.add_argument("--replot", action="store_true", help="measure nothing: re-make the tables, "
                   "CSV and plots from OUT/results.json")
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(fn=cmd_bench)

    p = sub.add_parser("validate", help="load and validate a scene file")
    p.add_argument("scene")
    p.set_defaults(fn=cmd_validate)

    p = sub.add_parser("demo", help="bake a sample scene's RI-Tree for one camera and render "
                       "it interpolated beside the exact render, into a folder")
    p.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    p.add_argument("--scene", default="glass_sphere", help="sample scene name")
    p.add_argument("--camera", default="close")
    p.add_argument("--size", type=int, default=300)
    p.add_argument("--workers", type=int, default=None)
    _bake_opts(p)
    _tree_opts(p)
    p.set_defaults(fn=cmd_demo)
    return ap


def _check_options(args):
    """Refuse bad worker counts, image sizes and sample counts before any work (ValueError,
    one line)."""
    from .parallel import workers_default
    from .scene.io import MAX_IMAGE_SIDE
    if hasattr(args, "workers"):
        if args.workers is None:
            workers_default()                       # a bad RIRAY_WORKERS fails here, not later
        elif args.workers < 1:
            raise ValueError(f"--workers must be >= 1 (got {args.workers})")
        if getattr(args, "scheduler", None) and args.workers is not None:
            raise ValueError("--workers and --scheduler exclude each other (the cluster's "
                             "workers trace)")
    if hasattr(args, "samples"):
        from .scene.camera import Shot
        Shot(samples=args.samples)                  # 1..MAX_SAMPLES per pixel
    for flag in ("width", "height", "size"):
        v = getattr(args, flag, None)
        if v is not None and not 1 <= v <= MAX_IMAGE_SIDE:
            raise ValueError(f"--{flag}: image size must be 1..{MAX_IMAGE_SIDE} pixels (got {v})")


def _error(cmd, msg):
    if _BAR["open"]:
        print(file=sys.stderr)
        _BAR["open"] = False
    print(f"riray {cmd}: {msg}", file=sys.stderr)


def _warn(cmd, msg):
    _error(cmd, f"warning: {msg}")


def main(argv=None) -> int:
    """The program. Once a command's output files are being renamed into place it ignores
    Ctrl-C until the process ends (atomic.command_output), and so does an interrupted command
    while it reports; called in-process (``argv`` given) the SIGINT handler is put back on
    return."""
    args = build_parser().parse_args(argv)
    sigint = signal.getsignal(signal.SIGINT)
    try:
        _check_options(args)
        return args.fn(args)
    except (ValueError, OSError) as e:
        _error(args.cmd, f"error: {e}")
        return 2
    except MemoryError as e:
        _error(args.cmd, f"error: out of memory ({str(e) or 'the input is too large'})")
        return 2
    except KeyboardInterrupt:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)      # a second Ctrl-C: one line still
        _error(args.cmd, "interrupted")
        return 130
    finally:
        if argv is not None and sigint is not None \
                and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, sigint)


if __name__ == "__main__":
    sys.exit(main())
