"""The state of one query call (Batch): its rays, where they were located, their sample sets and
units, the partial results and the answer codes. Every stage is a function ``stage(q, b)`` of
the TreeQuery ``q`` (tree, table, opt, material, st: fixed across calls) and the Batch ``b``,
whose named fields it reads and writes."""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from ...trace.objectfn import ObjectRays
from ...trace.patches import PatchHit
from ..answers import MISS, TRACED
from ..locate import Located
from .sets import SampleSets
from .units import Units
from .weights import Weights


class StageClock:
    """CPU seconds (this process's CPU clock) spent per named stage of a query. A stage run
    inside another is that stage's time only, not the outer one's."""

    def __init__(self):
        self.cpu: dict[str, float] = {}
        self._inner: list[float] = []      # per open stage: the time of stages run inside it

    @contextmanager
    def __call__(self, name: str):
        t0 = time.process_time()
        self._inner.append(0.0)
        try:
            yield
        finally:
            spent = time.process_time() - t0
            inner = self._inner.pop()
            self.cpu[name] = self.cpu.get(name, 0.0) + spent - inner
            if self._inner:
                self._inner[-1] += spent


class KnownHits:
    """Exact first hits (against every patch, within the ray's tmax) the query found for some
    of its N rays, so that nothing searches them again."""

    def __init__(self, n: int):
        self.pos = np.full(n, -1, np.int64)       # row of each ray in the hits, -1: none
        self.pieces: list[PatchHit] = []

    def add(self, rays, hit: PatchHit) -> None:
        """Record the hits of rays ``rays`` (none recorded yet)."""
        self.pos[rays] = self._count() + np.arange(len(rays))
        self.pieces.append(hit)

    def _count(self) -> int:
        return sum(len(h.t) for h in self.pieces)

    def _all(self) -> PatchHit:
        if len(self.pieces) > 1:
            self.pieces = [PatchHit(**{f: np.concatenate([getattr(h, f) for h in self.pieces])
                                       for f in self.pieces[0].__dict__})]
        return self.pieces[0]

    def hit(self, rays) -> np.ndarray:
        """Whether each of ``rays`` (all recorded) hits the object."""
        return self._all().hit[self.pos[rays]]

    def of(self, rays):
        """(positions within ``rays`` that have a recorded hit, their PatchHit), or None."""
        p = self.pos[rays]
        k = np.flatnonzero(p >= 0)
        return (k, self._all().take(p[k])) if len(k) else None


def empty_result(o, d) -> ObjectRays:
    """Misses for every ray (output = input ray), to be filled in by the stages."""
    n = len(o)
    return ObjectRays(hit=np.zeros(n, bool), null=np.zeros(n, bool), out_origin=o.copy(),
                      out_dir=d.copy(), t_first=np.full(n, np.inf), point=np.zeros((n, 3)),
                      normal=np.zeros((n, 3)), patch=np.full(n, -1, np.int64),
                      cls=np.full(n, -1, np.int64), events=np.zeros(n, np.int64),
                      refl_dir=np.zeros((n, 3)), fresnel=np.zeros(n),
                      tree=np.zeros(n, np.uint32), uv=np.zeros((n, 2)), out_weight=np.ones(n),
                      branch_color=np.zeros((n, 3)))


@dataclass
class Batch:
    """One query call over N rays. Per query ray (N): the rays, the result, answer and why
    codes, the known exact first hits. The located rays ``loc`` (M) and, once grouped, their
    sample sets; ``go`` are the rows of ``loc`` not answered yet, and ``set_of``, ``pc``
    (class) and ``unit_of`` are per row of ``go`` (narrowed with it)."""

    o: np.ndarray                      # (N, 3) ray origins (object space)
    d: np.ndarray                      # (N, 3) unit directions
    tmax: np.ndarray                   # (N,) something in front ends the ray there
    res: ObjectRays                    # (N) the answers
    ans: np.ndarray                    # (N,) int8 answer codes (answers.MISS...)
    why: np.ndarray                    # (N,) int8 why a ray was traced (answers.WHY_...)
    known: KnownHits
    clock: StageClock
    must: np.ndarray                   # (N,) bool: only Newton's exact hit may answer the ray
    newton_ok: np.ndarray              # (N,) bool: Newton's exact hit answered the ray
    exact_first_hits: int = 0          # rays whose exact first hit picked their class
    certified_first_hits: int = 0      # exact first hits found without the full search
    exact_mirror_hits: int = 0         # mirror rays answered from Newton's exact hit
    solved: int = 0                    # rays solved along a sample's path (SOLVED)
    loc: Located | None = None         # (M) the rays that found their four leaves
    sets: SampleSets | None = None     # the located rays' sample sets (S)
    go: np.ndarray | None = None       # (G,) rows of ``loc`` not answered yet
    set_of: np.ndarray | None = None   # (G,) sample set of each
    pc: np.ndarray | None = None       # (G,) class (-1: miss, -2: traced)
    loc_pc: np.ndarray | None = None   # (M,) class of every located ray, as classified
    units: Units | None = None         # the (set, class) pairs of the open rays
    unit_of: np.ndarray | None = None  # (G,) unit of each (once units are formed)
    weights: Weights | None = None     # (G) their interpolation weights

    @classmethod
    def of(cls, o, d, tmax) -> "Batch":
        n = len(o)
        return cls(o=o, d=d, tmax=tmax, res=empty_result(o, d), ans=np.full(n, MISS, np.int8),
                   why=np.zeros(n, np.int8), known=KnownHits(n), clock=StageClock(),
                   must=np.zeros(n, bool), newton_ok=np.zeros(n, bool))

    def trace(self, rays, why: int) -> None:
        """Answer query rays ``rays`` by the exact tracer, for reason ``why``."""
        self.ans[rays] = TRACED
        self.why[rays] = why

    def narrow(self, keep) -> None:
        """Keep only the open rays ``keep`` (mask or positions among them)."""
        self.go = self.go[keep]
        self.set_of = self.set_of[keep]
        self.pc = self.pc[keep]
        if self.unit_of is not None:
            self.unit_of = self.unit_of[keep]
