"""Exact-tracer benchmark (``riray bench-exact``): each sample scene's close view rendered exactly.

Per scene: scene construction and acceleration-structure build time, the render's wall time at
SIZE x SIZE over the worker processes, object-only and total time summed over chunks (CPU-side
seconds, the paper's split), object rays per object-only second (rays handed to f /
object-only seconds), and machine-independent work per object ray: BVH candidate pairs solved
by Newton, Newton iterations, de Casteljau fallback pairs and surface events. The environment
pass per ray: its stages' CPU microseconds (environment hit, carried and environment shading)
over the rays it handled (camera rays, the object's output and reflected rays), beside its
numpy floor (bench/env_floor.py) on the view's camera rays. Output: a Markdown table on stdout
and the same rows (plus the machine) as JSON.
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from ..render.exact import render_exact
from ..scene.camera import Shot, camera_rays
from ..trace.scene_tracer import SceneTracer
from ..scene.samples import SAMPLES, build
from .env_floor import floor_cpu_s

COLUMNS = (  # (key, header, format)
    ("scene", "scene", "{}"),
    ("scene_s", "scene s", "{:.2f}"),
    ("build_s", "build s", "{:.2f}"),
    ("wall_s", "render wall s", "{:.2f}"),
    ("object_cpu_s", "object-only s", "{:.2f}"),
    ("total_cpu_s", "total s", "{:.2f}"),
    ("object_rays", "object rays", "{:d}"),
    ("object_rays_per_s", "object rays/s", "{:,.0f}"),
    ("pairs_per_ray", "pairs/ray", "{:.2f}"),
    ("newton_iters_per_ray", "Newton it/ray", "{:.2f}"),
    ("fallback_pairs_per_ray", "fallback/ray", "{:.3f}"),
    ("events_per_ray", "events/ray", "{:.2f}"),
    ("environment_cpu_us_per_ray", "env CPU us/ray", "{:.2f}"),
    ("environment_floor_cpu_us_per_ray", "env floor CPU us/ray", "{:.2f}"),
)
ENV_STAGES = ("environment_hit", "carried", "environment_shade")   # frame.py's stage names


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict:
    """What the numbers were measured on."""
    return {"platform": platform.platform(), "processor": _cpu_model(),
            "cpu_count": os.cpu_count(), "python": platform.python_version(),
            "numpy": np.__version__}


def bench_scene(name: str, size: int = 300, camera: str = "close", workers: int | None = None,
                progress=None) -> dict:
    """One row: build and render ``name``'s ``camera`` view exactly at size x size."""
    t0 = time.perf_counter()
    scene = build(name)
    t1 = time.perf_counter()
    st = SceneTracer(scene)
    t2 = time.perf_counter()
    res = render_exact(st, Shot(camera=camera, width=size, height=size), workers=workers,
                       progress=progress)
    c, s = res.stats["counts"], res.stats["summary"]
    rays = max(int(c["object_candidates"]), 1)
    env_rays = c["camera_rays"] + c.get("output_rays", 0) + c.get("reflected_rays", 0)
    env_cpu = sum(c[f"stage_{k}_cpu_s"] for k in ENV_STAGES)
    o, d = camera_rays(*Shot(camera=camera, width=size, height=size).resolve(scene))
    floor = floor_cpu_s(st.env, o, d, st.env.closest(o, d).tri)
    return {
        "scene": name, "camera": camera, "size": size,
        "scene_s": t1 - t0, "build_s": t2 - t1, "wall_s": float(s["wall_s"]),
        "object_cpu_s": float(c["object_cpu_s"]), "total_cpu_s": float(c["total_cpu_s"]),
        "object_rays": int(c["object_candidates"]), "object_hits": int(c["object_hits"]),
        "object_rays_per_s": c["object_candidates"] / max(c["object_cpu_s"], 1e-9),
        "pairs_per_ray": c["pairs"] / rays, "newton_iters_per_ray": c["newton_iters"] / rays,
        "fallback_pairs_per_ray": c["fallback_pairs"] / rays, "events_per_ray": c["events"] / rays,
        "null_rays": int(c.get("null_rays", 0)),
        "environment_cpu_s": env_cpu, "environment_rays": int(env_rays),
        "environment_cpu_us_per_ray": 1e6 * env_cpu / max(env_rays, 1),
        "environment_floor_cpu_us_per_ray": 1e6 * floor / max(len(o), 1),
    }


def table(rows: list[dict]) -> str:
    """The rows as a Markdown table."""
    lines = ["| " + " | ".join(h for _, h, _ in COLUMNS) + " |",
             "|" + "|".join("---" if k == "scene" else "---:" for k, _, _ in COLUMNS) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(f.format(r[k]) for k, _, f in COLUMNS) + " |")
    return "\n".join(lines)


def run(scenes=SAMPLES, size: int = 300, camera: str = "close", workers: int | None = None,
        out: str | os.PathLike | None = None, progress_factory=None) -> dict:
    """Benchmark ``scenes``; returns (and writes to ``out`` as JSON) {"machine", "settings",
    "rows"}. ``progress_factory(label)`` gives each render's progress callback."""
    from ..parallel import workers_default
    for name in scenes:
        if name not in SAMPLES:
            raise ValueError(f"scenes: unknown sample {name!r}; samples: {', '.join(SAMPLES)}")
    if size < 1:
        raise ValueError(f"size: must be >= 1 (got {size})")
    nworkers = workers_default() if workers is None else max(1, int(workers))
    rows = []
    for name in scenes:
        prog = progress_factory(f"{name}/{camera} {size}x{size}") if progress_factory else None
        rows.append(bench_scene(name, size, camera, nworkers, prog))
    result = {"machine": machine(),
              "settings": {"scenes": list(scenes), "size": size, "camera": camera,
                           "workers": nworkers,
                           "command": f"riray bench-exact --scenes {' '.join(scenes)} "
                                      f"--size {size} --camera {camera} --workers {nworkers}"},
              "rows": rows}
    if out is not None:
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=2) + "\n")
    return result

