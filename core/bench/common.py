"""Helpers the benchmarks share: CPU clocks and medians (per-share stats are summed by
render/frame.py's sum_stats)."""

from __future__ import annotations

import resource

import numpy as np


def cpu_seconds() -> float:
    """CPU seconds of this process and its reaped children (the bake's worker pools)."""
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def median(xs) -> float:
    """The median of ``xs`` as a float; NaN for none."""
    return float(np.median(np.asarray(xs, np.float64))) if len(xs) else float("nan")
