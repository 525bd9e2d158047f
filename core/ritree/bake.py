"""Baking the RI-Tree (paper 3.3 and 4.3), level by level over all trees at once.

1. Viewpoint trees: the six faces of the padded box, split uniformly to ``viewpoint_depth``;
   only the leaf cells in the requested region get their corner viewpoints (shared corners are
   sampled once).
2. Direction trees: for every viewpoint, the hemicube slots that can see the object. Each level
   traces the midpoints of all open cells at once, interpolates them from the cell corners with
   the renderer's own rules (``interp.cell_weights``, usable = same class as the traced midpoint
   and not null), and splits the cells where the corners disagree in class or null state or
   where the interpolated output ray, hit point or normal misses the traced one by more than the
   tolerance. New corner samples are keyed on the finest grid, so cells share them.
3. Extra samples for leaves whose corners fall in two classes: the one- and two-interpolant
   cases, the class boundary located on the cell edges by binary search.

Tracing runs in chunks over worker processes; ``progress(fraction, message)`` is called between
chunks and ``cancel()`` (returning True) stops the bake with ``BakeCancelled``.

Sharded (``cluster``, see ``..cluster``): a pass's direction trees are split into consecutive
blocks (shards), each baked whole by ``bake_shard`` on a cluster worker, and ``_Baker._merge``
appends them exactly as one local pass over all of them would have: direction trees share no
samples (sample keys start with the tree id), a pass creates nodes level by level and samples
stage by stage (``_Stages``), each tree on its own, so the local order is (level or stage, tree,
order within the tree) and the merge interleaves the shards' blocks in that order.
"""

from __future__ import annotations

import os
import time

import numpy as np

from ..parallel import map_chunks
from .cache import fingerprint
from .derive import derive
from .dircube import CUBE, DOMAIN, N_SLOTS, U_AXIS, UV_AXES, V_AXIS, cube_to_dir
from .interp import FAIL, UNIT_CORNERS, angle_between, cell_weights
from .quadtree import CORNERS, Forest
from .region import Region, check_object
from .shardmerge import MergeBuffers, block_shifts, interleave
from .tree import (BOUNDARY, PATH_CHANGE, SAMPLE_FIELDS, UNVERIFIED, BakeParams, PackedSamples,
                   RITree, Samples)
from .verify import MEASURE_MIRROR_RAYS, viewpoint_errors

# The angle threshold (degrees) of the refinement rule (refine_rule): the paper's value.
REFINE_ANGLE_DEG = 20.0
# The baked-error tolerance (degrees) under which finest_rule counts traced rays: the
# render-time default's value when the rule was made (54f061c, 2026-12-04).
FINEST_TOLERANCE_DEG = 2.0
# The direction forest's per-node arrays a shard returns and the merge interleaves.
_NODE_FIELDS = ("child", "corner", "level", "ix", "iy", "dir_err", "dir_flags")
TRACE_CHUNK = 8192          # rays per worker task (bounds worker memory, keeps progress fluid)
SLOT_MIN_DEPTH = 1e-9      # object-box parts nearer than this (x its extent) along a slot's
                            # axis are ignored by the slot test (they project to infinity)


class BakeCancelled(Exception):
    """The bake was cancelled; nothing was written."""


class _Tracer:
    """Traces batches of (viewpoint, cube face, u, v) sample rays with the exact f."""

    def __init__(self, st, baker, workers, progress, cancel):
        self.st, self.baker, self.workers = st, baker, workers
        self.progress, self.cancel = progress, cancel
        self.kind, self.rays = "level", 0

    def __call__(self, vp, face, u, v) -> Samples:
        o = self.baker.vp_pos[vp]
        d = cube_to_dir(face, u, v)

        def work(a, b):
            return Samples.from_rays(self.st.object_function(o[a:b], d[a:b]))

        def prog(frac):
            if self.cancel is not None and self.cancel():
                raise BakeCancelled("bake cancelled")
            self.progress.tracing(frac)

        self.progress.begin(self.kind, len(o))
        parts = map_chunks(work, len(o), TRACE_CHUNK, self.workers, prog) if len(o) else []
        self.progress.end()
        self.rays += len(o)
        out = Samples.empty()
        for p in parts:
            out.extend(p)
        return out


class _Stages:
    """When a pass creates its samples: 0 the roots' corners; for direction level L < M,
    1 + 2 L the kept midpoints and 2 + 2 L the children's new corners; then the extra samples,
    1 + 2 M + step (M + 1) + the leaf's level. Within a pass the samples of one stage are
    ordered by tree (then as they were within the tree), and stages follow each other."""

    def __init__(self, M: int, steps: int):
        self.M = M
        self.count = np.zeros(1 + 2 * M + steps * (M + 1), np.int64)

    def mid(self, level):
        return 1 + 2 * level

    def corners(self, level):
        return 0 if level < 0 else 2 + 2 * level

    def extra(self, step, leaf_level):
        return 1 + 2 * self.M + step * (self.M + 1) + leaf_level


class _SampleIndex:
    """Sample ids by integer key, appended level by level (dedup of shared corners)."""

    def __init__(self):
        self.keys = np.zeros(0, np.int64)
        self.ids = np.zeros(0, np.int64)

    def lookup(self, keys):
        pos = np.searchsorted(self.keys, keys)
        pos = np.minimum(pos, len(self.keys) - 1) if len(self.keys) else pos
        found = (len(self.keys) > 0) & (self.keys[pos] == keys) if len(self.keys) else \
            np.zeros(len(keys), bool)
        return np.where(found, self.ids[pos] if len(self.keys) else -1, -1)

    def add(self, keys, ids):
        k = np.concatenate([self.keys, keys])
        i = np.concatenate([self.ids, ids])
        order = np.argsort(k, kind="stable")
        self.keys, self.ids = k[order], i[order]


