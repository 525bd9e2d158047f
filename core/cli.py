"""The ``riray`` command line: thin sub-commands that parse, call the engine and report."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from . import cli_args
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
                        many_classes=args.many_classes.replace("-", "_"),
                        solve_paths=args.solve_paths == "on",
                        mirror_rays=args.mirror_rays).validate()


def _bake_params(args):
    """BakeParams of --quality's preset, the preset's fields given as flags taking over."""
    from .ritree.tree import BakeParams
    given = {"viewpoint_depth": args.viewpoint_depth, "direction_depth": args.direction_depth,
             "viewpoint_refine": args.viewpoint_refine, "tolerance_deg": args.tolerance}
    return BakeParams.preset(
        args.quality, **{k: v for k, v in given.items() if v is not None},
        min_direction_depth=args.min_direction_depth, tolerance_dist=args.tolerance_dist,
        viewpoint_tolerance_deg=args.viewpoint_tolerance,
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


def _load_tree(args, scene, path=None):
    """The RI-Tree of ``path`` (default ``args.tree``) for ``scene``'s object; a tree without
    samples (its cameras saw nothing of the object) is used with a warning: every ray it meets
    is traced."""
    from .ritree import tree as ritree
    path = args.tree if path is None else path
    tree = ritree.load(path, scene)
    if len(tree.samples) == 0:
        _warn(args.cmd, f"{path}: the RI-Tree holds no samples; every ray is traced exactly")
    return tree


def _tree_paths(specs, scene) -> dict:
    """{object index: tree path} of ``--tree`` values: ``OBJECT=PATH``, or a bare PATH in a
    scene of one object. ValueError (before any tree is read) for an unknown or repeated
    object, a bare path among several objects, or a tree that another of the scene's objects
    was baked for."""
    from .scene.model import object_names
    names = [o.name for o in scene.objects]
    paths: dict = {}
    for spec in specs:
        name, eq, path = spec.partition("=")
        if not (eq and name in names):
            if len(names) > 1:
                raise ValueError(f"--tree {spec}: the scene has {len(names)} specular objects "
                                 f"({object_names(scene.objects)}): give --tree OBJECT=PATH")
            name, path = names[0], spec
        i = names.index(name)
        if i in paths:
            raise ValueError(f"--tree: two trees for the object {name!r}")
        _check_tree_owner(path, scene, i)
        paths[i] = path
    return paths


def _check_tree_owner(path, scene, i) -> None:
    """ValueError when the tree at ``path`` was baked for another of the scene's objects than
    object ``i`` (its header's fingerprint is theirs); any other mismatch is the load's."""
    from .ritree.cache import describe, fingerprint
    if len(scene.objects) == 1:
        return
    have = describe(path)["header"].get("fingerprint")
    prints = [fingerprint(o, scene.render.max_events) for o in scene.objects]
    if have != prints[i] and have in prints:
        raise ValueError(f"{path}: this RI-Tree was baked for the object "
                         f"{scene.objects[prints.index(have)].name!r}, not "
                         f"{scene.objects[i].name!r}")


def _connect(spec):
    """The Dask cluster of ``--scheduler`` (before the slow work); its address and dashboard on
    stderr."""
    from .cluster import connect
    cluster = connect(spec)
    dash = cluster.dashboard
    print(f"dask: scheduler {cluster.address}, {cluster.threads()} worker threads"
          + (f", dashboard {dash}" if dash else ""), file=sys.stderr, flush=True)
    return cluster


def _object_view(scene, name):
    """The scene as its specular object ``name`` sees it (Scene.view); its only object when
    ``name`` is None. ValueError when the scene has several and no name is given."""
    if name is None:
        if len(scene.objects) > 1:
            from .scene.model import object_names
            raise ValueError(f"the scene has {len(scene.objects)} specular objects "
                             f"({object_names(scene.objects)}): choose one with --object NAME")
        return scene
    return scene.view(scene.object_index(name))


def cmd_bake(args):
    from .trace.scene_tracer import SceneTracer
    params = _bake_params(args)
    _check_writable(args.out)
    scene = _object_view(_load(args.scene), args.object)
    cluster = _connect(args.scheduler) if args.scheduler else None
    try:
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
    from .trace.scene_tracer import object_tracers
    options = _query_options(args) if args.tree else None
    _check_writable(args.out if args.tree else Path(args.out).parent, folder=True)
    scene = _load(args.scene)
    shot = Shot(args.camera, args.width, args.height, args.samples)
    progress = None if args.quiet else _progress("render")
    if args.tree:
        from .render.interpolated import render_tree, save_tree_render
        paths = _tree_paths(args.tree, scene)
        sts = object_tracers(scene)
        trees = [_load_tree(args, st.scene, paths[i]) if i in paths else None
                 for i, st in enumerate(sts)]
        for st, tree in zip(sts, trees):
            if tree is None:
                _warn(args.cmd, f"no --tree for the object {st.scene.object.name!r}: it is "
                      "traced exactly")
        res = render_tree(sts[0], trees[0], shot, options=options,
                          reference=not args.no_reference, workers=args.workers,
                          progress=progress, others=list(zip(sts[1:], trees[1:])))
        with command_output():
            paths = save_tree_render(res, args.out)
        print(json.dumps({"written": [str(p) for p in paths], **res.stats["summary"]}, indent=2))
        return 0
    t0 = time.perf_counter()
    sts = object_tracers(scene)
    build_s = time.perf_counter() - t0
    res = render_exact(sts[0], shot, workers=args.workers, progress=progress, others=sts[1:])
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
    from .imageio import npy_header
    with open_regular(path) as f:
        shape, dtype, data = npy_header(f, path)
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
    scene = _object_view(_load(args.scene), args.object)
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
    # f's arrays; a dielectric's Fresnel tree (out_weight, branch_color) is rendering's
    arrays = {k: v for k, v in out.__dict__.items() if k not in ("out_weight", "branch_color")}
    with command_output():
        atomic_write(out_path, lambda f: np.savez_compressed(f, **arrays, **extra))
    print(f"{args.out}: {len(o)} rays, {int(out.hit.sum())} hit the object, "
          f"{int(out.null.sum())} null")
    return 0


def cmd_validate(args):
    from .scene.io import load_scene
    from .trace.scene_tracer import check_camera_outside, object_tracers
    scene = load_scene(args.scene)
    if scene.cameras:
        for st in object_tracers(scene):
            for cam in scene.cameras:
                check_camera_outside(st, cam)
    objects = "" if len(scene.objects) == 1 else (
        f"{len(scene.objects)} specular objects ("
        + ", ".join(f"{o.name!r}: {len(o.patches)}" for o in scene.objects) + " patches), ")
    print(f"{args.scene}: ok — {objects or f'{len(scene.object.patches)} patches, '}"
          f"{len(scene.meshes)} meshes, "
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
          f"baking the RI-Tree (viewpoint depth {params.viewpoint_depth}, direction depth "
          f"{params.direction_depth}) for this camera")
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


COMMANDS = {"render": cmd_render, "bake": cmd_bake, "info": cmd_info,
            "trace-rays": cmd_trace_rays, "bench-exact": cmd_bench_exact, "bench": cmd_bench,
            "validate": cmd_validate, "demo": cmd_demo}


def build_parser() -> argparse.ArgumentParser:
    """The parser of every sub-command (cli_args.py), each bound to its command here."""
    return cli_args.build_parser(COMMANDS)


def _error(cmd, msg):
    if _BAR["open"]:
        print(file=sys.stderr)
        _BAR["open"] = False
    print(f"riray {cmd}: {msg}", file=sys.stderr)


def _warn(cmd, msg):
    _error(cmd, f"warning: {msg}")


def main(argv=None) -> int:
    """The program. Once a command's output files are being renamed into place it ignores
    Ctrl-C until the process ends (files.command_output), and so does an interrupted command
    while it reports; called in-process (``argv`` given) the SIGINT handler is put back on
    return."""
    args = build_parser().parse_args(argv)
    sigint = signal.getsignal(signal.SIGINT)
    try:
        cli_args.check_options(args)
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
