"""The bake worker process: ``python worker.py JOB_DIR`` (Blender's bundled Python, or the
Python that imported the bpy module). Never imports bpy; never pickles.

JOB_DIR holds (written by riray_addon.jobs in Blender):
  job.json       {"task": "bake" | "estimate", "scene": "scene.json", "params": {...},
                  "output": "<cache>.tmp<pid>", "meta": {...},
                  "scheduler": "" | Dask scheduler address | "local:N"}
  scene.json     the core scene (object + cameras), riray JSON scene format
The worker writes:
  progress.json  {"fraction", "message", "time", "eta"} (atomically replaced, at most every
                 0.1 s; eta: core's estimate of the seconds left, when its message has one)
  result.json    {"status": "done" | "cancelled" | "failed", "error", "traceback", "bytes",
                  "estimate"} - last thing written (an estimate task: "estimate", the dict of
                  backend.estimate_bake, and no cache)
and stops early when the file JOB_DIR/cancel appears or its parent process goes away.

Imports: the extension folder (parent of riray_addon/) is mounted as a synthetic package whose
``riray_addon`` sub-package is also synthetic (its __init__ needs bpy and is not run), so
``riray_addon/backend.py`` and ``core`` import exactly as inside Blender (relative imports).
"""

from __future__ import annotations

import importlib
import json
import os
import re
import sys
import time
import traceback
import types

PKG = "_riray_worker_ext"
ETA_RE = re.compile(r"\(eta (\d+(?:\.\d+)?) s\)")     # core bake's progress message
PROGRESS_EVERY_S = 0.1
CANCEL_POLL_S = 0.05


def load_backend(ext_root: str):
    """riray_addon.backend imported below a synthetic package rooted at ``ext_root``."""
    if PKG not in sys.modules:
        root = types.ModuleType(PKG)
        root.__path__ = [ext_root]
        sys.modules[PKG] = root
        sub = types.ModuleType(f"{PKG}.riray_addon")
        sub.__path__ = [os.path.join(ext_root, "riray_addon")]
        sys.modules[sub.__name__] = sub
    return importlib.import_module(f"{PKG}.riray_addon.backend")


def _write_json(path: str, doc: dict) -> None:
    tmp = f"{path}.tmp"
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(doc, fh, default=float)
    os.replace(tmp, path)


def error_message(exc: BaseException) -> str:
    """What the user reads of a failed bake: core's refusals (ValueError) are written for them;
    anything else is a fault, named by its type."""
    return str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"


def run(job_dir: str) -> int:
    ext_root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with open(os.path.join(job_dir, "job.json"), encoding="utf-8") as fh:
        job = json.load(fh)
    progress_path = os.path.join(job_dir, "progress.json")
    result_path = os.path.join(job_dir, "result.json")
    cancel_path = os.path.join(job_dir, "cancel")
    parent = os.getppid()
    state = {"last": 0.0, "poll": 0.0, "cancelled": False}
    t0 = time.time()

    def progress(fraction: float, message: str = "") -> None:
        now = time.time()
        if now - state["last"] >= PROGRESS_EVERY_S or fraction >= 1.0:
            state["last"] = now
            eta = ETA_RE.search(str(message))
            _write_json(progress_path, {"fraction": float(min(max(fraction, 0.0), 1.0)),
                                        "message": str(message), "time": now - t0,
                                        "eta": float(eta[1]) if eta else None})

    def cancel() -> bool:
        now = time.time()
        if not state["cancelled"] and now - state["poll"] >= CANCEL_POLL_S:
            state["poll"] = now
            state["cancelled"] = os.path.exists(cancel_path) or os.getppid() != parent
        return state["cancelled"]

    output = job["output"]
    try:
        backend = load_backend(ext_root)
        from importlib import import_module
        io = import_module(f"{PKG}.core.scene.io")
        scene = io.load_scene(os.path.join(job_dir, job["scene"]))
        progress(0.0, "starting")
        if job.get("task") == "estimate":
            est = backend.estimate_bake(scene, job["params"], progress, cancel)
            _write_json(result_path, {"status": "done", "estimate": est,
                                      "time": time.time() - t0})
            return 0
        tree = backend.bake_tree(scene, job["params"], progress, cancel,
                                 job.get("scheduler", ""))
        if cancel():
            raise backend.BakeCancelled()
        meta = dict(job.get("meta", {}))
        meta["bake_s"] = time.time() - t0
        size = backend.save_tree(tree, output, meta, cancel,   # the bake is done: 100 %
                                 lambda f: progress(1.0, f"compressing the cache {100 * f:.0f}%"))
        progress(1.0, "done")
        _write_json(result_path, {"status": "done", "bytes": size, "time": time.time() - t0})
        return 0
    except BaseException as exc:      # noqa: BLE001 - everything is reported to the parent
        cancelled = type(exc).__name__ == "BakeCancelled" or isinstance(exc, KeyboardInterrupt)
        if os.path.exists(output):
            try:
                os.remove(output)
            except OSError:
                pass
        _write_json(result_path, {
            "status": "cancelled" if cancelled else "failed",
            "error": "" if cancelled else error_message(exc),
            "traceback": "" if cancelled else traceback.format_exc(),
            "time": time.time() - t0})
        return 0 if cancelled else 1


if __name__ == "__main__":
    if len(sys.argv) != 2:
        print("usage: worker.py JOB_DIR", file=sys.stderr)
        sys.exit(2)
    sys.exit(run(sys.argv[1]))
