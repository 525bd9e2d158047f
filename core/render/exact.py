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

from ..atomic import atomic_write_text
from ..scene.camera import camera_rays
from ..scene.model import Scene
from ..trace.scene_tracer import SceneTracer, check_camera_outside
from .frame import ExactAnswerer, ObjectAnswer, peak_rss_mib, render_frame, shade_share
from .frame import share_size  # noqa: F401  (transitional: the bench's import)
from .image import write_float_image, write_png


@dataclass
class RenderResult:
    image: np.ndarray                       # (H, W, 3) linear RGB
    stats: dict = field(default_factory=dict)
    masks: dict = field(default_factory=dict)   # name -> (H, W) bool or float images


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
    check_camera_outside(st, cam)

    frame = render_frame(st, o, d, ExactAnswerer(st), workers, progress)
    stats = frame.stats
    summary = {
        "scene": scene.name, "camera": cam.name, "width": w, "height": h, "mode": "exact",
        "rays_traced": stats["object_candidates"], "object_pixels": stats["object_hits"],
        "object_only_cpu_s": round(stats["object_cpu_s"], 4),
        "total_cpu_s": round(stats["total_cpu_s"], 4),
        "wall_s": round(frame.wall_s, 4), "build_s": round(build_s, 4),
        "peak_rss_mib": round(peak_rss_mib(), 1), "shares": frame.shares,
        "object_rays_per_cpu_s": round(stats["object_candidates"] / max(stats["object_cpu_s"], 1e-9), 1),
    }
    return RenderResult(image=frame.color.reshape(h, w, 3),
                        stats={"summary": summary, "counts": stats},
                        masks={"object": frame.object_mask.reshape(h, w)})


def save_render(res: RenderResult, stem) -> list[Path]:
    """Write STEM.png (8-bit sRGB), STEM.npy (float32 linear) and STEM.json (stats)."""
    stem = Path(stem)
    if stem.suffix.lower() in (".png", ".npy", ".json"):
        stem = stem.with_suffix("")
    stem.parent.mkdir(parents=True, exist_ok=True)
    png, npy, js = stem.with_suffix(".png"), stem.with_suffix(".npy"), stem.with_suffix(".json")
    write_png(png, res.image)
    write_float_image(npy, res.image)
    atomic_write_text(js, json.dumps(res.stats, indent=2, default=float) + "\n")
    return [png, npy, js]


def render_pixels(st: SceneTracer, origins, dirs, object_fn):
    """Transitional: the frame pipeline's shade_share over ``object_fn(o, d, tmax) ->
    (ObjectRays, extra)``; returns (colours, stats, hit indices, handed indices)."""
    def answerer(o, d, tmax):
        rays, extra = object_fn(o, d, tmax)
        return ObjectAnswer(rays=rays, stats=extra)
    share = shade_share(st, origins, dirs, answerer)
    return share.color, share.stats, share.hit, share.handed
