"""The reference renderer: every camera ray that reaches the object is traced exactly.

Per pixel (one ray per pixel, as in the paper): the environment is traced first so the object
is only asked about rays whose box entry lies in front of the nearest environment hit; f gives
the output ray(s) and first hit; the output rays are traced through the environment; local
illumination of the first hit is blended with the colour they carry (paper 5.4).

Stats follow the paper's tables: *object-only* time (f plus the object's local illumination)
and *total* time, each as CPU seconds (this process's CPU clock, ``*_cpu_s``) and wall seconds
(``*_wall_s``), with ray counts. The frame is rendered in a few large *shares* (one per worker,
more only where memory asks for it), so the tracer is called on whole-share batches.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..geometry.tessellate import tessellate
from ..parallel import map_chunks, workers_default
from ..scene.model import Mesh, Scene
from ..trace.boxes import slab_intervals
from ..trace.meshes import MeshSet
from ..trace.objectfn import SECONDARY_T_MIN_REL, ObjectRays, trace_object
from ..trace.patches import PatchTracer
from ..trace.shading import Environment, local_illumination
from .camera import camera_rays
from .image import write_float_image, write_png

# Most camera rays per share: bounds a share's working memory (about 1 GiB for the exact
# tracer's and the RI-Tree query's arrays) while keeping tracer calls large.
SHARE_RAYS = 1 << 18
# Grid resolution of the shadow proxy per NURBS patch (triangles are only shadow casters).
PROXY_GRID = 16


class SceneTracer:
    """A scene with its acceleration structures built once: the object's patch tracer and the
    environment (meshes, lights, world; the object's tessellated proxy as shadow caster when
    some light casts shadows)."""

    def __init__(self, scene: Scene):
        self.scene = scene
        self.tracer = PatchTracer(scene.object)
        occluder = None
        if any(light.shadows for light in scene.lights):
            occluder = MeshSet([_proxy_mesh(p) for p in scene.object.patches])
        self.env = Environment(scene, occluder=occluder)
        self.box_lo = self.tracer.lo - 1e-6 * self.tracer.diag
        self.box_hi = self.tracer.hi + 1e-6 * self.tracer.diag

    def object_function(self, origins, dirs, tmax=None, first=None) -> ObjectRays:
        """f of the rays (trace_object; ``first``: first hits already found, see there)."""
        return trace_object(self.tracer, self.scene.object.material, origins, dirs,
                            self.scene.render.max_events, tmax=tmax, first=first)

    def box_entry(self, origins, dirs):
        """Distance at which each ray enters the object's bounding box (inf if it misses)."""
        return slab_entry(origins, dirs, self.box_lo, self.box_hi)


def slab_entry(o, d, lo, hi):
    """Entry distance (>= 0) of rays into the box [lo, hi]; inf where they miss it."""
    tnear, tfar = slab_intervals(o, d, lo, hi)
    tn = np.maximum(tnear.max(axis=1), 0.0)
    tf = tfar.min(axis=1)
    return np.where(tn <= tf, tn, np.inf)


# Camera-inside test: rays from the camera position in these fixed directions (unit after
# normalization; generic, so they avoid the axes, poles and seams of revolved samples) count
# their crossings of the object until they escape; an odd count for the majority means inside.
INSIDE_DIRS = np.array([[0.267, 0.534, 0.802], [-0.713, 0.297, -0.635], [0.439, -0.818, 0.371],
                        [-0.182, -0.391, -0.902], [0.858, 0.137, -0.495], [-0.577, 0.761, 0.296],
                        [0.093, -0.274, 0.957]])
INSIDE_DIRS = INSIDE_DIRS / np.linalg.norm(INSIDE_DIRS, axis=1)[:, None]
INSIDE_MAX_CROSSINGS = 64   # a direction still hitting after this many is left out of the vote


def point_inside(st: SceneTracer, p) -> bool:
    """Whether ``p`` lies inside the object (crossing parity along INSIDE_DIRS, majority vote);
    False without tracing when ``p`` is outside the object's bounding box."""
    p = np.asarray(p, dtype=np.float64)
    if np.any(p < st.box_lo) or np.any(p > st.box_hi):
        return False
    k = len(INSIDE_DIRS)
    o, d = np.tile(p, (k, 1)), INSIDE_DIRS.copy()
    crossings = np.zeros(k, np.int64)
    live = np.arange(k)
    tmin = SECONDARY_T_MIN_REL * st.tracer.diag
    for _ in range(INSIDE_MAX_CROSSINGS):
        h = st.tracer.intersect(o[live], d[live], tmin=np.full(len(live), tmin))
        live = live[h.hit]
        if len(live) == 0:
            break
        crossings[live] += 1
        o[live] = h.point[h.hit]
    decided = np.ones(k, bool)
    decided[live] = False
    return int((crossings[decided] % 2 == 1).sum()) * 2 > int(decided.sum())


def _proxy_mesh(patch) -> Mesh:
    if patch.surface is None:
        return Mesh(name=patch.name, vertices=patch.vertices, triangles=patch.triangles, material="")
    v, t = tessellate(patch.surface, PROXY_GRID, PROXY_GRID)
    return Mesh(name=patch.name, vertices=v, triangles=t, material="")


def shade_carried(st: SceneTracer, obj: ObjectRays) -> tuple[np.ndarray, dict]:
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


@dataclass
class RenderResult:
    image: np.ndarray                       # (H, W, 3) linear RGB
    stats: dict = field(default_factory=dict)
    masks: dict = field(default_factory=dict)   # name -> (H, W) bool or float images


