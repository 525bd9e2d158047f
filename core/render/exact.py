"""The reference renderer: every camera ray that reaches the object is traced exactly.

Per camera ray (one per pixel by default, as in the paper; ``Shot.samples`` per pixel, filtered
on the film, for anti-aliasing): the environment is traced first so the object
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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..files import atomic_write_text
from ..scene.camera import Shot, check_image_size
from ..trace.scene_tracer import SceneTracer, check_camera_outside
from .film import Film
from .frame import ExactAnswerer, Specular, peak_rss_mib, render_frame
from ..imageio import write_float_image, write_png


@dataclass
class RenderResult:
    image: np.ndarray                       # (H, W, 3) linear RGB
    stats: dict = field(default_factory=dict)
    masks: dict = field(default_factory=dict)   # name -> (H, W) bool or float images


def render_exact(st: SceneTracer, shot: Shot = Shot(), workers=None,
                 progress=None, others: tuple = ()) -> RenderResult:
    """Render ``shot`` of the scene ``st`` traces (SceneTracer) exactly, ``shot.samples`` rays
    per pixel; ``others``: the SceneTracers of the scene's other specular objects
    (scene_tracer.object_tracers). masks["object"]: with one sample, the pixels whose ray hit
    an object (bool); with more, the fraction of each pixel's samples that did (float in
    [0, 1])."""
    scene = st.scene
    cam, w, h = shot.resolve(scene)
    check_image_size(w, h)
    for s in (st, *others):
        check_camera_outside(s, cam)
    frame = render_frame(st, Film(cam, w, h, shot.samples), ExactAnswerer(st), workers,
                         progress, others=[Specular(s, ExactAnswerer(s)) for s in others])
    stats = frame.stats
    summary = {
        "scene": scene.name, "camera": cam.name, "width": w, "height": h, "mode": "exact",
        "samples": shot.samples,
        "rays_traced": stats["object_candidates"], "object_pixels": stats["object_hits"],
        "object_only_cpu_s": round(stats["object_cpu_s"], 4),
        "total_cpu_s": round(stats["total_cpu_s"], 4),
        "wall_s": round(frame.wall_s, 4),
        "peak_rss_mib": round(peak_rss_mib(), 1), "shares": frame.shares,
        "object_rays_per_cpu_s": round(stats["object_candidates"] / max(stats["object_cpu_s"], 1e-9), 1),
    }
    dev = frame.developed
    return RenderResult(image=dev.images["color"], stats={"summary": summary, "counts": stats},
                        masks={"object": dev.fraction("object")})


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

