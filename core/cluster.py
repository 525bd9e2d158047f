"""Bakes on a Dask cluster (``riray bake --scheduler``): each bake pass's direction trees in
shards over ``dask.distributed`` workers, merged by the client into exactly the tree a local
bake makes (ritree/bake/shards.py: ``bake_shard``, ``ShardedPass.merge``).

A shard is a block of consecutive direction trees (the hemicube slots of consecutive
viewpoints), baked whole on one worker: every direction level, the midpoint tests and the extra
samples. It comes back as plain numpy arrays (nodes, float32 samples, extra samples; about
98 bytes a sample with its nodes). Direction trees share no samples (a sample's key starts
with its tree), so every sample is traced once, in one shard, and nothing is deduplicated;
corners that neighbouring cells of one tree share are deduplicated inside the shard, as in a
local bake. Which viewpoint cells and slots to bake, the refinement passes of camera-region
bakes and their verification on the cameras' rays stay on the client: little work, and they
need the whole tree.

The scene goes to the workers once per bake, in a worker plugin (``ScenePlugin``) that the
scheduler also hands to workers that join or restart later: the object and ``max_events`` as a
JSON scene (the direction trees trace the object only). Each worker process builds the
acceleration structures on its first shard and keeps them for the others. A worker lost
mid-shard is replaced and the shard re-run by the scheduler. Dask is optional
(``pip install 'riray[cluster]'``): only this module imports it, lazily.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import json
import logging
import math
import os
import signal
import socket
import sys
import time
import uuid
from concurrent.futures import CancelledError
from dataclasses import asdict

from . import __version__
from .ritree.bake import BakeCancelled, bake_shard
from .ritree.cache import fingerprint
from .ritree.tree import BakeParams

SHARD_TREES = 192        # direction trees per shard at most (glass_sphere: ~8 s of one core at
                         # depths 4/5): each shard's trace calls cost ~10 ms apiece whatever
                         # their size, ~25 of them, so fewer, larger shards waste less
SHARDS_PER_WORKER = 8    # at least this many shards per worker thread where the trees allow, so
                         # the last wave is short
MIN_SHARD_TREES = 16     # fewer trees per shard trace in batches too small to vectorize well
POLL_S = 0.1             # seconds between checks of cancel() and the connection while waiting
WORKER_WAIT_S = 30.0     # seconds to wait for a first worker at a scheduler without any
LOCAL_WORKERS_PER_CORE = 4   # local:N takes at most this many worker processes per CPU core
                             # (each is a Python process of ~100 MiB before any shard)
PROBE_S = 2.0            # seconds a TCP connect to the scheduler's address may take before the
                         # address is handed to Dask anyway (a slow but live scheduler); a
                         # refused connection or an unknown host fails at once
# Dask's nannies start workers with MALLOC_TRIM_THRESHOLD_=65536, which fixes glibc's mmap
# threshold at 128 KiB: every large numpy temporary is then mapped and unmapped, and a shard
# spends ~30 % of its CPU in the kernel (measured: 4/5 glass_sphere, 40 of 132 s). local:N unsets
# it (docs/cluster.md says how for `dask worker`). It also turns off the workers' statistical
# profiler (a stack sample every 10 ms: 2-3 % of a shard's CPU, measured at 3/4).
WORKER_CONFIG = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
                 "distributed.worker.profile.enabled": False}


# Level of Dask's own logging in local:N's processes. A shard that fails reaches the bake as
# its future's exception and is reported in one line; below CRITICAL a worker also prints the
# errors of a shutdown under load (a heartbeat to a scheduler that already closed, with a
# traceback) on the terminal after a Ctrl-C.
WORKER_LOG_LEVEL = logging.CRITICAL


class ClusterError(ValueError):
    """The cluster cannot be reached or cannot finish the bake; the message says why."""


def _interrupted_wait(record: logging.LogRecord) -> bool:
    """Logging filter: False for the event-loop error Dask's ``sync`` leaves behind when Ctrl-C
    interrupts a wait (a NameError about its ``future``, logged with a traceback by tornado);
    the bake reports the interruption itself, in one line."""
    exc = record.exc_info[1] if record.exc_info else None
    return not (isinstance(exc, NameError) and "'future'" in str(exc))


def connect(spec: str, timeout: float | None = None) -> "Cluster":
    """``local:N`` (a LocalCluster of N worker processes, one thread each, on this machine) or
    a running scheduler's address (``tcp://host:8786``). ``timeout``: seconds to connect
    (default: Dask's ``distributed.comm.timeouts.connect``). ClusterError (one line) when
    Dask is missing, ``spec`` is malformed or nothing answers."""
    try:
        import dask
        import distributed
    except ImportError:
        raise ClusterError("--scheduler needs Dask: pip install 'riray[cluster]'") from None
    if timeout is None:
        timeout = dask.utils.parse_timedelta(dask.config.get("distributed.comm.timeouts.connect"))
    tornado_log = logging.getLogger("tornado.application")
    if _interrupted_wait not in tornado_log.filters:
        tornado_log.addFilter(_interrupted_wait)
    local = None
    if spec.startswith("local:"):
        local = _local_cluster(spec, distributed)
        spec = local.scheduler_address
    else:
        _probe(spec, timeout)
    try:
        client = distributed.Client(spec, timeout=timeout)
    except BaseException as e:        # any failure to connect is the address's; Ctrl-C too
        if local is not None:
            _quiet_close(local)
        if not isinstance(e, Exception):
            raise
        raise ClusterError(f"Dask scheduler {spec}: cannot connect ({_line(e)})") from None
    cluster = Cluster(client, local)
    try:
        client.wait_for_workers(1, timeout=WORKER_WAIT_S)
    except Exception:                 # noqa: BLE001 - a time-out, or the connection went away
        cluster.close()
        raise ClusterError(f"Dask scheduler {spec}: no worker joined within {WORKER_WAIT_S:g} s "
                           "(start some with: dask worker ADDRESS)") from None
    return cluster


def _local_cluster(spec: str, distributed):
    """The LocalCluster of ``local:N``. Its worker processes never see a Ctrl-C: the terminal
    sends SIGINT to the whole process group, and a worker interrupted mid-task prints its own
    tracebacks. The cluster's event-loop thread is started with SIGINT blocked, and every
    thread it starts (the ones that spawn the workers, also those a nanny restarts) and every
    worker process inherits that mask; this process handles the Ctrl-C and closes the cluster.
    A Ctrl-C during the start-up is held back until the cluster exists, then raised after
    closing it. multiprocessing's resource tracker is started first: starting it unblocks
    SIGINT in the thread that does (resource_tracker.ensure_running), which would otherwise be
    the event-loop thread."""
    import dask
    from multiprocessing import resource_tracker
    n = spec[len("local:"):]
    if not n.isdigit() or int(n) < 1:
        raise ClusterError(f"--scheduler {spec}: expected local:N with N >= 1 worker processes")
    cap = max_local_workers()
    if int(n) > cap:
        raise ClusterError(f"--scheduler {spec}: at most {cap} worker processes on this machine "
                           f"(riray.cluster.LOCAL_WORKERS_PER_CORE: {LOCAL_WORKERS_PER_CORE} per CPU core)")
    block = hasattr(signal, "pthread_sigmask")       # POSIX
    if block:
        resource_tracker.ensure_running()
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT}) if block else None
    try:
        with dask.config.set(WORKER_CONFIG):
            local = distributed.LocalCluster(n_workers=int(n), threads_per_worker=1,
                                             processes=True, dashboard_address=":0",
                                             silence_logs=WORKER_LOG_LEVEL)
    except BaseException:
        if block:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        raise
    try:
        if block:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)   # raises a Ctrl-C held back
    except BaseException:
        _quiet_close(local)
        raise
    return local


def max_local_workers() -> int:
    """The most worker processes ``local:N`` starts: LOCAL_WORKERS_PER_CORE per CPU core."""
    return LOCAL_WORKERS_PER_CORE * max(1, os.cpu_count() or 1)


def _probe(spec: str, timeout: float) -> None:
    """ClusterError at once when nothing listens at a TCP (or TLS) scheduler address: the
    connection is refused or the host does not resolve. An address that does not take the
    connection within PROBE_S seconds is left to Dask's own connect timeout. A plain-TCP
    scheduler speaks first (its handshake): a peer silent for ``timeout`` seconds is not one
    (Dask would wait for it forever; the dashboard's port is like that)."""
    from distributed.comm import parse_address
    from distributed.comm.addressing import parse_host_port
    try:
        scheme, loc = parse_address(spec)
        if scheme not in ("tcp", "tls"):
            return
        host, port = parse_host_port(loc, 8786)
    except ValueError as e:
        raise ClusterError(f"Dask scheduler {spec}: not an address ({_line(e)})") from None
    try:
        sock = socket.create_connection((host, port), timeout=PROBE_S)
    except (ConnectionRefusedError, socket.gaierror) as e:
        raise ClusterError(f"Dask scheduler {spec}: cannot connect ({e.strerror or e})") from None
    except OSError:                   # a time-out or an unreachable network: Dask decides
        return
    with sock:
        if scheme != "tcp":           # TLS: the client speaks first
            return
        sock.settimeout(timeout)
        try:
            sock.recv(1)
        except TimeoutError:
            raise ClusterError(f"Dask scheduler {spec}: no answer within {timeout:g} s (is "
                               "this a Dask scheduler's address?)") from None
        except OSError:               # reset or closed: Dask's connect says what it sees
            pass


def _quiet_close(obj) -> None:
    """``obj.close()`` with Dask's shutdown chatter (connection errors of workers and comms
    that go away) kept off the terminal: the caller reports in one line."""
    loggers = [logging.getLogger(n) for n in ("distributed", "tornado", "asyncio")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL + 1)
    try:
        obj.close()
    except Exception:                 # noqa: BLE001 - closing what already went away
        pass
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


def _line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0]}" if text else type(e).__name__