class _Progress:
    """The bake's progress weighted by work: seconds spent / (seconds spent + seconds still
    expected), reported as ``progress(fraction, "label: NN% (eta S s)")``; the fraction never
    goes back (it holds while the estimate grows), S is the current estimate.

    Work is traced rays of two kinds, "level" (direction-tree corners and midpoints) and
    "extra" (the extra samples' binary search), at the seconds per ray measured for each kind
    (times the passes' measured overhead outside tracing). What is still expected is
    re-estimated as the bake goes: the deeper direction levels of a pass grow as the last level
    did; the extra samples are known exactly from their first step (``steps`` equal traces),
    before that as many per level ray as in the last pass; until then a pass after the first
    is expected to cost the mean seconds per direction tree of the passes before (the levels'
    first guesses are far off for deep trees). A camera bake's refinement passes are
    preceded, and the bake is ended, by the viewpoint cells' measurement (``refine`` /
    ``measure``), each expected to last as long as the last one did. The passes left grow in
    direction trees by the ratio of the last two refinement passes (``PASS_GROWTH0`` until two
    ran; the first refinement pass as many as the uniform pass)."""

    GROWTH0 = 2.0           # cells per cell from one direction level to the next, first guess
    RAYS_PER_CELL0 = 2.0    # rays traced per tested cell (midpoint, new corners), first guess
    EXTRA_PER_LEVEL0 = 1.0  # extra-sample rays per level ray, first guess
    EXTRA_COST0 = 2.0       # an extra-sample ray's cost in level rays until one was timed
    PASS_GROWTH0 = 3.0      # direction trees per tree from one refinement pass to the next,
                            # first guess (teapot close, depths 4/7, refine 3: 3.2, 3.4)
    PASS_GROWTH_MAX = 4.0   # a split viewpoint cell has four children

    def __init__(self, progress, passes: int, levels: int, steps: int):
        self.cb, self.passes, self.M, self.steps = progress, passes, levels, steps
        self.t0 = time.perf_counter()
        self.last, self.label, self.passes_done = 0.0, "starting", 0
        self.extra_per_level = self.EXTRA_PER_LEVEL0
        self.rays = {"level": 0, "extra": 0}          # rays traced (whole bake) ...
        self.secs = {"level": 0.0, "extra": 0.0}      # ... and the seconds they took
        self.call = None                              # (kind, rays, start) of the trace running
        self.pass_trees, self.pass_s = [], 0.0        # trees of each pass; seconds of the ended
        self.between_s = None                         # seconds of the last measurement
        self.pass_t0 = self.ended = self.t0
        self.trees, self.open = 0, False
        self._counts()

    def start_pass(self, trees: int):
        """A pass that bakes ``trees`` new direction trees begins (what ran since the last
        one ended, the viewpoint cells' measurement, is timed)."""
        now = time.perf_counter()
        if self.pass_trees:
            self.between_s = now - self.ended
        self.pass_t0, self.trees, self.open = now, trees, True
        self.pass_trees.append(trees)
        self._counts()

    def _counts(self):
        """Zero the open pass's counts and plan."""
        self.done = {"level": 0, "extra": 0}          # traced in this pass
        self.plan = {"level": 0.0, "extra": None}     # expected in this pass
        self.cells = self.level_start = 0

    def level(self, level: int, cells: int):
        """Direction level ``level`` of this pass is about to test ``cells`` cells (the deepest
        level, M, only traces their midpoints)."""
        per_cell, growth = self.RAYS_PER_CELL0, self.GROWTH0
        if self.cells:
            per_cell = (self.done["level"] - self.level_start) / self.cells
            growth = min(cells / self.cells, 4.0)
        ahead = [cells * growth ** j for j in range(self.M + 1 - level)]
        self.plan["level"] = self.done["level"] + per_cell * sum(ahead[:-1]) + ahead[-1]
        self.cells, self.level_start = cells, self.done["level"]
        self.emit(f"direction level {level}")

    def begin(self, kind: str, rays: int):
        if kind == "extra" and self.plan["extra"] is None:
            self.plan["level"] = self.done["level"]   # the levels are over: exact
            self.plan["extra"] = self.done["extra"] + rays * self.steps
        self.call = (kind, rays, time.perf_counter())

    def tracing(self, frac: float):
        self.emit(partial=frac)

    def end(self):
        kind, rays, t = self.call
        self.rays[kind] += rays
        self.secs[kind] += time.perf_counter() - t
        self.done[kind] += rays
        self.call = None

    def end_pass(self):
        if self.done["level"]:
            self.extra_per_level = self.done["extra"] / self.done["level"]
        self.ended = time.perf_counter()
        self.pass_s += self.ended - self.pass_t0
        self.passes_done, self.open = self.passes_done + 1, False

    def remaining_s(self, partial: float = 0.0) -> float | None:
        """Seconds still expected (None before any ray was timed)."""
        if not self.rays["level"] or not self.secs["level"]:
            return None
        now = time.perf_counter()
        baked = sum(self.pass_trees[:self.passes_done])
        per_tree = self.pass_s / baked if baked and self.pass_s > 0 else None
        between = self.between_s or 0.0
        if self.open:
            left = self._pass_left(now, partial)
            if per_tree is not None and self.plan["extra"] is None:
                # while the levels run: the mean cost per tree of the passes before
                est = per_tree * self.trees - (now - self.pass_t0)
                left = est if est > 0 else left
        else:                               # measuring the viewpoint cells
            left = max(between - (now - self.ended), 0.0)
        future = max(self.passes - self.passes_done - self.open, 0)
        if future:
            trees = self.pass_trees[-1]
            refined = self.pass_trees[1:]
            growth = min(refined[-1] / max(refined[-2], 1), self.PASS_GROWTH_MAX) \
                if len(refined) >= 2 else self.PASS_GROWTH0
            cost = per_tree if per_tree is not None else \
                (now - self.pass_t0 + left) / max(self.trees, 1)
            for k in range(future):
                after_uniform = k == 0 and len(self.pass_trees) == 1   # the first refinement
                trees *= 1.0 if after_uniform else growth
                left += between + cost * trees
        return left + (between if self.open else 0.0)     # the last measurement

    def _pass_left(self, now, partial) -> float:
        """Seconds still expected in the open pass, from its rays."""
        cost = {"level": self.secs["level"] / self.rays["level"]}
        cost["extra"] = (self.secs["extra"] / self.rays["extra"] if self.rays["extra"]
                         else self.EXTRA_COST0 * cost["level"])
        tracing = self.secs["level"] + self.secs["extra"] + (
            now - self.call[2] if self.call is not None else 0.0)
        overhead = (self.pass_s + now - self.pass_t0) / max(tracing, 1e-9)
        plan = dict(self.plan)
        if plan["extra"] is None:
            plan["extra"] = self.extra_per_level * plan["level"]
        left = 0.0
        for kind in ("level", "extra"):
            done = self.done[kind]
            if self.call is not None and self.call[0] == kind:
                done += partial * self.call[1]
            left += max(plan[kind] - done, 0.0) * cost[kind]
        return left * max(overhead, 1.0)

    def emit(self, label: str | None = None, partial: float = 0.0, done: bool = False):
        self.label = label or self.label
        if self.cb is None:
            return
        el = time.perf_counter() - self.t0
        left = 0.0 if done else self.remaining_s(partial)
        if left is None:
            return
        frac = min(max(el / (el + left) if el + left > 0 else 1.0, self.last), 1.0)
        self.last = frac
        where = self.label
        if self.passes > 1 and not done:
            where += f" (pass {min(self.passes_done + 1, self.passes)} of up to {self.passes})"
        self.cb(frac, f"{where}: {100 * frac:.0f}% (eta {left:.0f} s)")


