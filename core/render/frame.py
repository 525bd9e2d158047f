"""One frame pipeline for every renderer: camera rays -> environment hit and box entry -> the
object (through the RI-Tree or exactly) -> shading -> film.

A frame is cut into *shares* (``share_size``: one per worker, more only where memory asks for
it); each stage runs once per share over whole arrays. What answers the object's rays is an
*answerer*: a callable ``(origins, dirs, tmax) -> ObjectAnswer``, exact tracing
(``ExactAnswerer``) or an RI-Tree query (``TreeAnswerer``). ``shade_share`` renders one share;
``render_frame`` renders a frame's shares over worker processes and develops them on its film
(render/film.py: samples per pixel, pixel filter). Every stage's
CPU seconds (this process's CPU clock) land in the share's stats as ``stage_<name>_cpu_s``; the
paper's *object-only* time is ``object_cpu_s`` (f plus the object's local illumination) and the
*total* ``total_cpu_s``, with wall-clock twins ``*_wall_s``.
"""

from __future__ import annotations

import resource
import time
from dataclasses import dataclass, field

import numpy as np

from ..parallel import map_chunks, workers_default
from ..trace.objectfn import ObjectRays
from ..trace.shading import local_illumination
from .film import Developed, Film

# Most camera rays per share: bounds a share's working memory (about 1 GiB for the exact
# tracer's and the RI-Tree query's arrays) while keeping tracer calls large.
SHARE_RAYS = 1 << 18
NOT_HANDED = -1      # answer code of a ray never handed to the object (its box lies behind)


@dataclass
class ObjectAnswer:
    """The object's answer for the rays handed to it, in their order."""
    rays: ObjectRays                     # f of the rays (hit, first hit, output ray)
    answer: np.ndarray | None = None     # int8 answer code a ray (ritree.query); None: exact
    why: np.ndarray | None = None        # int8 reason a ray was traced (ritree.query)
    stats: dict = field(default_factory=dict)   # counts and CPU seconds of the answerer


def tracer_work(st, before: dict) -> dict:
    """The exact tracer's work counters (pairs, Newton iterations, fallback pairs) since
    ``before`` (a copy of ``st.tracer.stats``)."""
    return {k: st.tracer.stats[k] - before[k] for k in before}


class ExactAnswerer:
    """Every ray traced exactly; the stats hold the tracer's work counters for these rays."""

    def __init__(self, st):
        self.st = st

    def __call__(self, origins, dirs, tmax) -> ObjectAnswer:
        before = dict(self.st.tracer.stats)
        rays = self.st.object_function(origins, dirs, tmax)
        return ObjectAnswer(rays=rays, stats=tracer_work(self.st, before))


class TreeAnswerer:
    """Rays answered by an RI-Tree query (``ritree.query.TreeQuery``), which traces what the
    tree cannot answer; the stats hold the query's counts and stage seconds and the tracer's
    work counters for the rays it traced."""

    def __init__(self, query):
        self.query = query

    def __call__(self, origins, dirs, tmax) -> ObjectAnswer:
        before = dict(self.query.st.tracer.stats)
        rays, answer, why, stats = self.query(origins, dirs, tmax)
        return ObjectAnswer(rays=rays, answer=answer, why=why,
                            stats={**stats, **tracer_work(self.query.st, before)})


@dataclass
class ShareResult:
    """One share rendered: colours, which rays went to the object and what it answered."""
    color: np.ndarray          # (n, 3) linear RGB of the share's camera rays
    handed: np.ndarray         # indices (into the share) of the rays handed to the object
    hit: np.ndarray            # indices (into the share) of the rays that hit the object
    answer: ObjectAnswer       # the answerer's result for the handed rays
    stats: dict                # counts and seconds (summed over shares by sum_stats)


class _Clock:
    """CPU and wall seconds of named stages, added to a stats dict."""

    def __init__(self, stats: dict):
        self.stats = stats
        self.cpu, self.wall = time.process_time(), time.perf_counter()

    def lap(self, stage: str) -> float:
        cpu, wall = time.process_time(), time.perf_counter()
        self.stats[f"stage_{stage}_cpu_s"] = cpu - self.cpu
        self.cpu, self.wall = cpu, wall
        return cpu


def shade_carried(st, obj: ObjectRays) -> tuple[np.ndarray, dict]:
    """(1 - diffuse) * tint * the colour the output ray carries from the environment (and, for
    dielectrics, the Fresnel-weighted reflection) for rays that hit the object; the local
    illumination is added separately (it is object-only work, this is environment work)."""
    mat = st.scene.object.material
    carried = np.zeros((len(obj.hit), 3))
    ok = ~obj.null
    counts = {"output_rays": int(ok.sum()), "null_rays": int(obj.null.sum())}
    if np.any(ok):
        carried[ok] = st.env.shade_rays(obj.out_origin[ok], obj.out_dir[ok])
    if mat.kind == "dielectric":
        fr = obj.fresnel[:, None]
        refl = st.env.shade_rays(obj.point, obj.refl_dir)
        carried = fr * refl + (1.0 - fr) * carried
        counts["reflected_rays"] = len(obj.point)
    return (1.0 - mat.diffuse) * np.asarray(mat.tint) * carried, counts


