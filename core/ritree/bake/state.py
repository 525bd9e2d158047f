"""The bake's configuration (what it was asked, fixed for the bake) and its state (the
forests and samples, grown pass by pass), each one object built complete."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..dircube import DOMAIN, UV_AXES
from ..quadtree import Forest
from ..tree import SAMPLE_FIELDS, BakeParams, PackedSamples, Samples

TRACE_CHUNK = 8192          # rays per worker task (bounds worker memory, keeps progress fluid)


@dataclass
class BakeConfig:
    """One bake's settings: the object (``st``, a SceneTracer), ``params``, the local worker
    processes, ``cancel()``, the cluster (None: local), whether shards return packed samples
    (``pack``) and the rays per worker task (``chunk``); and what follows from them: the padded
    box, the depths and the finest viewpoint and direction grids (points per side)."""

    st: Any
    params: BakeParams
    workers: int | None = None
    cancel: Callable[[], bool] | None = None
    cluster: Any = None
    pack: bool = False
    chunk: int = TRACE_CHUNK
    box_lo: np.ndarray = field(init=False)      # (3,) the padded box
    box_hi: np.ndarray = field(init=False)
    diag: float = field(init=False)             # the object's (unpadded) box diagonal
    class_of: np.ndarray = field(init=False)    # (P,) class id of each patch
    D: int = field(init=False)                  # uniform viewpoint depth
    M: int = field(init=False)                  # maximum direction depth
    Dmax: int = field(init=False)               # finest viewpoint depth (after refinement)
    Gv: int = field(init=False)                 # finest viewpoint grid: 2^Dmax + 1 points
    Gd: int = field(init=False)                 # finest direction grid: 2^M + 1 points

    def __post_init__(self):
        tracer, p = self.st.tracer, self.params
        pad = p.pad * tracer.diag + 1e-12
        self.box_lo, self.box_hi, self.diag = tracer.lo - pad, tracer.hi + pad, tracer.diag
        self.class_of = tracer.class_of
        self.D, self.M = p.viewpoint_depth, p.direction_depth
        self.Dmax = self.D + p.viewpoint_refine
        self.Gv, self.Gd = (1 << self.Dmax) + 1, (1 << self.M) + 1


class Stages:
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


class SampleIndex:
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


@dataclass
class BakeStats:
    """What the bake counted: rays traced (here and on the cluster), the cluster workers' CPU
    seconds, the seconds spent merging shards and the shards run."""

    rays: int = 0
    remote_cpu_s: float = 0.0
    merge_s: float = 0.0
    shards: int = 0


def _no_extras() -> dict:
    return {"ex_node": np.zeros(0, np.int64), "ex_kind": np.zeros(0, np.int8),
            "ex_ids": np.zeros((0, 4), np.int64), "ex_pos": np.zeros((0, 4, 2), np.float32),
            "ex_corner": np.zeros((0, 4), np.int64)}


@dataclass
class BakeState:
    """The forests and samples a bake grows: the viewpoint forest (corners = viewpoint ids) and
    its viewpoints, the direction forest (corners = sample ids) with each tree's baked
    rectangle, the samples with their index and creation stages, the measured errors and
    flags, the extra samples (RITree's ``ex_*`` arrays, sorted by node) and the counts."""

    vpf: Forest
    stages: Stages
    vp_pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))   # (V, 3)
    vp_face: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    keys_by_id: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    vp_key: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))     # sorted keys
    vp_key_id: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # their ids
    dirf: Forest = field(default_factory=lambda: Forest.empty(np.zeros((0, 4))))
    rect: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))     # (5 V, 4)
    samples: Samples | PackedSamples = field(default_factory=Samples.empty)
    index: SampleIndex = field(default_factory=SampleIndex)
    dir_err: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    dir_flags: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    vp_err: np.ndarray | None = None      # the last measurement (None: none yet)
    vp_flags: np.ndarray | None = None
    ex: dict = field(default_factory=_no_extras)
    stats: BakeStats = field(default_factory=BakeStats)

    @classmethod
    def empty(cls, cfg: BakeConfig) -> "BakeState":
        """No viewpoints yet: six viewpoint-tree domains, the faces of the padded box."""
        lo, hi = cfg.box_lo, cfg.box_hi
        vp_dom = np.array([[lo[a], hi[a], lo[b], hi[b]]
                           for f in range(6) for (a, b) in [UV_AXES[f // 2]]])
        return cls(vpf=Forest.empty(vp_dom),
                   stages=Stages(cfg.M, cfg.params.search_steps))

    @classmethod
    def for_shard(cls, cfg: BakeConfig, task: dict) -> "BakeState":
        """A shard's state: the task's viewpoints (``vp_pos``, ``vp_face``) and their direction
        trees' rectangles (``rect``), the trees not yet baked."""
        state = cls.empty(cfg)
        state.vp_pos, state.vp_face, state.rect = task["vp_pos"], task["vp_face"], task["rect"]
        state.dirf = Forest.empty(DOMAIN[state.vp_face].reshape(-1, 4))
        return state

    def add_samples(self, s: Samples, stage) -> np.ndarray:
        """Append samples ``s`` created at ``stage`` (one, or one per sample, non-decreasing);
        returns their ids."""
        np.add.at(self.stages.count, np.broadcast_to(stage, (len(s),)), 1)
        return self.samples.extend(s)

    def grow_records(self) -> None:
        """Grow the direction nodes' errors (NaN) and flags (0) to the forest's size."""
        k = len(self.dirf.child)
        if len(self.dir_err) < k:
            self.dir_err = np.concatenate([self.dir_err,
                                           np.full(k - len(self.dir_err), np.nan, np.float32)])
            self.dir_flags = np.concatenate([self.dir_flags,
                                             np.zeros(k - len(self.dir_flags), np.uint8)])

    def record(self, nodes, err, flags) -> None:
        """Store the measured error (degrees) and flags of direction ``nodes``."""
        self.grow_records()
        self.dir_err[nodes] = err
        self.dir_flags[nodes] = flags

    def add_extras(self, ex: dict) -> None:
        """Append extra samples (``ex_*`` arrays) and keep them sorted by node."""
        self.ex = {k: np.concatenate([self.ex[k], ex[k]]) for k in self.ex}
        order = np.argsort(self.ex["ex_node"])
        self.ex = {k: v[order] for k, v in self.ex.items()}


def take(s: Samples, idx) -> Samples:
    """The samples ``idx`` of ``s``."""
    return Samples(**{k: getattr(s, k)[idx] for k in SAMPLE_FIELDS})


def classes(samples, ids, class_of) -> np.ndarray:
    """Class of sample ids (-1: misses the object)."""
    p = samples.patch[ids]
    return np.where(p >= 0, class_of[np.maximum(p, 0)], -1)
