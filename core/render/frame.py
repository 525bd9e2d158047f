"""One frame pipeline for every renderer: camera rays -> environment hit and box entry -> the
specular objects (each through its RI-Tree or exactly; the nearest hit wins) -> shading (what
the rays leaving an object meet: the environment or another object) -> film.

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
        rays = self.st.object_function(origins, dirs, tmax, fresnel_tree=True)
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
class Specular:
    """One specular object of a frame: its SceneTracer (of the scene's ``view`` for it: the
    object alone, the environment shared: trace.scene_tracer.object_tracers) and the answerer
    of its rays."""
    st: object
    answerer: object


@dataclass
class ObjectShare:
    """What one specular object answered in a share."""
    handed: np.ndarray         # indices (into the share) of the rays handed to the object
    answer: ObjectAnswer       # the answerer's result for the handed rays, in their order
    won: np.ndarray            # (handed,) bool: the object is the ray's nearest hit

    @property
    def hit(self) -> np.ndarray:
        """Indices (into the share) of the rays whose nearest hit is this object."""
        return self.handed[self.won]


@dataclass
class ShareResult:
    """One share rendered: colours, which rays went to each specular object and what it
    answered (``objects``, in the scene's order)."""
    color: np.ndarray          # (n, 3) linear RGB of the share's camera rays
    objects: list[ObjectShare]
    stats: dict                # counts and seconds (summed over shares by sum_stats)

    @property
    def handed(self) -> np.ndarray:
        """The rays handed to the first object (the only one in a scene of one)."""
        return self.objects[0].handed

    @property
    def answer(self) -> ObjectAnswer:
        """The first object's answer (the only one in a scene of one)."""
        return self.objects[0].answer

    @property
    def hit(self) -> np.ndarray:
        """Indices (into the share) of the rays that hit a specular object, ascending."""
        if len(self.objects) == 1:
            return self.objects[0].hit
        return np.sort(np.concatenate([o.hit for o in self.objects]))


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


# Specular objects one camera ray may meet in a chain (a glass object seen in a mirror seen in
# another is three): each link is one more answer pass over the rays still meeting objects, and
# two mirrors facing each other would otherwise bounce a ray to no end; past the last link the
# environment alone shades what an object's output rays meet.
MAX_OBJECT_CHAIN = 3


def box_entries(objs: list[Specular], origins, dirs, skip: int = -1) -> list:
    """Each object's box entry distance of the rays (None for object ``skip``)."""
    return [None if k == skip else o.st.box_entry(origins, dirs) for k, o in enumerate(objs)]


def nearest_objects(objs: list[Specular], origins, dirs, tmax, entry: list
                    ) -> list[ObjectShare | None]:
    """Each object's answer for the rays whose box entry (``entry``: ``box_entries``) lies
    before their nearest hit so far (``tmax``: the environment's, then the nearer objects'),
    in the objects' order; the nearest hit wins (``ObjectShare.won``). An object without
    entries (the one the rays leave) gets none (None)."""
    best = np.array(tmax, np.float64, copy=True)
    winner = np.full(len(origins), -1)
    found: list = []
    for k, obj in enumerate(objs):
        if entry[k] is None:
            found.append(None)
            continue
        handed = np.flatnonzero(entry[k] < best)
        ans = obj.answerer(origins[handed], dirs[handed], best[handed])
        rows = handed[ans.rays.hit]
        best[rows] = np.minimum(best[rows], ans.rays.t_first[ans.rays.hit])
        winner[rows] = k
        found.append((handed, ans))
    return [None if f is None else ObjectShare(f[0], f[1], winner[f[0]] == k)
            for k, f in enumerate(found)]


def shade_carried(objs: list[Specular], k: int, obj: ObjectRays, chain: int = 1
                  ) -> tuple[np.ndarray, dict]:
    """(1 - diffuse) * tint * the colour the output ray carries (and, for dielectrics, the
    Fresnel-weighted reflection and, where traced exactly, the colour of the Fresnel tree's
    other branches: ObjectRays.out_weight, branch_color) for rays that hit object ``k``; what
    those rays meet is shaded by ``shade_leaving``. The local illumination is added separately
    (it is object-only work, this is environment work)."""
    mat = objs[k].st.scene.object.material
    carried = np.zeros((len(obj.hit), 3))
    ok = ~obj.null
    counts = {"output_rays": int(ok.sum()), "null_rays": int(obj.null.sum())}
    if np.any(ok):
        carried[ok] = shade_leaving(objs, k, obj.out_origin[ok], obj.out_dir[ok], chain, counts)
    if mat.kind == "dielectric":
        fr = obj.fresnel[:, None]
        refl = shade_leaving(objs, k, obj.point, obj.refl_dir, chain, counts)
        carried = fr * refl + (1.0 - fr) * (obj.out_weight[:, None] * carried
                                            + obj.branch_color)
        counts["reflected_rays"] = len(obj.point)
    return (1.0 - mat.diffuse) * np.asarray(mat.tint) * carried, counts


def shade_leaving(objs: list[Specular], k: int, origins, dirs, chain: int, counts: dict
                  ) -> np.ndarray:
    """(N, 3) colour seen along rays leaving object ``k``, the ``chain``-th object on their
    way from the camera: the environment's, or another specular object's where one is nearer
    (answered by its answerer, shaded in turn) while the chain is shorter than
    MAX_OBJECT_CHAIN. ``counts["chained_hits"]`` adds the rays another object answered."""
    env = objs[k].st.env
    if len(objs) == 1 or chain >= MAX_OBJECT_CHAIN:
        return env.shade_rays(origins, dirs)
    env_hits = env.closest(origins, dirs)
    col = np.zeros((len(origins), 3))
    met = np.zeros(len(origins), bool)
    entry = box_entries(objs, origins, dirs, skip=k)
    for j, share in enumerate(nearest_objects(objs, origins, dirs, env_hits.t, entry)):
        if share is None or not share.won.any():
            continue
        rows, obj = share.hit, share.answer.rays.take(share.won)
        local = local_illumination(obj.point, obj.normal, dirs[rows],
                                   objs[j].st.scene.object.material, env)
        carried, sub = shade_carried(objs, j, obj, chain + 1)
        col[rows] = local + carried
        met[rows] = True
        counts["chained_hits"] = counts.get("chained_hits", 0) + len(rows) \
            + sub.get("chained_hits", 0)
    rest = np.flatnonzero(~met)
    col[rest] = env.shade_rays(origins[rest], dirs[rest], hits=env_hits.take(rest))
    return col


def shade_share(st, origins, dirs, answerer, others: tuple = ()) -> ShareResult:
    """Colours of one share of camera rays; the rays whose box entry lies in front of the
    nearest environment hit are handed to ``answerer`` (the object of ``st``) and to each of
    the scene's ``others`` (Specular), the nearest hit winning; a scene of one object makes
    no pass more than that object needs."""
    objs = [Specular(st, answerer), *others]
    t0, c0 = time.perf_counter(), time.process_time()
    stats: dict = {}
    clock = _Clock(stats)
    n = len(origins)
    col = np.zeros((n, 3))
    env_hits = st.env.closest(origins, dirs)       # found once: reused by the rays that miss
    clock.lap("environment_hit")                    # the objects
    entry = box_entries(objs, origins, dirs)
    c1 = clock.lap("box_entry")
    # object-only (the paper's measure): output rays and the objects' local illumination
    t1 = time.perf_counter()
    found = nearest_objects(objs, origins, dirs, env_hits.t, entry)
    clock.lap("object")
    hits = [f.answer.rays.take(f.won) for f in found]
    local = [local_illumination(h.point, h.normal, dirs[f.hit], o.st.scene.object.material,
                                st.env) for f, h, o in zip(found, hits, objs)]
    c_obj, t_obj = clock.lap("local_light") - c1, time.perf_counter() - t1
    counts: dict = {}
    for k, (f, h) in enumerate(zip(found, hits)):
        carried, c = shade_carried(objs, k, h)
        col[f.hit] = local[k] + carried
        counts = sum_stats([counts, c])
    clock.lap("carried")
    rest = np.ones(n, bool)
    for f in found:
        rest[f.hit] = False
    rest = np.flatnonzero(rest)
    col[rest] = st.env.shade_rays(origins[rest], dirs[rest], hits=env_hits.take(rest))
    clock.lap("environment_shade")
    stats.update({"camera_rays": n, "object_candidates": sum(len(f.handed) for f in found),
                  "object_hits": sum(len(h.hit) for h in hits),
                  "events": sum(int(h.events.sum()) for h in hits), "object_cpu_s": c_obj,
                  "object_wall_s": t_obj, "total_cpu_s": time.process_time() - c0,
                  "total_wall_s": time.perf_counter() - t0, **counts,
                  **sum_stats(f.answer.stats for f in found)})
    return ShareResult(color=col, objects=found, stats=stats)


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
    object_mask: np.ndarray    # (n,) bool: the ray hit a specular object
    answer: np.ndarray         # (n,) int8 answer code of the nearest object hit (else of the
                               # first handed the ray); NOT_HANDED off every object's box
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
        for o in p.objects[::-1]:         # a ray's first object's code, its nearest's if any
            if o.answer.answer is not None:
                answer[o.handed + off] = o.answer.answer
                why[o.handed + off] = o.answer.why
        for o in p.objects[1:]:
            if o.answer.answer is not None:
                answer[o.hit + off] = o.answer.answer[o.won]
                why[o.hit + off] = o.answer.why[o.won]
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
                 per_worker: int = 1, others: tuple = ()) -> FilmedFrame:
    """Render ``film``'s camera rays in shares over ``workers`` processes (forked: they
    inherit ``st``, ``answerer`` and the scene's ``others`` (Specular); each makes its share's
    rays and develops their colours); ``progress(fraction)`` is called as shares finish and
    may raise to stop."""
    workers = workers_default() if workers is None else workers

    def work(a, b):
        share = shade_share(st, *film.rays(a, b), answerer, others)
        hit = np.zeros(b - a)
        hit[share.hit] = 1.0
        return film.develop(a, b, {"color": share.color}, {"object": hit}), share.stats

    t0 = time.perf_counter()
    parts = map_chunks(work, film.n_rays, share_size(film.n_rays, workers, per_worker),
                       workers, progress)
    return FilmedFrame(film.join(p[0] for p in parts), sum_stats(p[1] for p in parts),
                       len(parts), time.perf_counter() - t0)
