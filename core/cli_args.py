"""The ``riray`` command line's arguments: the parser of every sub-command, the option groups
they share, and the checks that refuse bad values before any work."""

from __future__ import annotations

import argparse

from . import __version__

DESCRIPTION = "The riray command line: thin sub-commands that parse, call the engine and report."


def tree_options(p):
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
    p.add_argument("--many-classes", choices=("first-hit", "trace"), default="first-hit",
                   help="a ray whose 16 samples hold more than two classes takes the class of "
                   "its exact first hit (first-hit, the default; a miss is then answered "
                   "exactly) or is traced (trace, the paper's two-patch condition)")
    p.add_argument("--solve-paths", choices=("on", "off"), default="on",
                   help="a ray the tolerance (--max-error) or --path-identity would trace, or "
                   "with too few usable samples, is first solved exactly along the path of "
                   "its nearest sample (the same "
                   "surfaces in the same order); only where it leaves that path is it traced "
                   "(on, the default; off: trace every such ray)")
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


def bake_options(p):
    from .ritree.params import QUALITY_PRESETS
    from .ritree.tree import BakeParams
    d = BakeParams()

    def preset(field):
        """The help's default of a field the quality preset sets: each preset's value."""
        return ", ".join(f"{q} {v[field]:g}" for q, v in QUALITY_PRESETS.items())

    p.add_argument("--quality", choices=tuple(QUALITY_PRESETS), default="default",
                   help="bake quality preset, the add-on's Quality: the depths, viewpoint "
                   "refinement and tolerance the flags below do not give (default: default, "
                   "the paper's depths; fast: about a third of the bake time; draft: quicker "
                   "still, more rays traced at render time)")
    p.add_argument("--viewpoint-depth", type=int, default=None,
                   help="uniform viewpoint-tree depth (default: the preset's, "
                   f"{preset('viewpoint_depth')})")
    p.add_argument("--direction-depth", type=int, default=None,
                   help="maximum direction-tree depth (default: the preset's, "
                   f"{preset('direction_depth')})")
    p.add_argument("--viewpoint-refine", type=int, default=None,
                   help="extra viewpoint levels where the cameras' rays lack interpolants "
                   "(camera-region bakes only; default: the preset's, "
                   f"{preset('viewpoint_refine')})")
    p.add_argument("--min-direction-depth", type=int, default=d.min_direction_depth,
                   help=f"direction trees split at least this deep (default {d.min_direction_depth})")
    p.add_argument("--tolerance", type=float, default=None, metavar="DEG",
                   help="bake angular tolerance (degrees; default: the preset's, "
                   f"{preset('tolerance_deg')})")
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


def build_parser(commands: dict):
    ap = argparse.ArgumentParser(prog="riray", description=DESCRIPTION)
    ap.add_argument("--version", action="version", version=f"riray {__version__}")
    sub = ap.add_subparsers(dest="cmd", required=True)

    def scene_arg(p):
        p.add_argument("scene", help="scene file (.json) or a sample name (teapot, vase_glass, ...)")

    def object_arg(p, verb):
        p.add_argument("--object", default=None, metavar="NAME",
                       help=f"the specular object to {verb} (required when the scene has "
                       "several)")

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
    p.add_argument("--tree", action="append", default=None, metavar="[OBJECT=]PATH",
                   help="render through this baked RI-Tree (.rit); --out is then a folder "
                   "(interpolated, exact, traced mask, error, stats). In a scene of several "
                   "specular objects give one OBJECT=PATH per object (repeat --tree); an "
                   "object without one is traced exactly")
    p.add_argument("--no-reference", action="store_true",
                   help="with --tree: skip the exact reference render and error statistics")
    tree_options(p)
    p.set_defaults(fn=commands["render"])

    p = sub.add_parser("bake", help="bake the object's RI-Tree into a .rit cache file")
    scene_arg(p)
    object_arg(p, "bake")
    p.add_argument("--out", required=True, help="the .rit file to write (atomically)")
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="bake the direction trees in shards on a Dask cluster: a running "
                   "scheduler's address (tcp://host:8786) or local:N (N worker processes on "
                   "this machine); needs riray[cluster] (docs/cluster.md)")
    bake_options(p)
    p.set_defaults(fn=commands["bake"])

    p = sub.add_parser("info", help="print a .rit file's parameters, region, counts and size")
    p.add_argument("tree")
    p.set_defaults(fn=commands["info"])

    p = sub.add_parser("trace-rays", help="apply the object function f to a batch of rays",
                       description="Input: an N x 6 float64 .npy (origin xyz, direction xyz). "
                       "Output .npz arrays: hit, null, out_origin, out_dir, t_first, point, "
                       "normal, patch, cls, events, refl_dir, fresnel, tree, uv (see "
                       "docs/cli.md).")
    scene_arg(p)
    object_arg(p, "apply f of")
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
    tree_options(p)
    p.set_defaults(fn=commands["trace-rays"])

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
    p.set_defaults(fn=commands["bench-exact"])

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
    p.set_defaults(fn=commands["bench"])

    p = sub.add_parser("validate", help="load and validate a scene file")
    p.add_argument("scene")
    p.set_defaults(fn=commands["validate"])

    p = sub.add_parser("demo", help="bake a sample scene's RI-Tree for one camera and render "
                       "it interpolated beside the exact render, into a folder")
    p.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    p.add_argument("--scene", default="glass_sphere", help="sample scene name")
    p.add_argument("--camera", default="close")
    p.add_argument("--size", type=int, default=300)
    p.add_argument("--workers", type=int, default=None)
    bake_options(p)
    tree_options(p)
    p.set_defaults(fn=commands["demo"])
    return ap


def check_options(args):
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