def bake(st, params: BakeParams | None = None, region: Region | None = None, progress=None,
         cancel=None, workers=None, cluster=None) -> RITree:
    """Bake the RI-Tree of ``st`` (render.exact.SceneTracer) with ``params`` over ``region``,
    tracing over ``workers`` local processes, or with ``cluster`` (``..cluster.Cluster``) as
    shards on a Dask cluster: the same tree either way.

    With a camera region and ``params.viewpoint_refine`` > 0, the viewpoint cells where the
    cameras' own rays would still be traced (too few usable interpolants, thresholds) or where
    the measured viewpoint-level error exceeds ``viewpoint_tolerance_deg`` (verify.py) are
    split further, up to that many extra levels (non-uniform viewpoint subdivision). The final
    tree's viewpoint-level errors are measured and stored (``vp_err``, ``vp_flags``)."""
    params = (params or BakeParams()).validate()
    check_object(st)
    t0, c0 = time.perf_counter(), _cpu_seconds()
    refine = params.viewpoint_refine if region is not None and region.rays is not None else 0
    prog = _Progress(progress, 1 + refine, params.direction_depth, params.search_steps)
    baker = _Baker(st, params, prog, cancel, workers)
    baker.cluster = cluster
    # without cameras nothing reads the samples after the bake: shards come back packed
    baker.pack = region is None or not region.cameras
    baker.start(region)
    passes, measured = 0, False
    for _ in range(refine):
        if not baker.refine(region):
            measured = True                    # nothing split since the last measurement
            break
        passes += 1
    if not measured:
        baker.measure(region)
    tree = baker.tree()
    # what the caller renders with is exactly what a cache file stores
    if not isinstance(tree.samples, PackedSamples):
        tree.samples = tree.samples.packed(tree.box_lo, tree.box_hi)
    tree.samples = derive(tree.samples, st.tracer, tree.diag)
    tree.meta.update({"fingerprint": fingerprint(st.scene.object, st.scene.render.max_events),
                      "region": (region or Region()).describe(), "refine_passes": passes,
                      "viewpoint_mirror_rays": MEASURE_MIRROR_RAYS,
                      "bake_seconds": round(time.perf_counter() - t0, 3),
                      "bake_cpu_s": round(_cpu_seconds() - c0 + baker.remote_cpu_s, 3)})
    if cluster is not None:
        tree.meta["cluster"] = {**cluster.describe(), "shards": baker.shards,
                                "merge_s": round(baker.merge_s, 3)}
    prog.emit("done", done=True)
    return tree


