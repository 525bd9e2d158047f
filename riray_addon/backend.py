"""The seam between the add-on and the RI-Tree (core/ritree). No bpy: this module runs in
Blender *and* in the bake worker process.

The add-on only ever calls the functions below:

    bake_tree(scene, params, progress, cancel, scheduler) -> RITree   (worker process)
    save_tree(tree, path, meta, cancel, progress) / read_header(path) / load_tree(path)
        (a file that cannot be used raises TreeCacheError)
    estimate_bake(scene, params, progress, cancel) -> {"time_s", "bytes", ...}   (worker process)
    tree_answerer(scene_tracer, tree, options) -> TreeAnswerer   (engine; core/render/frame.py)

``scene`` is a core Scene (the object, the environment and, for camera-driven bakes, one camera
per camera and frame); ``params`` holds riray_addon.properties.BAKE_KEYS plus "width" and
"height"; progress(fraction, message) and cancel() -> bool are polled between trace chunks.
Cache files are core's .rit files (docs/tree-format.md); the add-on's own meta data (object,
fingerprint of geometry + transform + material, parameters) rides in the header under "addon".
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from dataclasses import fields
from types import SimpleNamespace

import numpy as np

from ..core.trace.scene_tracer import SceneTracer
from ..core.ritree import bake as ritree_bake
from ..core.ritree import cache as ritree_cache
from ..core.ritree import tree as ritree
from ..core.ritree.cache import TreeCacheError
from ..core.render.frame import TreeAnswerer
from ..core.ritree.query import QueryOptions, TreeQuery
from ..core.parallel import map_chunks, workers_default
from ..core.ritree.bake import TRACE_CHUNK
from ..core.ritree.dircube import N_SLOTS, U_AXIS, V_AXIS
from ..core.ritree.locate import entry_points
from ..core.ritree.region import Region, region_for_cameras

BACKEND = "ritree"
# The estimate's trial bake (estimate_bake): the share of the bake's viewpoint cells it bakes,
# at least so many cells (without cameras: so many of every cell, each a full tree's cost), in
# aligned blocks of so many cells a side, drawn with a fixed seed.
EST_TRIAL_SHARE = 1 / 16
EST_TRIAL_CELLS = 24
EST_TRIAL_CELLS_FULL = 6
EST_TRIAL_BLOCK = 1
EST_TRIAL_SEED = 1
EST_CALIBRATION_RAYS = (128, 1024, 8192)   # batch sizes whose cost per ray is measured
EST_START_S = 1.0               # worker start, imports, scene read, tracer (measured 0.7 s on
                                # the glass_sphere sample, 2-core AMD EPYC), and polling


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


def estimate_bake(scene, params: dict, progress=None, cancel=None) -> dict:
    """Bake time (s) and cache size (bytes) before baking, measured by a trial: a real bake of
    a sample of the viewpoint cells (ranked by the cameras' rays through them, every k-th)
    with the cameras' rays through them, scaled up level by level. The first
    viewpoint level's direction trees are counted exactly from the cameras' region (every
    viewpoint without cameras); a finer level gets the share of its possible trees that the
    trial's refinement passes made; samples a tree are the trial's at each level; the cache's
    bytes follow the samples, the bake's seconds the trial's exact traces at the cost per ray
    of the bake's larger batches (measured here), the rest the samples. Runs in the worker
    process (seconds: the region at full HD, the trial); ``progress(fraction, message)`` and
    ``cancel()`` as for bake_tree (BakeCancelled)."""
    step = progress or (lambda fraction, message="": None)
    st = SceneTracer(scene)
    bp = bake_params(params)
    kind = "mirror" if scene.object.material.kind == "mirror" else "glass"
    region, region_s = None, 0.0
    if params.get("bake_for_cameras", True) and scene.cameras:
        step(0.0, "finding what the cameras see")
        t0 = time.perf_counter()
        region = region_for_cameras(st, bp, scene.cameras, int(params["width"]),
                                    int(params["height"]))
        region_s = time.perf_counter() - t0
    trial, weight = _trial_region(st, bp, region)
    t0 = time.perf_counter()
    st.tracer.occlusion_proxy                   # built once a bake: not scaled with the trial
    fixed_s = time.perf_counter() - t0
    cost, speedup = _calibrate(st)
    t0 = time.perf_counter()
    tree, calls = _trial(st, bp, trial, lambda fraction: step(fraction, "trial bake"), cancel)
    trial_s = time.perf_counter() - t0
    trees, scale = _extrapolate(tree, bp, region, weight)
    ray_share = 1.0 if region is None else len(region.rays[0]) / max(len(trial.rays[0]), 1)
    bake_s = _bake_seconds(trial_s, calls, scale, ray_share, cost, speedup)
    trial_bytes, save_s, save_fixed_s = _saved(tree)
    save_s = save_fixed_s + scale * (save_s - save_fixed_s)
    return {"time_s": EST_START_S + region_s + fixed_s + bake_s + save_s,
            "bytes": scale * trial_bytes, "rays": round(scale * tree.meta["rays_traced"]),
            "samples": scale * tree.meta["samples"], "direction_trees": trees, "kind": kind,
            "region_s": region_s, "trial_s": trial_s, "bake_s": bake_s}


def _trial(st, bp, region, progress, cancel):
    """(tree, calls): the trial bake over ``region`` in this process, and each exact trace it
    made as (rays, whether they were bake samples, seconds)."""
    calls = []
    traced = st.object_function

    def timed(o, d, *args, **kw):
        t0 = time.perf_counter()
        out = traced(o, d, *args, **kw)
        calls.append((len(o), "record" in kw, time.perf_counter() - t0))
        return out
    st.object_function = timed
    try:
        return ritree_bake.bake(st, bp, region, progress=lambda f, m="": progress(f),
                                cancel=cancel, workers=1), calls
    except ritree_bake.BakeCancelled as exc:
        raise BakeCancelled() from exc
    finally:
        del st.object_function


def _bake_seconds(trial_s, calls, scale, ray_share, cost, speedup) -> float:
    """The bake's seconds from the trial's: each exact trace of the trial as a batch ``scale``
    times as large (the checks on the cameras' rays ``ray_share`` times), at the cost per ray
    ``cost(batch)`` gives that size, sample batches split over the bake's worker processes
    as core splits them, ``speedup`` times faster than one process at most (measured); the
    rest of the trial (bookkeeping) ``scale`` times."""
    rest, traced = trial_s, 0.0
    for n, sample, seconds in calls:
        rest -= seconds
        k = scale if sample else ray_share
        big = n * k
        if sample and big > TRACE_CHUNK:
            chunks = math.ceil(big / TRACE_CHUNK)
            traced += seconds * k * cost(TRACE_CHUNK) / cost(n) / min(speedup, chunks)
        else:
            traced += seconds * k * cost(big) / cost(n)
    return max(rest, 0.0) * scale + traced


def _calibrate(st):
    """(cost, speedup) of the object's exact traces here, measured on EST_CALIBRATION_RAYS
    batches of rays from around its box towards it: ``_cost_per_ray`` and, for the largest
    batch, ``_parallel_speedup``."""
    rng = np.random.default_rng(EST_TRIAL_SEED)
    c = 0.5 * (st.tracer.lo + st.tracer.hi)
    r = 0.5 * max(st.tracer.diag, 1e-9)
    batches = []
    for n in EST_CALIBRATION_RAYS:
        o = c + 1.5 * r * _unit(rng.normal(size=(n, 3)))
        batches.append((o, _unit(c + 0.5 * r * rng.uniform(-1, 1, (n, 3)) - o)))
    cost = _cost_per_ray(st, batches)
    return cost, _parallel_speedup(st, *batches[-1], cost)


def _cost_per_ray(st, batches):
    """cost(n): the seconds a ray costs when traced n at a time, from the timed ``batches``
    ((origins, dirs) of EST_CALIBRATION_RAYS rays; log-log between them, flat beyond)."""
    per_ray = []
    for o, d in batches:
        t0 = time.perf_counter()
        st.object_function(o, d)
        per_ray.append((time.perf_counter() - t0) / len(o))
    log_n, log_c = np.log(EST_CALIBRATION_RAYS), np.log(np.maximum(per_ray, 1e-12))
    return lambda n: float(np.exp(np.interp(np.log(max(n, 1.0)), log_n, log_c)))


def _parallel_speedup(st, o, d, cost) -> float:
    """How many times faster rays ``o``, ``d`` trace split over the bake's worker processes,
    as the bake splits its batches, than the same chunks one after another (``cost``): 1 ..
    the number of processes (two processes on two cores baked 1.4x, not 2x, faster than one).
    Timed from the first chunk's start to the last one's end (the system-wide monotonic
    clock): the processes' own start is a bake pass's fixed cost, spread there over many
    chunks."""
    workers = workers_default()
    if workers <= 1:
        return 1.0
    n, chunk = len(o), math.ceil(len(o) / workers)

    def timed(a, b):
        t0 = time.monotonic()
        st.object_function(o[a:b], d[a:b])
        return t0, time.monotonic()
    spans = np.array(map_chunks(timed, n, chunk, workers))
    split = spans[:, 1].max() - spans[:, 0].min()
    return float(np.clip(n * cost(chunk) / max(split, 1e-9), 1.0, workers))


def _unit(v):
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _trial_region(st, bp, region) -> tuple[Region, np.ndarray]:
    """The trial's Region and the weight of each block of viewpoint cells (how many blocks
    of the bake the drawn one stands for; 0: not drawn). Blocks of EST_TRIAL_BLOCK x
    EST_TRIAL_BLOCK cells of ``region`` are ranked by the cameras' rays through them and
    every k-th is drawn, from a random start, so that the trial's blocks mix busy and quiet
    ones as the bake's do: about EST_TRIAL_SHARE of the cells, at least EST_TRIAL_CELLS
    (without cameras: EST_TRIAL_CELLS_FULL of every cell). The trial bakes
    their cells with the cameras' rays through them."""
    n = 1 << bp.viewpoint_depth
    cells = np.ones((6, n, n), bool) if region is None else region.cells
    b = min(EST_TRIAL_BLOCK, n)
    nb = n // b
    blocks = cells.reshape(6, nb, b, nb, b).sum((2, 4)).ravel()
    load = np.zeros(len(blocks))
    if region is not None:
        face, ix, iy = _entry_cells(st, bp, *region.rays[:2])
        block_of = (face * nb + ix // b) * nb + iy // b
        load = np.bincount(block_of, minlength=len(blocks)).astype(np.float64)
    rng = np.random.default_rng(EST_TRIAL_SEED)
    ids = np.flatnonzero(blocks)
    ids = ids[np.lexsort((rng.random(len(ids)), load[ids]))]       # ties in random order
    want = EST_TRIAL_CELLS_FULL         # without cameras nothing is refined: few cells do
    if region is not None:
        want = max(EST_TRIAL_SHARE * cells.sum(), min(EST_TRIAL_CELLS, cells.sum()))
    k = max(len(ids) * blocks[ids].mean() / want, 1.0)               # every k-th block
    take = ids[np.unique(np.arange(rng.uniform(0.0, k), len(ids), k).astype(np.int64))]
    weight = np.zeros(len(blocks))
    weight[take] = len(ids) / len(take)
    keep = (weight > 0).reshape(6, nb, nb)
    mask = keep.repeat(b, 1).repeat(b, 2)
    if region is None:
        return Region(cells=mask), weight
    o, d, t = region.rays
    inside = keep.ravel()[block_of]
    return (Region(cells=cells & mask, levels=region.levels,
                   rays=(o[inside], d[inside], t[inside]), cameras=region.cameras), weight)


def _entry_cells(st, bp, o, d):
    """(face, ix, iy): the viewpoint cell at the first level through which rays (o, d) enter
    the object's padded box (as region_for_cameras finds it)."""
    pad = bp.pad * st.tracer.diag + 1e-12
    box = SimpleNamespace(box_lo=st.tracer.lo - pad, box_hi=st.tracer.hi + pad)
    _, face, x, y, _ = entry_points(box, o, d)
    axis = face // 2
    n = 1 << bp.viewpoint_depth
    cell = []
    for c, a in ((x, U_AXIS[axis]), (y, V_AXIS[axis])):
        frac = np.clip((c - box.box_lo[a]) / (box.box_hi[a] - box.box_lo[a]), 0.0, 1.0)
        cell.append(np.minimum((frac * n).astype(np.int64), n - 1))
    return face, cell[0], cell[1]


def _extrapolate(tree, bp, region, weight) -> tuple[float, float]:
    """(direction trees, scale): the bake's direction trees estimated from the trial ``tree``
    and how many times the trial's samples the bake's are. A level's trees: at the first
    level those the region needs (without cameras: the trial's per viewpoint times every
    viewpoint); at a finer one the region's possible trees there times the share the trial
    made of those within its blocks (each block counted by its ``weight``). Samples: the
    trial's per tree at each level."""
    grid = _Grid(bp)
    face, gx, gy = grid.of_viewpoints(tree)
    level, block = grid.level(gx, gy), grid.block(face, gx, gy)
    w = weight[block]
    tree_ids = np.flatnonzero(tree.dir_forest.root >= 0)
    vp = tree_ids // N_SLOTS
    per_tree = _samples_per_tree(tree)[tree_ids]
    trees = samples = 0.0
    for L in range(grid.D, grid.Dmax + 1):
        mine = level[vp] == L
        if not mine.any():
            continue
        if region is None:
            count = np.sum(mine) * 6 * ((1 << grid.D) + 1) ** 2 / max(np.sum(level == L), 1)
        else:
            every, possible = grid.possible(region.levels[L][0], L, weight)
            count = every if L == grid.D else every * np.sum(w[vp[mine]]) / max(possible, 1e-300)
        trees += count
        samples += count * np.sum(w[vp[mine]] * per_tree[mine]) / np.sum(w[vp[mine]])
    return trees, samples / max(per_tree.sum(), 1)


class _Grid:
    """The bake's finest viewpoint grid (2^Dmax + 1 points a side of each box face), where
    viewpoints and direction-tree keys are placed, its levels and the trial's blocks."""

    def __init__(self, bp):
        self.D, self.Dmax = bp.viewpoint_depth, bp.viewpoint_depth + bp.viewpoint_refine
        self.G = (1 << self.Dmax) + 1
        self.nb = (1 << self.D) // min(EST_TRIAL_BLOCK, 1 << self.D)

    def of_viewpoints(self, tree):
        """(face, gx, gy) of the tree's viewpoints."""
        face = np.asarray(tree.vp_face, np.int64)
        axis = face // 2
        rows = np.arange(len(face))
        out = [face]
        for a in (U_AXIS[axis], V_AXIS[axis]):
            lo, hi = tree.box_lo[a], tree.box_hi[a]
            pos = tree.vp_pos[rows, a]
            out.append(np.rint((pos - lo) / (hi - lo) * (self.G - 1)).astype(np.int64))
        return tuple(out)

    def of_keys(self, keys):
        """(face, gx, gy) of direction-tree keys (viewpoint key * N_SLOTS + slot)."""
        vk = np.asarray(keys, np.int64) // N_SLOTS
        return vk // (self.G * self.G), vk % self.G, (vk % (self.G * self.G)) // self.G

    def level(self, gx, gy):
        """The viewpoint level at which grid points are first cell corners."""
        out = np.full(len(gx), self.Dmax)
        for L in range(self.Dmax - 1, self.D - 1, -1):
            step = 1 << (self.Dmax - L)
            out[(gx % step == 0) & (gy % step == 0)] = L
        return out

    def block(self, face, gx, gy):
        """The trial block each grid point belongs to (on a border, the one above / right of
        it, the last block at the face's far edges)."""
        span = (self.G - 1) // self.nb
        bx = np.minimum(gx // span, self.nb - 1)
        by = np.minimum(gy // span, self.nb - 1)
        return (face * self.nb + bx) * self.nb + by

    def possible(self, keys, L, weight) -> tuple[int, float]:
        """Of the region's direction-tree ``keys`` at viewpoint level L, those of viewpoints
        first made at L: (how many, their total ``weight`` by block)."""
        face, gx, gy = self.of_keys(keys)
        new = self.level(gx, gy) == L
        return int(new.sum()), float(weight[self.block(face[new], gx[new], gy[new])].sum())


def _samples_per_tree(tree) -> np.ndarray:
    """(T,) samples each direction tree holds: its nodes' corners and its extra samples."""
    f = tree.dir_forest
    node_tree = f.tree_of_nodes()
    pairs = [np.repeat(node_tree, 4) * (1 << 32) + f.corner.ravel()]
    if len(tree.ex_node):
        pairs.append(np.repeat(node_tree[tree.ex_node], 4) * (1 << 32) + tree.ex_ids.ravel())
    pairs = np.unique(np.concatenate(pairs))
    pairs = pairs[(pairs % (1 << 32)) < (1 << 31)]          # drop unsampled corners (-1)
    return np.bincount(pairs >> 32, minlength=len(f.root)).astype(np.float64)


def _saved(tree) -> tuple[int, float, float]:
    """(bytes, seconds, fixed seconds) of the trial ``tree`` saved as a cache file (then
    removed); the fixed seconds are those of a file of one array (the atomic write's fsyncs,
    the encoders' start): a bake's save costs them once, not once per trial's worth."""
    fd, path = tempfile.mkstemp(suffix=".rit")
    os.close(fd)
    try:
        t0 = time.perf_counter()
        ritree_cache.save_tree(path, {}, {"x": np.zeros(1)})
        t1 = time.perf_counter()
        ritree.save(tree, path, {})
        t2 = time.perf_counter()
        return os.path.getsize(path), t2 - t1, min(t1 - t0, t2 - t1)
    finally:
        os.remove(path)


def tree_answerer(st, tree, options: dict | None = None) -> TreeAnswerer:
    """The frame pipeline's answerer for object rays through the tree, with the render-time
    rules ``options`` (QueryOptions keywords)."""
    return TreeAnswerer(TreeQuery(tree, st, QueryOptions(**(options or {}))))


__all__ = ["BACKEND", "BakeCancelled", "TreeCacheError", "bake_tree", "save_tree", "read_header",
           "load_tree", "estimate_bake", "tree_answerer"]
