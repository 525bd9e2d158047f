"""The seam between the add-on and the RI-Tree (core/ritree). No bpy: this module runs in
Blender *and* in the bake worker process.

The add-on only ever calls the functions below:

    bake_tree(scene, params, progress, cancel, scheduler) -> RITree   (worker process)
    save_tree(tree, path, meta, cancel, progress) / read_header(path) / load_tree(path)
        (a file that cannot be used raises TreeCacheError)
    estimate_bake(scene, params) -> {"time_s", "bytes", "rays"}
    tree_answerer(scene_tracer, tree, options) -> TreeAnswerer   (engine; core/render/frame.py)

``scene`` is a core Scene (the object, the environment and, for camera-driven bakes, one camera
per camera and frame); ``params`` holds riray_addon.properties.BAKE_KEYS plus "width" and
"height"; progress(fraction, message) and cancel() -> bool are polled between trace chunks.
Cache files are core's .rit files (docs/tree-format.md); the add-on's own meta data (object,
fingerprint of geometry + transform + material, parameters) rides in the header under "addon".
"""

from __future__ import annotations

import os
import time
from dataclasses import fields

import numpy as np

from ..core.trace.scene_tracer import SceneTracer
from ..core.ritree import bake as ritree_bake
from ..core.ritree import cache as ritree_cache
from ..core.ritree import tree as ritree
from ..core.ritree.cache import TreeCacheError
from ..core.render.frame import TreeAnswerer
from ..core.ritree.query import QueryOptions, TreeQuery
from ..core.ritree.region import region_for_cameras

BACKEND = "ritree"
CALIBRATION_RAYS = 2048         # rays traced to measure this object's cost per ray (estimate)
CALIBRATION_RUNS = 3            # timed runs of them; the median counts (the machine is shared)
# Estimate model for camera bakes, fit to Draft / Fast / Default bakes of a glass NURBS sphere
# seen by one camera at 1920 x 1080 (docs/blender.md, "How good the estimate is"). The
# viewpoints baked are the first level's plus a share of what each finer level adds (the
# refinement passes split only some cells), each with a typical sample count. The time is the
# worker's start, the cameras' region (computed by the estimate itself, timed), the bake (a
# sample costs about a ray and each pass checks the tree on the cameras' rays at a fraction of
# a ray each), and compressing the cache; the size a fixed part plus bytes per sample.
EST_LEVEL_SHARE = (0.8, 0.3)    # share of the viewpoints the 2nd, 3rd... level adds (last repeats)
EST_SAMPLES_PER_VIEWPOINT = 52
EST_RAYS_PER_SAMPLE = 1.25      # ray costs per sample (extra samples where surfaces meet)
EST_CHECK_RAYS = 0.14           # ray costs per camera ray and pass
EST_START_S = 2.0               # worker start, imports, scene read
EST_SAVE_S_PER_BYTE = 1.0e-6    # compressing and writing the cache
EST_BYTES_FIXED = 47e3
EST_BYTES_PER_SAMPLE = {"glass": 9.5, "mirror": 7.5}


class BakeCancelled(Exception):
    """Raised by bake_tree when cancel() turned true."""


def bake_params(params: dict) -> ritree.BakeParams:
    """BakeParams from the add-on's parameter dict (unknown keys ignored)."""
    names = {f.name for f in fields(ritree.BakeParams)}
    return ritree.BakeParams(**{k: v for k, v in params.items() if k in names}).validate()


def bake_tree(scene, params: dict, progress, cancel, scheduler: str = ""):
    """Bake the RI-Tree of ``scene.object`` (runs in the worker process); on the Dask cluster
    at ``scheduler`` (an address or local:N, core/cluster.py) where one is given."""
    cluster = None
    if scheduler:
        from ..core.cluster import connect
        progress(0.0, f"connecting to {scheduler}")
        cluster = connect(scheduler)
        dash = cluster.dashboard
        progress(0.0, f"Dask scheduler {cluster.address}, {cluster.threads()} worker threads"
                 + (f", dashboard {dash}" if dash else ""))
    try:
        return _bake(scene, params, progress, cancel, cluster)
    finally:
        if cluster is not None:
            cluster.close()


def _bake(scene, params, progress, cancel, cluster):
    st = SceneTracer(scene)
    bp = bake_params(params)
    region = None
    if params.get("bake_for_cameras", True) and scene.cameras:
        region = region_for_cameras(st, bp, scene.cameras, int(params["width"]),
                                    int(params["height"]))
    try:
        return ritree_bake.bake(st, bp, region, progress=progress, cancel=cancel,
                                cluster=cluster)
    except ritree_bake.BakeCancelled as exc:
        raise BakeCancelled() from exc