def _cpu_seconds() -> float:
    """CPU seconds (user + system) of this process and of its finished worker processes."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


class _Baker:
    """The bake's state: viewpoint forest, direction forest and samples, grown pass by pass."""

    def __init__(self, st, params, progress, cancel, workers):
        self.st, self.params, self.cancel = st, params, cancel
        self.progress = progress
        lo, hi, diag = st.tracer.lo, st.tracer.hi, st.tracer.diag
        pad = params.pad * diag + 1e-12
        self.box_lo, self.box_hi, self.diag = lo - pad, hi + pad, diag
        self.D, self.M = params.viewpoint_depth, params.direction_depth
        self.Dmax = self.D + params.viewpoint_refine
        self.Gv = (1 << self.Dmax) + 1                  # global viewpoint grid (finest level)
        self.Gd = (1 << self.M) + 1
        self.class_of = st.tracer.class_of
        vp_dom = np.array([[self.box_lo[a], self.box_hi[a], self.box_lo[b], self.box_hi[b]]
                           for f in range(6) for (a, b) in [UV_AXES[f // 2]]])
        self.vpf = Forest.empty(vp_dom)
        self.vp_key = np.zeros(0, np.int64)             # sorted global keys ...
        self.vp_key_id = np.zeros(0, np.int64)          # ... and their viewpoint ids
        self.keys_by_id = np.zeros(0, np.int64)
        self.vp_pos = np.zeros((0, 3))
        self.vp_face = np.zeros(0, np.int64)
        self.dirf = Forest.empty(np.zeros((0, 4)))
        self.rect = np.zeros((0, 4))
        self.samples = Samples.empty()
        self.index = _SampleIndex()
        self.tracer = _Tracer(st, self, workers, progress, cancel)
        self.stages = _Stages(self.M, params.search_steps)
        self.cluster, self.shards, self.remote_cpu_s, self.merge_s = None, 0, 0.0, 0.0
        self.pack = False                   # shards return packed samples (the last pass)
        self.dir_err = np.zeros(0, np.float32)
        self.dir_flags = np.zeros(0, np.uint8)
        self.vp_err = self.vp_flags = None
        self.ex = {"ex_node": np.zeros(0, np.int64), "ex_kind": np.zeros(0, np.int8),
                   "ex_ids": np.zeros((0, 4), np.int64), "ex_pos": np.zeros((0, 4, 2), np.float32),
                   "ex_corner": np.zeros((0, 4), np.int64)}

    # ------------------------------------------------------------------ viewpoints
    def _viewpoints(self, leaves):
        """Corner viewpoint ids of viewpoint-forest ``leaves`` (created where new); returns the
        ids of the new viewpoints."""
        face = self.vpf.tree_of_nodes()[leaves]
        cc = self.vpf.corner_coords(leaves, self.Dmax)                    # (L, 4, 2)
        G = self.Gv
        keys = face[:, None] * G * G + cc[..., 1] * G + cc[..., 0]
        uk = np.unique(keys)
        pos = np.searchsorted(self.vp_key, uk)
        have = (pos < len(self.vp_key)) & (self.vp_key[np.minimum(pos, len(self.vp_key) - 1)] == uk) \
            if len(self.vp_key) else np.zeros(len(uk), bool)
        new_keys = uk[~have]
        start = len(self.vp_key)
        f = new_keys // (G * G)
        gy, gx = (new_keys % (G * G)) // G, new_keys % G
        pos3 = np.zeros((len(new_keys), 3))
        ax = f // 2
        rows = np.arange(len(new_keys))
        axes = np.array([UV_AXES[k // 2] for k in range(6)])
        lo, hi = self.box_lo, self.box_hi
        pos3[rows, ax] = np.where(f % 2 == 1, hi[ax], lo[ax])
        a_u, a_v = axes[f, 0], axes[f, 1]
        pos3[rows, a_u] = lo[a_u] + (hi[a_u] - lo[a_u]) * gx / (G - 1)
        pos3[rows, a_v] = lo[a_v] + (hi[a_v] - lo[a_v]) * gy / (G - 1)
        # ids follow creation order; vp_key keeps the keys sorted for lookups
        self.vp_pos = np.concatenate([self.vp_pos, pos3])
        self.vp_face = np.concatenate([self.vp_face, f])
        ids_all = np.concatenate([np.arange(start), start + rows])
        keys_all = np.concatenate([self.keys_by_id, new_keys])
        order = np.argsort(keys_all)
        self.vp_key, self.vp_key_id = keys_all[order], ids_all[order]
        self.keys_by_id = keys_all
        idx = self.vp_key_id[np.searchsorted(self.vp_key, keys)]
        self.vpf.corner[leaves] = idx
        return start + rows

    # ------------------------------------------------------------------ direction trees
    def _add_trees(self, vps, slots_rect):
        """Direction trees for new viewpoints ``vps``: ``slots_rect(vps) -> (needed (n, 5),
        rects (n, 5, 4))``. Returns the tree ids created."""
        n = len(vps)
        dom = DOMAIN[self.vp_face[vps]]                                   # (n, 5, 4)
        needed, rects = slots_rect(vps, dom)
        rects = np.stack([np.maximum(rects[..., 0], dom[..., 0]), np.minimum(rects[..., 1], dom[..., 1]),
                          np.maximum(rects[..., 2], dom[..., 2]), np.minimum(rects[..., 3], dom[..., 3])], -1)
        first = len(self.dirf.root)                     # = 5 * vps[0]: vps are the newest
        self.dirf.domain = np.concatenate([self.dirf.domain, dom.reshape(-1, 4)])
        self.dirf.root = np.concatenate([self.dirf.root, -np.ones(n * N_SLOTS, np.int64)])
        self.rect = np.concatenate([self.rect, rects.reshape(-1, 4)])
        return first + np.flatnonzero(needed.ravel())

    def _tree_vp_cube(self, tr):
        vp = tr // N_SLOTS
        return vp, CUBE[self.vp_face[vp], tr % N_SLOTS]

    def uv_of(self, tr, gxy):
        d = self.dirf.domain[tr]
        Gd = self.Gd
        return (d[:, 0] + (d[:, 1] - d[:, 0]) * gxy[:, 0] / (Gd - 1),
                d[:, 2] + (d[:, 3] - d[:, 2]) * gxy[:, 1] / (Gd - 1))

    def _trace(self, tr, u, v, kind="level"):
        vp, cube = self._tree_vp_cube(tr)
        self.tracer.kind = kind
        return self.tracer(vp, cube, u, v)

    def _add(self, s: Samples, stage) -> np.ndarray:
        """Append samples ``s`` created at ``stage`` (one, or one per sample, non-decreasing);
        returns their ids."""
        np.add.at(self.stages.count, np.broadcast_to(stage, (len(s),)), 1)
        return self.samples.extend(s)

    def _ensure(self, tr, gxy, stage):
        """Sample ids for grid points (tree, gx, gy), tracing the ones not sampled yet (they are
        created at ``stage``)."""
        Gd = self.Gd
        keys = tr * Gd * Gd + gxy[:, 1] * Gd + gxy[:, 0]
        ids = self.index.lookup(keys)
        miss = np.flatnonzero(ids < 0)
        if len(miss):
            nk, first, inv2 = np.unique(keys[miss], return_index=True, return_inverse=True)
            t_new, g_new = tr[miss][first], gxy[miss][first]
            u, v = self.uv_of(t_new, g_new)
            new = self._add(self._trace(t_new, u, v), stage)
            self.index.add(nk, new)
            ids[miss] = new[inv2.ravel()]
        return ids

    def _overlaps_rect(self, nodes, tr):
        cc = self.dirf.corner_coords(nodes, self.M)
        u_lo, v_lo = self.uv_of(tr, cc[:, 0])
        u_hi, v_hi = self.uv_of(tr, cc[:, 3])
        r = self.rect[tr]
        return (u_hi >= r[:, 0]) & (u_lo <= r[:, 1]) & (v_hi >= r[:, 2]) & (v_lo <= r[:, 3])

    def _hidden_hits(self, nodes, tr, ms):
        """BOUNDARY for the direction cells ``nodes`` whose corners and traced midpoints ``ms``
        all miss while their frustum (the rays from their viewpoint through the cell) meets the
        box of some sub-patch or triangle of the object: a hit may lie between the samples
        (paper Fig. 9(b)), so the render checks the cell's misses."""
        out = np.zeros(len(nodes), np.uint8)
        i = np.flatnonzero(np.all(self.samples.patch[self.dirf.corner[nodes]] < 0, axis=1)
                           & (ms.patch < 0))
        if len(i) == 0:
            return out
        cc = self.dirf.corner_coords(nodes[i], self.M)
        u0, v0 = self.uv_of(tr[i], cc[:, 0])
        u1, v1 = self.uv_of(tr[i], cc[:, 3])
        vp, cube = self._tree_vp_cube(tr[i])
        seen = rects_see_object(self.st.tracer, self.vp_pos[vp], cube,
                                np.stack([u0, u1, v0, v1], axis=1))
        out[i[seen]] = BOUNDARY
        return out

    def _bake_directions(self, trees):
        """Adaptive direction trees (paper 3.3) for ``trees``, all trees of a level at once
        (on the cluster's workers, shard by shard, when there is one)."""
        if self.cluster is not None:
            return self._bake_sharded(trees)
        p, M, Gd, dirf = self.params, self.M, self.Gd, self.dirf
        self.progress.start_pass(len(trees))
        self.stages.count[:] = 0
        nodes = dirf.add_roots(trees)
        dirf.corner[nodes] = self._ensure(np.repeat(trees, 4),
                                          np.tile(CORNERS * (Gd - 1), (len(trees), 1)),
                                          self.stages.corners(-1)).reshape(-1, 4)
        tol_ang, tol_d = np.radians(p.tolerance_deg), p.tolerance_dist * self.diag
        # levels 0..M-1 split where the test fails; leaves at the maximum depth M are tested too
        # (their error recorded, UNVERIFIED where they would split), not split
        for level in range(M + 1):
            if len(nodes) == 0:
                break
            tr = dirf.tree_of_nodes()[nodes]
            inside = self._overlaps_rect(nodes, tr)           # only the baked rectangle refines
            nodes, tr = nodes[inside], tr[inside]
            self.progress.level(level, len(nodes))
            cc = dirf.corner_coords(nodes, M)
            mid = (cc[:, 0] + cc[:, 3]) // 2 if level < M else (cc[:, 0] + cc[:, 3]) / 2
            if level < p.min_direction_depth:
                split = np.ones(len(nodes), bool)
            else:
                u, v = self.uv_of(tr, mid)
                ms = self._trace(tr, u, v)
                scale = dirf.cube_scale(nodes, tr, np.broadcast_to(UNIT_CORNERS[:, 0], (len(tr), 4)),
                                        np.broadcast_to(UNIT_CORNERS[:, 1], (len(tr), 4)))
                split, err, flags = _midpoint_test(self.samples, dirf.corner[nodes], scale, ms,
                                                   self.class_of, tol_ang, tol_d)
                flags |= self._hidden_hits(nodes, tr, ms)
                self._record(nodes, err, flags | np.where(split & (level == M), UNVERIFIED, 0))
                if level == M:
                    break
                # the traced midpoint becomes a corner of the children: keep it
                keep = np.flatnonzero(split)
                if len(keep):
                    new = self._add(_take(ms, keep), self.stages.mid(level))
                    self.index.add((tr * Gd * Gd + mid[:, 1] * Gd + mid[:, 0])[keep], new)
            sn = nodes[split]
            if len(sn) == 0:
                break
            kids = dirf.split(sn)                                        # (n, 4)
            kc = dirf.corner_coords(kids.ravel(), M)                     # (4n, 4, 2)
            ktr = np.repeat(tr[split], 4)
            dirf.corner[kids.ravel()] = self._ensure(np.repeat(ktr, 4), kc.reshape(-1, 2),
                                                     self.stages.corners(level)).reshape(-1, 4)
            nodes = kids.ravel()
        # extra samples (paper 4.3) for the new trees' leaves inside their rectangles
        self.progress.label = "extra samples"
        tree_of = dirf.tree_of_nodes()
        leaves = np.flatnonzero((dirf.child < 0) & np.isin(tree_of, trees))
        leaves = leaves[self._overlaps_rect(leaves, tree_of[leaves])]
        ex = _extras(dirf, leaves, self.samples, self.class_of, self._trace_vpc, self.uv_of,
                     tree_of, M, p.search_steps, self._add, self.stages.extra)
        for k in self.ex:
            self.ex[k] = np.concatenate([self.ex[k], ex[k]])
        order = np.argsort(self.ex["ex_node"])
        self.ex = {k: v[order] for k, v in self.ex.items()}
        self.progress.end_pass()

    # ------------------------------------------------------------------ shards
    def _bake_sharded(self, trees):
        """``_bake_directions`` on the cluster: consecutive blocks of ``trees`` baked by
        ``bake_shard`` on the workers, merged here (into buffers touched while waiting)."""
        blocks = np.array_split(trees, self.cluster.shard_count(len(trees)))
        blocks = [b for b in blocks if len(b)]
        prog = self.progress
        buffers = self.merge_buffers(len(trees))
        results = self.cluster.run(self.st, self.params, [self._shard_task(b) for b in blocks],
                                   self.cancel, prog.cb, (prog.passes_done, prog.passes),
                                   buffers)
        t0 = time.perf_counter()
        self._merge(blocks, results, buffers)
        self.merge_s += time.perf_counter() - t0
        self.shards += len(blocks)
        prog.end_pass()

    def _id_dtype(self):
        """Dtype of merged node and sample ids (packed: the final tree, as a file holds it)."""
        return np.dtype(np.int32 if self.pack else np.int64)

    def merge_buffers(self, trees: int) -> MergeBuffers:
        """Buffers for the merge of a pass over ``trees`` direction trees."""
        groups = {k: "nodes" for k in _NODE_FIELDS}
        groups.update({k: "samples" for k in (PackedSamples.FIELDS if self.pack
                                               else SAMPLE_FIELDS)})
        return MergeBuffers(groups, {"nodes": len(self.dirf.child),
                                     "samples": len(self.samples)}, trees,
                            {"child": self._id_dtype(), "corner": self._id_dtype()})

    def _shard_task(self, block) -> dict:
        """What a worker needs to bake direction trees ``block`` (sorted): their viewpoints and
        baked rectangles, renumbered from 0 in the same order."""
        vps, inv = np.unique(block // N_SLOTS, return_inverse=True)
        rows = (vps[:, None] * N_SLOTS + np.arange(N_SLOTS)).ravel()
        return {"trees": inv.ravel() * N_SLOTS + block % N_SLOTS, "vp_pos": self.vp_pos[vps],
                "vp_face": self.vp_face[vps], "rect": self.rect[rows], "pack": self.pack}

    def _merge(self, blocks, results, buffers=None):
        """Append the shards' trees (``results`` of ``bake_shard`` for ``blocks``) as one local
        pass over all of them makes them: nodes in (level, shard, shard's order), samples in
        (stage, shard, shard's order); ids in node and sample arrays renumbered to match, shard
        by shard as they are copied. Each array is written once, into ``buffers`` (a
        MergeBuffers) where they hold it."""
        f, K0, S0 = self.dirf, len(self.dirf.child), len(self.samples)
        self._record(np.zeros(0, np.int64), np.float32(0), np.uint8(0))    # grow to K0
        ncount = np.array([r["node_counts"] for r in results])
        scount = np.array([r["sample_counts"] for r in results])
        nshift, sshift = block_shifts(ncount, K0), block_shifts(scount, S0)
        nmaps, smaps, ex = [], [], {k: [v] for k, v in self.ex.items()}
        ids = self._id_dtype()
        for i, (block, r) in enumerate(zip(blocks, results)):
            # new ids of the shard's nodes and samples, and -1 (an id of -1 stays -1)
            nmap = np.append(np.arange(len(r["level"])) + nshift[i, r["level"]], -1).astype(ids)
            smap = np.append(np.arange(len(r["patch"])) + np.repeat(sshift[i], scount[i]),
                             -1).astype(ids)
            nmaps.append(nmap)
            smaps.append(smap)
            f.root[block] = nmap[r["root"]]
            ex["ex_node"].append(nmap[r["ex_node"]])
            ex["ex_ids"].append(smap[r["ex_ids"]])
            for k in ("ex_kind", "ex_pos", "ex_corner"):
                ex[k].append(r[k])
            self.tracer.rays += int(r["rays"])
            self.remote_cpu_s += float(r["cpu_s"])

        def merged(name, counts, head, maps=None):
            return interleave([r[name] for r in results], counts, head,
                              None if buffers is None else buffers.get(name), maps)

        f.child = merged("child", ncount, f.child.astype(ids), nmaps)
        f.corner = merged("corner", ncount, f.corner.astype(ids), smaps)
        for k in ("level", "ix", "iy"):
            setattr(f, k, merged(k, ncount, getattr(f, k)))
        self.dir_err = merged("dir_err", ncount, self.dir_err)
        self.dir_flags = merged("dir_flags", ncount, self.dir_flags)
        if self.pack:                  # the first and only pass: nothing to put before it
            self.samples = PackedSamples(**{k: merged(k, scount, results[0][k][:0])
                                            for k in PackedSamples.FIELDS},
                                         lo=self.box_lo, hi=self.box_hi)
        else:
            self.samples = Samples(**{k: merged(k, scount, getattr(self.samples, k))
                                      for k in SAMPLE_FIELDS})
        self.ex = {k: np.concatenate(v) for k, v in ex.items()}
        order = np.argsort(self.ex["ex_node"], kind="stable")      # sorted runs: merged
        self.ex = {k: v[order] for k, v in self.ex.items()}

    def _record(self, nodes, err, flags):
        """Store the measured error and flags of direction ``nodes`` (arrays grown to the
        forest's size)."""
        k = len(self.dirf.child)
        if len(self.dir_err) < k:
            self.dir_err = np.concatenate([self.dir_err,
                                           np.full(k - len(self.dir_err), np.nan, np.float32)])
            self.dir_flags = np.concatenate([self.dir_flags,
                                             np.zeros(k - len(self.dir_flags), np.uint8)])
        self.dir_err[nodes] = err
        self.dir_flags[nodes] = flags

    def _trace_vpc(self, tr, u, v):
        return self._trace(tr, u, v, "extra")

    # ------------------------------------------------------------------ passes
    def start(self, region):
        """Uniform viewpoint trees to depth D; corner viewpoints of the region's cells."""
        nodes = self.vpf.add_roots(np.arange(6))
        for _ in range(self.D):
            nodes = self.vpf.split(nodes).ravel()
        if region is not None and region.cells is not None:
            face = self.vpf.tree_of_nodes()[nodes]
            nodes = nodes[region.cells[face, self.vpf.ix[nodes], self.vpf.iy[nodes]]]
        vps = self._viewpoints(nodes)
        self._bake_directions(self._add_trees(vps, self._slot_fn(region, self.D)))

    def refine(self, region) -> bool:
        """One refinement pass: split the viewpoint cells where the region's rays are traced
        for lack of interpolants or by the thresholds, or where the measured viewpoint-level
        error exceeds ``viewpoint_tolerance_deg``; False when nothing is left to split. With
        ``finest_min_traced`` > 0, the pass that makes the finest level (and any later one)
        splits only the cells through which at least that many of the region's rays are traced
        under ``finest_rule``: the last level goes where tracing costs most."""
        from .locate import entry_points
        from .query import WHY_THRESHOLD, WHY_USABLE, TreeQuery
        tree = self.tree()
        o, d, tmax = region.rays
        finest = int(self.vpf.level[self.vpf.child < 0].max()) + 1 >= self.Dmax
        if finest and self.params.finest_min_traced > 0:
            self.measure(region, tree)
            leaf = self._traced_cells(tree, o, d, tmax)
        else:
            _, ans, why, _ = TreeQuery(tree, self.st, refine_rule())(o, d, tmax)
            bad = (why == WHY_USABLE) | (why == WHY_THRESHOLD)
            t_in, face, x, y, _ = entry_points(tree, o[bad], d[bad])
            leaf, _, _ = self.vpf.locate(face, x, y)
            err = self.measure(region, tree)
            leaf = np.union1d(leaf[leaf >= 0],
                              np.flatnonzero(err > self.params.viewpoint_tolerance_deg))
        leaf = leaf[self.vpf.level[leaf] < self.Dmax]
        if len(leaf) == 0:
            return False
        # level by level: a new viewpoint's direction rectangles are those the rays through
        # the new cells it is a corner of need, the rectangles of their level (the finest pass
        # may split cells of several levels, and a finer level's rectangles are narrower; a
        # later, finer cell that reuses the viewpoint needs no more: for one viewpoint a
        # coarser level's rectangle holds a finer one's)
        levels = self.vpf.level[leaf]
        trees = []
        for lv in np.unique(levels):
            kids = self.vpf.split(leaf[levels == lv]).ravel()
            vps = self._viewpoints(kids)
            if len(vps):
                trees.append(self._add_trees(vps, self._slot_fn(region, int(lv) + 1)))
        if trees:
            self._bake_directions(np.concatenate(trees))
        return True

    def _traced_cells(self, tree, o, d, tmax) -> np.ndarray:
        """Viewpoint leaves through which at least ``finest_min_traced`` of the rays (o, d,
        tmax) are traced under ``finest_rule``, on ``tree``, the tree as it is now (its
        viewpoint errors just measured)."""
        from .locate import locate
        from .query import TRACED, TreeQuery
        _, ans, _, _ = TreeQuery(tree, self.st, finest_rule())(o, d, tmax)
        tr = ans == TRACED
        loc, _ = locate(tree, o[tr], d[tr], tmax[tr])
        count = np.bincount(loc.vnode, minlength=len(self.vpf.child))
        return np.flatnonzero(count >= self.params.finest_min_traced)

    def measure(self, region, tree=None) -> np.ndarray:
        """Viewpoint-level errors of the current tree on the region's cameras (verify.py),
        kept for the tree; cells above the tolerance are flagged UNVERIFIED (a later pass that
        splits them measures their children). Returns the errors (NaN: not measured)."""
        cams = region.cameras if region is not None else None
        tree = tree or self.tree()
        err, flags = viewpoint_errors(tree, self.st, cams or [])
        flags[err > self.params.viewpoint_tolerance_deg] |= UNVERIFIED
        # kept for the bake and given to ``tree``, which a pass may query with them (its
        # decoded samples and locators are not built twice)
        self.vp_err, self.vp_flags = tree.vp_err, tree.vp_flags = err, flags
        return err

    def _slot_fn(self, region, level):
        """(needed slots, rects) of new viewpoints: the region's, or every slot that can see
        the object over its whole domain (no region)."""
        def fn(vps, dom):
            if region is None or region.tree_keys is None:
                return (_slots_seeing(self.vp_pos[vps], self.vp_face[vps], self.st.tracer.lo,
                                      self.st.tracer.hi), dom.copy())
            keys, rects = region.rects_at(level)
            tk = (self.keys_by_id[vps][:, None] * N_SLOTS + np.arange(N_SLOTS)).ravel()
            pos = np.clip(np.searchsorted(keys, tk), 0, max(len(keys) - 1, 0))
            found = (keys[pos] == tk) if len(keys) else np.zeros(len(tk), bool)
            out = dom.reshape(-1, 4).copy()
            out[found] = rects[pos[found]]
            return found.reshape(-1, N_SLOTS), out.reshape(-1, N_SLOTS, 4)
        return fn

    def tree(self) -> RITree:
        self._record(np.zeros(0, np.int64), np.float32(0), np.uint8(0))      # grow to the forest
        kv = len(self.vpf.child)
        vp_err = np.full(kv, np.nan, np.float32)
        vp_flags = np.zeros(kv, np.uint8)
        if self.vp_err is not None:
            vp_err[:len(self.vp_err)] = self.vp_err
            vp_flags[:len(self.vp_flags)] = self.vp_flags
        return RITree(params=self.params, box_lo=self.box_lo, box_hi=self.box_hi,
                      diag=self.diag, class_of=self.class_of.astype(np.int64),
                      vp_forest=self.vpf, vp_pos=self.vp_pos, vp_face=self.vp_face,
                      dir_forest=self.dirf, dir_rect=self.rect, samples=self.samples,
                      **self.ex, dir_err=self.dir_err.copy(), dir_flags=self.dir_flags.copy(),
                      vp_err=vp_err, vp_flags=vp_flags,
                      meta={"rays_traced": int(self.tracer.rays),
                            "viewpoints": int(len(self.vp_pos)),
                            "direction_trees": int(np.sum(self.dirf.root >= 0)),
                            "samples": int(len(self.samples)),
                            "extra_cells": int(len(self.ex["ex_node"]))})


def bake_shard(st, params: BakeParams, task: dict) -> dict:
    """Bake one shard's direction trees (``_Baker._shard_task``) in this process, one core: the
    cluster workers' work. Returns plain arrays: the forest's nodes (level-major: ``node_counts``
    per level), ``root`` per tree, the samples (stage-major: ``sample_counts`` per stage), the
    extra samples, ``rays`` traced and ``cpu_s`` (this thread's CPU seconds)."""
    c0 = time.thread_time()
    b = _Baker(st, params, _Progress(None, 1, params.direction_depth, params.search_steps),
               None, 1)
    b.vp_pos, b.vp_face, b.rect = task["vp_pos"], task["vp_face"], task["rect"]
    b.dirf = Forest.empty(DOMAIN[b.vp_face].reshape(-1, 4))
    b._bake_directions(task["trees"])
    b._record(np.zeros(0, np.int64), np.float32(0), np.uint8(0))
    f, i32 = b.dirf, np.int32                    # shard-local ids: int32 halves the transfer
    smp, fields = b.samples, SAMPLE_FIELDS
    if task["pack"]:                             # as the cache stores them (codec.py)
        smp, fields = smp.packed(b.box_lo, b.box_hi), PackedSamples.FIELDS
    return {"level": f.level, "ix": f.ix, "iy": f.iy, "child": f.child.astype(i32),
            "corner": f.corner.astype(i32), "root": f.root[task["trees"]].astype(i32),
            "dir_err": b.dir_err, "dir_flags": b.dir_flags,
            "node_counts": np.bincount(f.level, minlength=b.M + 1),
            "sample_counts": b.stages.count, "rays": b.tracer.rays,
            "cpu_s": time.thread_time() - c0,
            **{k: getattr(smp, k) for k in fields},
            **{k: v.astype(i32) if k in ("ex_node", "ex_ids", "ex_corner") else v
               for k, v in b.ex.items()}}


def refine_rule():
    """The query rule whose traced rays split viewpoint cells in a refinement pass: the paper's,
    with its 20-degree angle threshold, null rays traced (since 527fbe9; answered null before),
    not the render-time default, which may change."""
    from .query import QueryOptions
    return QueryOptions(angle_deg=REFINE_ANGLE_DEG, max_error_deg=None, null_interp=False)


def finest_rule():
    """The query rule whose traced rays choose the cells of the finest viewpoint level
    (``finest_min_traced``): the baked-error tolerance at FINEST_TOLERANCE_DEG with exact mirror
    hits, every other rule off, pinned here (not the render-time default, which may change)."""
    from .query import QueryOptions
    return QueryOptions(policy="ri", extrapolation=None, angle_deg=None, distance=None,
                        null_interp=True, max_error_deg=FINEST_TOLERANCE_DEG,
                        fallback_angle_deg=REFINE_ANGLE_DEG, path_identity=False,
                        mirror_rays="newton")


def _take(s: Samples, idx) -> Samples:
    return Samples(**{k: getattr(s, k)[idx] for k in SAMPLE_FIELDS})


def _cls(samples: Samples, ids, class_of):
    p = samples.patch[ids]
    return np.where(p >= 0, class_of[np.maximum(p, 0)], -1)


def _midpoint_test(samples, corner, scale, ms: Samples, class_of, tol_ang, tol_d):
    """Split test of cells with corner sample ids ``corner`` (N, 4) and traced midpoints ``ms``;
    ``scale`` (N, 4) weighs the corners' output directions as the renderer does
    (perspective-correct: the length of each corner's direction-cube point).

    Returns (split (N,), err (N,) float32, flags (N,) uint8): err is the output-direction error
    in degrees of the midpoint interpolated as the renderer would (the corners of its class,
    not null), 0 where the midpoint and all corners miss or are null of one class, NaN where
    there is no interpolation to measure; flags mark object/miss boundaries and ray-tree
    hash changes among the corners and the midpoint."""
    cc = _cls(samples, corner, class_of)
    cm = np.where(ms.patch >= 0, class_of[np.maximum(ms.patch, 0)], -1)
    cn = samples.null[corner]
    disagree = np.any(cc != cm[:, None], axis=1) | np.any(cn != ms.null[:, None], axis=1)
    usable = (cc == cm[:, None]) & ~cn
    half = np.full(len(corner), 0.5)
    w, st = cell_weights(usable, half, half)
    smooth = ~disagree & ~ms.null & (cm >= 0)
    fail = np.zeros(len(corner), bool)
    err = np.full(len(corner), np.nan, np.float32)
    err[~disagree & (ms.null | (cm < 0))] = 0.0
    meas = ~ms.null & (cm >= 0) & (st != FAIL)
    if np.any(meas):
        i = np.flatnonzero(meas)
        wi = w[i][:, :, None]
        ci = corner[i]
        od = np.einsum("nkc,nk->nc", samples.out_d[ci].astype(np.float64), w[i] * scale[i])
        od /= np.maximum(np.linalg.norm(od, axis=1), 1e-300)[:, None]
        nm = (samples.normal[ci].astype(np.float64) * wi).sum(1)
        nm /= np.maximum(np.linalg.norm(nm, axis=1), 1e-300)[:, None]
        oo = (samples.out_o[ci].astype(np.float64) * wi).sum(1)
        pt = (samples.point[ci].astype(np.float64) * wi).sum(1)
        e_od = angle_between(od, ms.out_d[i].astype(np.float64))
        err[i] = np.degrees(e_od)
        fail[i] = ((e_od > tol_ang)
                   | (angle_between(nm, ms.normal[i].astype(np.float64)) > tol_ang)
                   | (np.linalg.norm(oo - ms.out_o[i], axis=1) > tol_d)
                   | (np.linalg.norm(pt - ms.point[i], axis=1) > tol_d))
    fail |= smooth & (st == FAIL)
    hit = np.concatenate([cc, cm[:, None]], axis=1) >= 0
    flags = np.where(hit.any(1) & ~hit.all(1), BOUNDARY, 0).astype(np.uint8)
    th = np.concatenate([samples.tree[corner], ms.tree[:, None]], axis=1).astype(np.int64)
    th_hit = np.where(hit, th, -1)
    lo = np.where(hit, th, np.iinfo(np.int64).max).min(axis=1)
    flags |= np.where(th_hit.max(axis=1) > lo, PATH_CHANGE, 0).astype(np.uint8)
    return disagree | (smooth & fail), err, flags


def _slots_seeing(vp_pos, vface, lo, hi):
    """(V, 5) whether the object's box [lo, hi] meets each hemicube slot's frustum from each
    viewpoint (conservative: ``rect_sees_boxes`` on the slot domains)."""
    V = len(vp_pos)
    out = np.zeros((V, N_SLOTS), bool)
    ext = np.max(hi - lo)
    for s in range(N_SLOTS):
        dom = DOMAIN[vface, s]
        out[:, s] = rect_sees_boxes(vp_pos, CUBE[vface, s], dom, np.broadcast_to(lo, (V, 3)),
                                    np.broadcast_to(hi, (V, 3)), ext)
    return out


def rects_see_object(tracer, p, cube, rect):
    """(k,) whether some ray from ``p`` (k, 3) through cube-face rectangles ``rect`` (k, 4) on
    faces ``cube`` (k,) may meet the object of ``tracer`` (trace.patches.PatchTracer):
    conservative, on the boxes of its flat sub-patches and triangles (its BVHs)."""
    out = np.zeros(len(p), bool)
    bvhs = [tracer.bvh] + ([tracer.meshes.bvh] if tracer.meshes is not None else [])
    for bvh in (b for b in bvhs if b is not None):
        out |= bvh.any_box(len(p), lambda q, lo, hi: rect_sees_boxes(p[q], cube[q], rect[q], lo,
                                                                     hi, tracer.diag))
    return out


def rect_sees_boxes(p, cube, rect, lo, hi, ext):
    """(k,) whether some ray from points ``p`` (k, 3) with a direction in the cube-face
    rectangle ``rect`` (k, 4: u0, u1, v0, v1 on cube faces ``cube`` (k,)) may meet the boxes
    [lo, hi] (k, 3) (conservative). The face has axis b: the part of a box in front of p along b
    (depth >= SLOT_MIN_DEPTH * ``ext``) is again a box, the central projection of its corners
    bounds its image on the face, and that bound must overlap the rectangle."""
    k = len(p)
    rows = np.arange(k)
    b = cube // 2
    sign = np.where(cube % 2 == 1, 1.0, -1.0)
    p_b = p[rows, b]
    front = p_b + sign * SLOT_MIN_DEPTH * (ext + 1e-300)
    lo_c, hi_c = np.array(lo, np.float64), np.array(hi, np.float64)
    lo_c[rows, b] = np.where(sign > 0, np.maximum(lo_c[rows, b], front), lo_c[rows, b])
    hi_c[rows, b] = np.where(sign > 0, hi_c[rows, b], np.minimum(hi_c[rows, b], front))
    ok = lo_c[rows, b] <= hi_c[rows, b]
    pts = np.where(_BOX_CORNERS[None], hi_c[:, None, :], lo_c[:, None, :])    # (k, 8, 3)
    rel = pts - p[:, None, :]
    col = np.arange(8)[None]
    depth = np.where(ok[:, None], sign[:, None] * rel[rows[:, None], col, b[:, None]], 1.0)
    u = rel[rows[:, None], col, U_AXIS[b][:, None]] / depth
    v = rel[rows[:, None], col, V_AXIS[b][:, None]] / depth
    return ok & (u.max(1) >= rect[:, 0]) & (u.min(1) <= rect[:, 1]) \
        & (v.max(1) >= rect[:, 2]) & (v.min(1) <= rect[:, 3])


_BOX_CORNERS = np.array([[(i >> k) & 1 for k in range(3)] for i in range(8)], bool)   # (8, 3)


def _extras(dirf, leaves, samples, class_of, trace, uv_of, tree_of, M, steps, add, stage):
    """Extra samples of two-class leaves, appended by ``add(samples, stages)`` with
    ``stage(step, leaf level)``. Corner slots c0..c3 = (0,0), (1,0), (0,1), (1,1);
    edges are searched from a corner of one class towards its neighbour of the other class.

    one-interpolant (kind 1): lone corner L; v1 on the edge L->(L^1) (x edge), v2 on L->(L^2)
    (y edge), both in L's class; v3, v4 the other-class ends of the same brackets.
    two-interpolant (kind 2): corners A1, A2 of class A on one side, edges A1->B1, A2->B2;
    v1, v2 in class A (on those edges), v3, v4 in class B (same edges).
    ``ex_corner`` stores (L, -1, -1, -1) or (A1, A2, B1, B2)."""
    corner = dirf.corner[leaves]
    valid = np.all(corner >= 0, axis=1)
    leaves, corner = leaves[valid], corner[valid]
    cls = np.where(samples.null[corner], -2, _cls(samples, corner, class_of))
    srt = np.sort(cls, axis=1)
    # exactly two classes: sorted row is a a b b, a b b b or a a a b
    two = (srt[:, 0] != srt[:, 3]) & (np.sum(srt[:, 1:] != srt[:, :-1], axis=1) == 1)
    leaves, corner, cls = leaves[two], corner[two], cls[two]
    first = cls == cls[:, :1]
    n_first = first.sum(1)
    # the lone corner of a 1-vs-3 cell
    lone = np.where(n_first == 1, np.argmax(first, 1), np.where(n_first == 3, np.argmin(first, 1), -1))
    # two-vs-two: adjacent pairs share an edge (same row: c0c1 / c2c3, or same column: c0c2 / c1c3)
    pair = n_first == 2
    same_row = pair & (first[:, 0] == first[:, 1])
    same_col = pair & (first[:, 0] == first[:, 2])
    kind = np.where(lone >= 0, 1, np.where(same_row | same_col, 2, 0))
    sel = kind > 0
    leaves, corner, kind, lone = leaves[sel], corner[sel], kind[sel], lone[sel]
    same_row, same_col = same_row[sel], same_col[sel]
    E = len(leaves)
    # edges (start corner, end corner) to search: two per cell
    e_from = np.zeros((E, 2), np.int64)
    e_to = np.zeros((E, 2), np.int64)
    k1 = kind == 1
    e_from[k1] = lone[k1, None]
    e_to[k1, 0] = lone[k1] ^ 1
    e_to[k1, 1] = lone[k1] ^ 2
    # two-interpolant: same row -> vertical edges c0->c2, c1->c3; same column -> c0->c1, c2->c3
    e_from[same_row] = [0, 1]
    e_to[same_row] = [2, 3]
    e_from[same_col] = [0, 2]
    e_to[same_col] = [1, 3]
    ex_corner = -np.ones((E, 4), np.int64)
    ex_corner[k1, 0] = lone[k1]
    k2 = kind == 2
    ex_corner[k2] = np.concatenate([e_from[k2], e_to[k2]], axis=1)

    tr = tree_of[leaves]
    cc = dirf.corner_coords(leaves, M).astype(np.float64)               # (E, 4, 2) grid coords
    rows = np.arange(E)[:, None]
    p0 = cc[rows, e_from]                                               # (E, 2, 2)
    p1 = cc[rows, e_to]
    c_from = np.where(samples.null[corner[rows, e_from]], -2, _cls(samples, corner[rows, e_from], class_of))
    lo_f = np.zeros((E, 2))                                             # fraction in start class
    hi_f = np.ones((E, 2))                                              # fraction in other class
    lo_s = corner[rows, e_from].copy()
    hi_s = corner[rows, e_to].copy()
    trr = np.repeat(tr, 2)
    # bracket ends: corner sample ids (>= 0) or probes, coded -1 - (index into probes)
    probes = Samples.empty()
    for step in range(steps):
        f = 0.5 * (lo_f + hi_f)
        g = p0 + (p1 - p0) * f[..., None]                              # (E, 2, 2)
        u, v = uv_of(trr, g.reshape(-1, 2))
        s = trace(trr, u, v)
        c = np.where(s.null, -2, np.where(s.patch >= 0, class_of[np.maximum(s.patch, 0)], -1)).reshape(E, 2)
        ids = (-1 - probes.extend(s)).reshape(E, 2)
        same = c == c_from
        lo_f = np.where(same, f, lo_f)
        lo_s = np.where(same, ids, lo_s)
        hi_f = np.where(same, hi_f, f)
        hi_s = np.where(same, hi_s, ids)
    # keep only the probes that ended as bracket ends
    ends = np.concatenate([lo_s, hi_s], axis=1)
    used, inv = np.unique(-1 - ends[ends < 0], return_inverse=True)
    new = add(_take(probes, used), stage(used // max(2 * E, 1), dirf.level[leaves[(used % max(2 * E, 1)) // 2]]))
    ends[ends < 0] = new[inv.ravel()]
    lo_s, hi_s = ends[:, :2], ends[:, 2:]
    # local cell coordinates of the bracket ends
    a = CORNERS[e_from].astype(np.float64)                             # (E, 2, 2)
    b = CORNERS[e_to].astype(np.float64)
    pos_lo = a + (b - a) * lo_f[..., None]
    pos_hi = a + (b - a) * hi_f[..., None]
    ex_ids = np.concatenate([lo_s, hi_s], axis=1)                       # v1 v2 (start class), v3 v4
    ex_pos = np.concatenate([pos_lo, pos_hi], axis=1).astype(np.float32)
    order = np.argsort(leaves)
    return {"ex_node": leaves[order], "ex_kind": kind[order].astype(np.int8),
            "ex_ids": ex_ids[order], "ex_pos": ex_pos[order], "ex_corner": ex_corner[order]}