class _Import:
    """Pickles as ``importlib.import_module(name)``."""

    def __init__(self, name: str):
        self.name = name

    def __reduce__(self):
        return importlib.import_module, (self.name,)


class _Remote:
    """This module's function ``name``, pickled as ``riray.cluster.<name>``: the workers run the
    installed package ``riray`` even where this client imports core under another name
    (inside Blender's extension)."""

    def __init__(self, name: str):
        self.name = name

    def __call__(self, *args):
        return getattr(sys.modules[__name__], self.name)(*args)

    def __reduce__(self):
        return getattr, (_Import("riray.cluster"), self.name)


def scene_payload(scene) -> str:
    """What the workers need of ``scene``, as JSON: its object and max_events (a scene of the
    scene format) and the object's fingerprint, to check what they rebuild."""
    from .scene.io import scene_to_dict
    from .scene.model import Scene
    return json.dumps({"scene": scene_to_dict(Scene(objects=[scene.object], render=scene.render)),
                       "fingerprint": fingerprint(scene.object, scene.render.max_events)})


_PAYLOADS: dict = {}          # worker process: scene token -> scene_payload (ScenePlugin)
_TRACERS: dict = {}           # worker process: scene token -> its SceneTracer, built once


def __getattr__(name):
    """``ScenePlugin``, made on first use (its base class is Dask's, imported lazily)."""
    if name != "ScenePlugin":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from distributed import WorkerPlugin

    class ScenePlugin(WorkerPlugin):
        """Hands every worker, those there now and those that join or restart later, the
        bake's scene once; the worker builds its tracer on its first shard."""

        def __init__(self, token: str, payload: str):
            self.token, self.payload = token, payload

        def setup(self, worker):
            _PAYLOADS[self.token] = self.payload

        def teardown(self, worker):
            _PAYLOADS.pop(self.token, None)
            _TRACERS.pop(self.token, None)

        def __reduce__(self):
            return _Remote("ScenePlugin"), (self.token, self.payload)

    globals()["ScenePlugin"] = ScenePlugin
    return ScenePlugin