def save_tree(tree, path: str, meta: dict, cancel=None, progress=None) -> int:
    """Write the cache file atomically (see core/ritree/cache.py); BakeCancelled when
    ``cancel()`` turns true while it is compressed; ``progress(fraction)`` follows the
    compression. Returns its size."""
    try:
        ritree.save(tree, path, {"addon": meta}, cancel, progress)
    except ritree_cache.SaveCancelled as exc:
        raise BakeCancelled() from exc
    return os.path.getsize(path)


def read_header(path: str) -> dict | None:
    """The cache's header document {"backend", "tree", "meta"}, or None when the file is
    missing or not a riray tree."""
    try:
        header = ritree_cache.describe(path)["header"]
    except (OSError, ValueError):
        return None
    return {"backend": BACKEND, "tree": header, "meta": header.get("addon", {})}


def load_tree(path: str):
    """(RITree, header document): the file read whole into memory and checked."""
    tree = ritree.load(path)
    return tree, {"backend": BACKEND, "tree": tree.header(), "meta": tree.meta.get("addon", {})}


def estimate_bake(scene, params: dict) -> dict:
    """Bake time (s) and cache size (bytes) before baking: the viewpoints the cameras need (or
    every one, without cameras) times a typical sample count, at the measured cost of one ray
    through this object, plus the cameras' region as long as it takes here."""
    st = SceneTracer(scene)
    bp = bake_params(params)
    per_ray = _cost_per_ray(st)
    kind = "mirror" if scene.object.material.kind == "mirror" else "glass"
    region_s, checks = 0.0, 0.0
    if params.get("bake_for_cameras", True) and scene.cameras:
        t0 = time.perf_counter()
        region = region_for_cameras(st, bp, scene.cameras, int(params["width"]),
                                    int(params["height"]))
        region_s = time.perf_counter() - t0
        viewpoints = _viewpoints(region)
        checks = EST_CHECK_RAYS * len(region.rays[0]) * (1 + bp.viewpoint_refine)
    else:
        viewpoints = 6 * (2 ** bp.viewpoint_depth + 1) ** 2 * 3
    samples = viewpoints * EST_SAMPLES_PER_VIEWPOINT
    rays = int(samples * EST_RAYS_PER_SAMPLE)
    size = EST_BYTES_FIXED + samples * EST_BYTES_PER_SAMPLE[kind]
    bake_s = (rays + checks) * per_ray
    return {"time_s": EST_START_S + region_s + bake_s + size * EST_SAVE_S_PER_BYTE,
            "bytes": float(size), "rays": rays, "per_ray_s": per_ray, "kind": kind,
            "region_s": region_s}


def _cost_per_ray(st) -> float:
    """Seconds one ray through the object takes here: the median of CALIBRATION_RUNS runs of
    CALIBRATION_RAYS rays from around its box towards it."""
    rng = np.random.default_rng(1)
    c = 0.5 * (st.tracer.lo + st.tracer.hi)
    r = 0.5 * max(st.tracer.diag, 1e-9)
    o = c + 1.5 * r * _unit(rng.normal(size=(CALIBRATION_RAYS, 3)))
    d = _unit(c + 0.5 * r * rng.uniform(-1, 1, (CALIBRATION_RAYS, 3)) - o)
    runs = []
    for _ in range(CALIBRATION_RUNS):
        t0 = time.perf_counter()
        st.object_function(o, d)
        runs.append((time.perf_counter() - t0) / CALIBRATION_RAYS)
    return float(np.median(runs))


def _viewpoints(region) -> float:
    """Viewpoints a camera bake is expected to hold: the region's first level, then a share of
    what each finer level adds (EST_LEVEL_SHARE)."""
    counts = [len(region.levels[lv][0]) for lv in sorted(region.levels)]
    total = float(counts[0])
    for i, (coarse, fine) in enumerate(zip(counts, counts[1:])):
        total += EST_LEVEL_SHARE[min(i, len(EST_LEVEL_SHARE) - 1)] * (fine - coarse)
    return total


def _unit(v):
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def tree_answerer(st, tree, options: dict | None = None) -> TreeAnswerer:
    """The frame pipeline's answerer for object rays through the tree, with the render-time
    rules ``options`` (QueryOptions keywords)."""
    return TreeAnswerer(TreeQuery(tree, st, QueryOptions(**(options or {}))))


__all__ = ["BACKEND", "BakeCancelled", "TreeCacheError", "bake_tree", "save_tree", "read_header",
           "load_tree", "estimate_bake", "tree_answerer"]
