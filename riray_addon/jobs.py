"""Bake jobs on Blender's side (no bpy): start the worker process, poll its progress, cancel it,
install the finished cache; estimate jobs alike, whose result is the estimate. Everything here
is called from Blender's main thread (a modal operator's timer, a bpy.app.timers function or a
blocking loop); the work itself runs in the worker process, so the UI never freezes.

Files: a private job folder (tempfile, removed when the job ends, however it ends) for
job.json / scene.json / progress / result / log; the cache is written by the worker to
``<cache>.tmp<pid>`` beside the final path and moved into place with os.replace only when the
bake finished, so a cancelled or failed bake keeps any previous cache untouched.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

from ..core.scene.io import save_scene

WORKER = os.path.join(os.path.dirname(os.path.abspath(__file__)), "worker.py")
CANCEL_GRACE_S = 5.0        # after a cancel request the worker is killed if still running


def python_executable() -> str:
    """The interpreter for the worker: $RIRAY_PYTHON, else this process's Python (Blender's
    bundled one inside Blender, the venv's with the bpy module)."""
    return os.environ.get("RIRAY_PYTHON") or sys.executable


class BakeJob:
    """One bake in a worker process. ``state``: running | done | cancelled | failed."""

    task = "bake"               # what the worker does (worker.py)

    def __init__(self, object_name: str, cache_path: str):
        self.object_name = object_name
        self.cache_path = cache_path
        self.state = "new"
        self.fraction = 0.0
        self.message = ""
        self.worker_eta = None          # (seconds left, at the worker's elapsed time) from core
        self.error = ""
        self.traceback = ""
        self.bytes = 0
        self.started = 0.0
        self.finished = 0.0
        self.cancel_requested = 0.0
        self.proc = None
        self.job_dir = ""
        self.tmp_output = ""

    # ------------------------------------------------------------------ lifecycle
    def start(self, scene, params: dict, meta: dict, scheduler: str = "") -> "BakeJob":
        """Start the worker; ``scheduler``: a Dask scheduler address or local:N to bake on
        (core/cluster.py), "" to bake in the worker's own processes."""
        self.job_dir = tempfile.mkdtemp(prefix="riray_bake_")
        try:
            self._launch(scene, params, meta, scheduler)
        except BaseException:
            shutil.rmtree(self.job_dir, ignore_errors=True)
            raise
        self.state = "running"
        self.started = time.time()
        self.message = "starting worker"
        return self

    def _launch(self, scene, params: dict, meta: dict, scheduler: str) -> None:
        """Write the job folder's files and start the worker process."""
        self.tmp_output = self._output_path()
        save_scene(scene, os.path.join(self.job_dir, "scene.json"))
        with open(os.path.join(self.job_dir, "job.json"), "w", encoding="utf-8") as fh:
            json.dump({"task": self.task, "scene": "scene.json", "params": params,
                       "output": self.tmp_output, "meta": meta, "scheduler": scheduler}, fh,
                      default=float)
        log = open(os.path.join(self.job_dir, "worker.log"), "wb")
        try:
            self.proc = subprocess.Popen([python_executable(), WORKER, self.job_dir],
                                         stdin=subprocess.DEVNULL, stdout=log,
                                         stderr=subprocess.STDOUT, cwd=self.job_dir)
        finally:
            log.close()

    @property
    def running(self) -> bool:
        return self.state == "running"

    @property
    def elapsed(self) -> float:
        return (self.finished or time.time()) - self.started if self.started else 0.0

    @property
    def eta(self) -> float | None:
        """Seconds left: the bake's own estimate (weighted by its work) counted down since it
        was written, else extrapolated from the fraction (None before any progress)."""
        if not self.running or self.fraction <= 0.01:
            return None
        if self.worker_eta is not None:
            left, at = self.worker_eta
            return max(left - (self.elapsed - at), 0.0)
        return self.elapsed * (1.0 - self.fraction) / self.fraction

    def cancel(self) -> None:
        """Ask the worker to stop (it polls the cancel file); killed after CANCEL_GRACE_S."""
        if not self.running:
            return
        if not self.cancel_requested:
            self.cancel_requested = time.time()
            open(os.path.join(self.job_dir, "cancel"), "wb").close()
            self.message = "cancelling"

    def poll(self) -> str:
        """Update progress / state from the worker's files; returns the state."""
        if not self.running:
            return self.state
        self._read_progress()
        rc = self.proc.poll()
        if rc is None:
            if self.cancel_requested and time.time() - self.cancel_requested > CANCEL_GRACE_S:
                self.proc.kill()
                self.proc.wait()
                self._finish("cancelled", "")
            return self.state
        result = self._read_json("result.json") or {}
        status = result.get("status")
        if status == "done" and rc == 0:
            try:
                if self._take(result):
                    self.fraction = 1.0
                    self._finish("done", "")
                    return self.state
            except OSError as exc:
                self._finish("failed", f"could not write {self.cache_path}: {exc}")
                return self.state
        if status == "cancelled" or self.cancel_requested:
            self._finish("cancelled", "")
        else:
            err = result.get("error") or f"the worker exited with code {rc}"
            self.traceback = result.get("traceback", "") or self._log_tail()
            self._finish("failed", err)
        return self.state

    def wait(self, timeout: float | None = None, interval: float = 0.05,
             on_progress=None) -> str:
        """Poll until the job ends (or ``timeout`` seconds); returns the state."""
        t0 = time.time()
        while self.poll() == "running":
            if on_progress is not None:
                on_progress(self)
            if timeout is not None and time.time() - t0 > timeout:
                break
            time.sleep(interval)
        return self.state

    # ------------------------------------------------------------------ internals
    def _output_path(self) -> str:
        """Where the worker writes the cache: beside the final path (its folder made)."""
        os.makedirs(os.path.dirname(os.path.abspath(self.cache_path)), exist_ok=True)
        return f"{os.path.abspath(self.cache_path)}.tmp{os.getpid()}_{id(self)}"

    def _take(self, result: dict) -> bool:
        """Move the finished cache into place (OSError when it cannot be); False when the
        worker wrote none."""
        if not os.path.exists(self.tmp_output):
            return False
        os.replace(self.tmp_output, self.cache_path)
        self.bytes = int(result.get("bytes", 0))
        return True

    def _finish(self, state: str, error: str) -> None:
        self.state = state
        self.error = error
        self.finished = time.time()
        self.message = {"done": "finished", "cancelled": "cancelled"}.get(state, error)
        if self.tmp_output and os.path.exists(self.tmp_output):
            try:
                os.remove(self.tmp_output)
            except OSError:
                pass
        shutil.rmtree(self.job_dir, ignore_errors=True)   # a failure's traceback is read already

    def _read_json(self, name: str) -> dict | None:
        try:
            with open(os.path.join(self.job_dir, name), encoding="utf-8") as fh:
                return json.load(fh)
        except (OSError, ValueError):
            return None

    def _read_progress(self) -> None:
        p = self._read_json("progress.json")
        if p:
            self.fraction = float(p.get("fraction", self.fraction))
            if p.get("eta") is not None:
                self.worker_eta = (float(p["eta"]), float(p.get("time", self.elapsed)))
            if not self.cancel_requested:
                self.message = str(p.get("message", self.message))

    def _log_tail(self, n: int = 2000) -> str:
        try:
            with open(os.path.join(self.job_dir, "worker.log"), "rb") as fh:
                return fh.read()[-n:].decode("utf-8", "replace")
        except OSError:
            return ""