def share_size(n: int, workers: int, per_worker: int = 1) -> int:
    """Rays per share of an n-ray frame: ``per_worker`` shares per worker (more give finer
    progress and cancel steps, fewer give larger tracer batches), split further to stay within
    SHARE_RAYS."""
    shares = max(int(workers) * int(per_worker), -(-n // SHARE_RAYS), 1)
    return max(1, -(-n // shares))


def peak_rss_mib() -> float:
    """Peak resident memory (MiB) of this process or of any finished child (a worker pool)."""
    import resource
    kib = max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
              resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
    return kib / 1024.0


def render_pixels(st: SceneTracer, origins, dirs, object_fn):
    """Colours of camera rays; ``object_fn(o, d, tmax) -> (ObjectRays, extra)`` answers the rays
    that may reach the object (exact tracing, or the RI-Tree). Returns (colours, stats, indices
    of the rays that hit the object, indices of the rays handed to ``object_fn``)."""
    t0, c0 = time.perf_counter(), time.process_time()
    n = len(origins)
    col = np.zeros((n, 3))
    env_t = st.env.hit_distance(origins, dirs)
    box_t = st.box_entry(origins, dirs)
    cand = np.flatnonzero(box_t < env_t)
    # object-only (the paper's measure): output rays and the object's local illumination
    t1, c1 = time.perf_counter(), time.process_time()
    obj, extra = object_fn(origins[cand], dirs[cand], env_t[cand])
    hit = cand[obj.hit]
    obj = obj.take(obj.hit)
    local = local_illumination(obj.point, obj.normal, dirs[hit], st.scene.object.material, st.env)
    c_obj, t_obj = time.process_time() - c1, time.perf_counter() - t1
    carried, counts = shade_carried(st, obj)
    col[hit] = local + carried
    rest = np.ones(n, bool)
    rest[hit] = False
    col[rest] = st.env.shade_rays(origins[rest], dirs[rest])
    stats = {"camera_rays": n, "object_candidates": len(cand), "object_hits": len(hit),
             "events": int(obj.events.sum()), "object_cpu_s": c_obj, "object_wall_s": t_obj,
             "total_cpu_s": time.process_time() - c0, "total_wall_s": time.perf_counter() - t0,
             **counts, **extra}
    return col, stats, hit, cand


def _merge(stats_list):
    out = {}
    for s in stats_list:
        for k, v in s.items():
            out[k] = out.get(k, 0) + v
    return out


def render_exact(scene: Scene, camera=None, width=None, height=None, workers=None,
                 progress=None, st: SceneTracer | None = None) -> RenderResult:
    """Render ``camera`` (name or None for the first) exactly; sizes default to the scene's."""
    w = int(scene.render.width if width is None else width)
    h = int(scene.render.height if height is None else height)
    cam = scene.camera(camera)
    o, d = camera_rays(cam, w, h)
    wall0 = time.perf_counter()
    st = st or SceneTracer(scene)
    build_s = time.perf_counter() - wall0
    if point_inside(st, np.asarray(cam.matrix_world, dtype=np.float64)[:3, 3]):
        raise ValueError(f"camera {cam.name!r} is inside the object {scene.object.name!r}")

    def exact_fn(oo, dd, tmax):
        before = dict(st.tracer.stats)
        res = st.object_function(oo, dd, tmax)
        return res, {k: st.tracer.stats[k] - before[k] for k in before}

    def work(a, b):
        c, s, hit, _ = render_pixels(st, o[a:b], d[a:b], exact_fn)
        return c, s, hit + a

    workers = workers_default() if workers is None else workers
    wall1 = time.perf_counter()
    parts = map_chunks(work, len(o), share_size(len(o), workers), workers, progress)
    wall = time.perf_counter() - wall1
    col = np.concatenate([p[0] for p in parts]).reshape(h, w, 3)
    stats = _merge([p[1] for p in parts])
    hitmask = np.zeros(len(o), bool)
    for p in parts:
        hitmask[p[2]] = True
    summary = {
        "scene": scene.name, "camera": cam.name, "width": w, "height": h, "mode": "exact",
        "rays_traced": stats["object_candidates"], "object_pixels": stats["object_hits"],
        "object_only_cpu_s": round(stats["object_cpu_s"], 4),
        "total_cpu_s": round(stats["total_cpu_s"], 4),
        "wall_s": round(wall, 4), "build_s": round(build_s, 4),
        "peak_rss_mib": round(peak_rss_mib(), 1), "shares": len(parts),
        "object_rays_per_cpu_s": round(stats["object_candidates"] / max(stats["object_cpu_s"], 1e-9), 1),
    }
    return RenderResult(image=col, stats={"summary": summary, "counts": stats},
                        masks={"object": hitmask.reshape(h, w)})


def save_render(res: RenderResult, stem) -> list[Path]:
    """Write STEM.png (8-bit sRGB), STEM.npy (float32 linear) and STEM.json (stats)."""
    stem = Path(stem)
    if stem.suffix.lower() in (".png", ".npy", ".json"):
        stem = stem.with_suffix("")
    stem.parent.mkdir(parents=True, exist_ok=True)
    png, npy, js = stem.with_suffix(".png"), stem.with_suffix(".npy"), stem.with_suffix(".json")
    write_png(png, res.image)
    write_float_image(npy, res.image)
    js.write_text(json.dumps(res.stats, indent=2, default=float) + "\n")
    return [png, npy, js]