def shade_share(st, origins, dirs, answerer) -> ShareResult:
    """Colours of one share of camera rays; the rays whose box entry lies in front of the
    nearest environment hit are handed to ``answerer``."""
    t0, c0 = time.perf_counter(), time.process_time()
    stats: dict = {}
    clock = _Clock(stats)
    n = len(origins)
    col = np.zeros((n, 3))
    env_hits = st.env.closest(origins, dirs)       # found once: reused by the rays that miss
    env_t = env_hits.t                              # the object
    clock.lap("environment_hit")
    handed = np.flatnonzero(st.box_entry(origins, dirs) < env_t)
    c1 = clock.lap("box_entry")
    # object-only (the paper's measure): output rays and the object's local illumination
    t1 = time.perf_counter()
    ans = answerer(origins[handed], dirs[handed], env_t[handed])
    hit = handed[ans.rays.hit]
    obj = ans.rays.take(ans.rays.hit)
    clock.lap("object")
    local = local_illumination(obj.point, obj.normal, dirs[hit], st.scene.object.material, st.env)
    c_obj, t_obj = clock.lap("local_light") - c1, time.perf_counter() - t1
    carried, counts = shade_carried(st, obj)
    col[hit] = local + carried
    clock.lap("carried")
    rest = np.ones(n, bool)
    rest[hit] = False
    rest = np.flatnonzero(rest)
    col[rest] = st.env.shade_rays(origins[rest], dirs[rest], hits=env_hits.take(rest))
    clock.lap("environment_shade")
    stats.update({"camera_rays": n, "object_candidates": len(handed), "object_hits": len(hit),
                  "events": int(obj.events.sum()), "object_cpu_s": c_obj, "object_wall_s": t_obj,
                  "total_cpu_s": time.process_time() - c0,
                  "total_wall_s": time.perf_counter() - t0, **counts, **ans.stats})
    return ShareResult(color=col, handed=handed, hit=hit, answer=ans, stats=stats)


def sum_stats(dicts) -> dict:
    """Key-wise sums of stats dicts (keys missing from some count as 0)."""
    out: dict = {}
    for d in dicts:
        for k, v in d.items():
            out[k] = out.get(k, 0) + v
    return out


def share_size(n: int, workers: int, per_worker: int = 1) -> int:
    """Rays per share of an n-ray frame: ``per_worker`` shares per worker (more give finer
    progress and cancel steps, fewer give larger tracer batches), split further to stay within
    SHARE_RAYS."""
    shares = max(int(workers) * int(per_worker), -(-n // SHARE_RAYS), 1)
    return max(1, -(-n // shares))


def peak_rss_mib() -> float:
    """Peak resident memory (MiB) of this process or of any finished child (a worker pool)."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(_own_peak_rss_kib(), children) / 1024.0


def _own_peak_rss_kib() -> int:
    """This process's peak resident memory (KiB): Linux's VmHWM where /proc has it, since
    getrusage's figure also holds the peak of the process that started this one (a program
    started from Blender would report Blender's memory); else getrusage's."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


@dataclass
class FrameResult:
    """A frame's camera rays rendered, in ray order (row-major, top row first)."""
    color: np.ndarray          # (n, 3) linear RGB
    object_mask: np.ndarray    # (n,) bool: the ray hit the object
    answer: np.ndarray         # (n,) int8 answer code; NOT_HANDED off the object's box
    why: np.ndarray            # (n,) int8 reason a ray was traced (0 where none)
    stats: dict                # summed over shares
    shares: int
    wall_s: float              # wall seconds of the shares' rendering


def join_shares(parts: list[ShareResult], wall_s: float) -> FrameResult:
    """One FrameResult from consecutive shares."""
    sizes = [len(p.color) for p in parts]
    n = int(sum(sizes))
    mask = np.zeros(n, bool)
    answer = np.full(n, NOT_HANDED, np.int8)
    why = np.zeros(n, np.int8)
    off = 0
    for p, size in zip(parts, sizes):
        mask[p.hit + off] = True
        if p.answer.answer is not None:
            answer[p.handed + off] = p.answer.answer
            why[p.handed + off] = p.answer.why
        off += size
    color = np.concatenate([p.color for p in parts]) if parts else np.zeros((0, 3))
    return FrameResult(color=color, object_mask=mask, answer=answer, why=why,
                       stats=sum_stats(p.stats for p in parts), shares=len(parts),
                       wall_s=wall_s)


@dataclass
class FilmedFrame:
    """A frame's camera rays rendered and developed on its film (render/film.py)."""
    developed: Developed       # image "color"; box "object" (rays that hit the object)
    stats: dict                # summed over shares
    shares: int
    wall_s: float              # wall seconds of the shares' rendering


def render_frame(st, film: Film, answerer, workers=None, progress=None,
                 per_worker: int = 1) -> FilmedFrame:
    """Render ``film``'s camera rays in shares over ``workers`` processes (forked: they
    inherit ``st`` and ``answerer``; each makes its share's rays and develops their colours);
    ``progress(fraction)`` is called as shares finish and may raise to stop."""
    workers = workers_default() if workers is None else workers

    def work(a, b):
        share = shade_share(st, *film.rays(a, b), answerer)
        hit = np.zeros(b - a)
        hit[share.hit] = 1.0
        return film.develop(a, b, {"color": share.color}, {"object": hit}), share.stats

    t0 = time.perf_counter()
    parts = map_chunks(work, film.n_rays, share_size(film.n_rays, workers, per_worker),
                       workers, progress)
    return FilmedFrame(film.join(p[0] for p in parts), sum_stats(p[1] for p in parts),
                       len(parts), time.perf_counter() - t0)