def _tracer(token: str):
    if token not in _TRACERS:
        from .trace.scene_tracer import SceneTracer
        from .scene.io import scene_from_dict
        if token not in _PAYLOADS:
            raise ClusterError("this worker has no scene for the bake (its plugin is missing)")
        doc = json.loads(_PAYLOADS[token])
        scene = scene_from_dict(doc["scene"])
        if fingerprint(scene.object, scene.render.max_events) != doc["fingerprint"]:
            raise ClusterError("the scene rebuilt on the worker differs from the client's")
        _TRACERS[token] = SceneTracer(scene)
    return _TRACERS[token]


def run_shard(version: str, token: str, params: dict, task: dict) -> dict:
    """A worker's task: ``bake_shard`` with the scene's tracer built once per worker process."""
    if version != __version__:
        raise ClusterError(f"a worker runs riray {__version__}, the client riray {version}: "
                           "install the same version everywhere")
    return bake_shard(_tracer(token), BakeParams(**params), task)


SHARD_TASK = _Remote("run_shard")     # what run() submits per shard


class Cluster:
    """A Dask client (and the LocalCluster it owns, for ``local:N``) that bakes shards."""

    def __init__(self, client, local=None):
        self.client, self.local = client, local
        self.scene = None             # the token of the scene the workers hold (ScenePlugin)

    @property
    def address(self) -> str:
        return self.client.scheduler.address

    @property
    def dashboard(self) -> str | None:
        """The scheduler's dashboard link; None where there is none (local:N without bokeh,
        which draws its pages)."""
        if self.local is not None and importlib.util.find_spec("bokeh") is None:
            return None
        try:
            return self.client.dashboard_link
        except (KeyError, AttributeError):
            return None

    def threads(self) -> int:
        """Worker threads now connected."""
        return max(1, sum(self.client.nthreads().values()))

    def describe(self) -> dict:
        return {"scheduler": self.address, "worker_threads": self.threads()}

    def shard_count(self, trees: int, threads: int | None = None) -> int:
        """Shards for a pass of ``trees`` direction trees: at most SHARD_TREES trees each, at
        least SHARDS_PER_WORKER per worker thread while they keep MIN_SHARD_TREES trees."""
        threads = self.threads() if threads is None else threads
        n = max(math.ceil(trees / SHARD_TREES),
                min(SHARDS_PER_WORKER * threads, trees // MIN_SHARD_TREES))
        return max(1, min(n, trees))

    def run(self, st, params: BakeParams, tasks: list, cancel=None, progress=None,
            passes=(0, 1), buffers=None) -> list:
        """``bake_shard`` results of ``tasks`` (in order), computed on the workers.

        ``progress(fraction, message)`` counts finished shards (weighted by their trees) and
        samples; ``passes`` = (passes done, passes in all) places this pass in the bake.
        ``buffers`` (shardmerge.MergeBuffers) hears of each result as it arrives and gets the
        client's idle time between polls to touch the merge's memory.
        ``cancel()`` returning True, an error or Ctrl-C cancels every shard still queued or
        running, and raises. A shard's own error is raised as it was raised on the worker."""
        from distributed import wait
        token = self._send_scene(st.scene)
        run = uuid.uuid4().hex[:8]
        futures = {self.client.submit(SHARD_TASK, __version__, token, asdict(params), t,
                                      key=f"riray-shard-{run}-{i}", pure=False): i
                   for i, t in enumerate(tasks)}
        report = _Progress(progress, [len(t["trees"]) for t in tasks], self.threads(), passes)
        results = [None] * len(tasks)
        try:
            while futures:
                if cancel is not None and cancel():
                    raise BakeCancelled("bake cancelled")
                try:
                    done, _ = wait(list(futures), timeout=POLL_S, return_when="FIRST_COMPLETED")
                except TimeoutError:
                    done = ()
                except CancelledError as e:         # Dask cancels all when the scheduler is lost
                    raise self._lost(len(futures), e) from None
                for f in done:
                    i = futures.pop(f)
                    results[i] = self._result(f, i, len(tasks))
                    report.shard(i, len(results[i]["patch"]))
                    if buffers is not None:
                        buffers.add(results[i], len(tasks[i]["trees"]))
                if buffers is not None and futures:
                    buffers.touch()
                if futures and self.client.status not in ("running", "connecting"):
                    raise self._lost(len(futures))
        finally:
            if futures:
                self.client.cancel(list(futures), force=True)
        return results

    def _send_scene(self, scene) -> str:
        """Register the scene with the workers (once per scene); returns its token."""
        payload = scene_payload(scene)
        token = hashlib.sha256(payload.encode()).hexdigest()[:16]
        if token != self.scene:
            self._drop_scene()
            plugin = __getattr__("ScenePlugin")(token, payload)
            self.client.register_plugin(plugin, name=f"riray-scene-{token}")
            self.scene = token
        return token

    def _drop_scene(self) -> None:
        if self.scene is not None:
            try:
                self.client.unregister_worker_plugin(f"riray-scene-{self.scene}")
            except Exception:          # noqa: BLE001 - the workers or scheduler are gone
                pass
            self.scene = None

    def _lost(self, unfinished: int, why=None) -> ClusterError:
        return ClusterError(f"lost the Dask scheduler {self.address} ({unfinished} shards "
                            "unfinished" + (f"; {_line(why)})" if why is not None else ")"))

    def _result(self, future, i: int, n: int) -> dict:
        try:
            return future.result()
        except ValueError:
            raise                          # the shard's own error (a bad scene, versions)
        except Exception as e:             # noqa: BLE001 - lost workers, scheduler, connection
            from distributed import KilledWorker
            why = "its workers kept dying" if isinstance(e, KilledWorker) else _line(e)
            raise ClusterError(f"shard {i + 1} of {n} failed on the cluster: {why}") from None

    def close(self) -> None:
        """Drop the scene, then close the client, then the LocalCluster (its workers first),
        with Dask's shutdown logging kept off the terminal."""
        self._drop_scene()
        _quiet_close(self.client)
        if self.local is not None:
            _quiet_close(self.local)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class _Progress:
    """A pass's progress as shards finish: the share of its direction trees done, placed among
    the bake's passes; ETA = seconds so far x trees left / trees done (for this pass, and every
    refinement pass left as long as this one)."""

    def __init__(self, cb, trees: list, threads: int, passes):
        self.cb, self.trees, self.threads = cb, trees, threads
        self.done, self.passes_done, self.passes = 0, passes[0], passes[1]
        self.shards = self.samples = 0
        self.t0 = time.perf_counter()
        self.emit()

    def shard(self, i: int, samples: int) -> None:
        self.done += self.trees[i]
        self.shards += 1
        self.samples += samples
        self.emit()

    def emit(self) -> None:
        if self.cb is None:
            return
        f = self.done / max(sum(self.trees), 1)
        head = (f"shards {self.shards}/{len(self.trees)}, {self.samples:,} samples, "
                f"{self.threads} worker threads")
        if self.passes > 1:
            head += f" (pass {self.passes_done + 1} of up to {self.passes})"
        frac = (self.passes_done + f) / self.passes
        if f == 0:
            self.cb(frac, f"{head}: {100 * frac:.0f}%")
            return
        el = time.perf_counter() - self.t0
        left = el / f - el + (self.passes - self.passes_done - 1) * el / f
        self.cb(frac, f"{head}: {100 * frac:.0f}% (eta {left:.0f} s)")