class EstimateJob(BakeJob):
    """The estimate of one bake (backend.estimate_bake: the cameras' region and a trial bake)
    in a worker process, so that Blender stays responsive; ``estimate`` holds the result
    ({"time_s", "bytes", ...}) once done, for the bake settings ``key`` it was asked for."""

    task = "estimate"

    def __init__(self, object_name: str, key: str):
        super().__init__(object_name, "")
        self.key = key
        self.estimate: dict = {}

    def _output_path(self) -> str:
        return ""

    def _take(self, result: dict) -> bool:
        self.estimate = dict(result.get("estimate") or {})
        return bool(self.estimate)


JOBS: dict[str, BakeJob] = {}      # object name -> its current / last bake job
ESTIMATES: dict[str, EstimateJob] = {}     # object name -> its current / last estimate


def running_job(obj_name: str | None = None) -> BakeJob | None:
    """The running bake of ``obj_name`` (of any object when None), or None."""
    for name, job in JOBS.items():
        if job.running and (obj_name is None or name == obj_name):
            return job
    return None


def format_duration(s: float | None) -> str:
    if s is None or s != s:
        return "?"
    s = max(0.0, float(s))
    if s < 60:
        return f"{s:.0f} s" if s >= 10 else f"{s:.1f} s"
    if s < 3600:
        return f"{int(s // 60)} min {int(s % 60):02d} s"
    return f"{int(s // 3600)} h {int(s % 3600 // 60):02d} min"


def format_bytes(n: float | None) -> str:
    if n is None or n < 0:
        return "?"
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024.0
    return f"{n:.1f} GiB"
