"""Process-parallel map over index chunks (fork: workers inherit built acceleration structures).

Falls back to running in-process where fork is unavailable or one worker is asked for.
Worker count: ``RIRAY_WORKERS`` or the machine's CPU count.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
from collections.abc import Callable

_TASK: Callable | None = None


def workers_default() -> int:
    """``RIRAY_WORKERS`` if set (a positive integer, else ValueError naming it), else the
    machine's CPU count."""
    env = os.environ.get("RIRAY_WORKERS", "").strip()
    if env:
        try:
            n = int(env)
        except ValueError:
            n = 0
        if n < 1:
            raise ValueError(f"RIRAY_WORKERS must be a positive integer (got {env!r})")
        return n
    return max(1, os.cpu_count() or 1)


def _run(bounds):
    return _TASK(*bounds)


def map_chunks(fn: Callable, n: int, chunk: int, workers: int | None = None,
               progress: Callable[[float], None] | None = None) -> list:
    """[fn(start, stop) for each chunk of range(n)], in order, over ``workers`` processes.

    ``progress(fraction)`` is called in the parent as chunks finish."""
    global _TASK
    bounds = [(s, min(s + chunk, n)) for s in range(0, n, chunk)]
    workers = workers_default() if workers is None else workers
    out = []
    if workers <= 1 or len(bounds) <= 1 or "fork" not in mp.get_all_start_methods():
        for i, b in enumerate(bounds):
            out.append(fn(*b))
            if progress:
                progress((i + 1) / len(bounds))
        return out
    _TASK = fn
    # Ctrl-C is the parent's alone: the workers are forked with SIGINT blocked (so a Ctrl-C
    # during the fork cannot reach them) and ignore it; the parent terminates and joins them
    # on any exit, so none outlives it.
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        pool = mp.get_context("fork").Pool(min(workers, len(bounds)), signal.signal,
                                           (signal.SIGINT, signal.SIG_IGN))
    except BaseException:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        _TASK = None
        raise
    try:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        for i, r in enumerate(pool.imap(_run, bounds)):
            out.append(r)
            if progress:
                progress((i + 1) / len(bounds))
    finally:
        pool.terminate()
        pool.join()
        _TASK = None
    return out
