"""How the RI-Tree query answered each ray (answer and why codes), and the named columns of the
sample table every answer is interpolated from."""

from __future__ import annotations

import numpy as np

# Answer codes: how each ray was answered. FULL..EXTRAPOLATED_S interpolate an output ray;
# NULL_S answers the null ray (trapped: every interpolant of the query's class is null);
# SOLVED is exact, solved along a sample's path (query/paths.py); TRACED and OUTSIDE (not in
# the baked region) are answered by the exact tracer.
MISS, FULL, REDUCED, EXTRA_S, EXTRAPOLATED_S, TRACED, OUTSIDE, NULL_S = 0, 1, 2, 3, 4, 5, 6, 7
SOLVED = 8
ANSWER_NAMES = ("miss", "interpolated_16", "interpolated_reduced", "interpolated_extra",
                "interpolated_extrapolated", "traced", "traced_outside_tree", "interpolated_null",
                "solved_along_path")
# Why a ray was traced.
WHY_CLASSES, WHY_USABLE, WHY_THRESHOLD, WHY_RAYTREE, WHY_BLEND = 1, 2, 3, 4, 5
WHY_TOLERANCE, WHY_UNSAMPLED, WHY_PATH = 6, 7, 8
WHY_NAMES = ("", "more_than_two_classes", "too_few_usable", "threshold", "raytree_mismatch",
             "degenerate_blend", "tolerance", "unsampled_hit", "path_change")


def is_interpolated(ans) -> np.ndarray:
    """Rays whose output ray was interpolated (FULL..EXTRAPOLATED_S; not NULL_S)."""
    ans = np.asarray(ans)
    return (ans >= FULL) & (ans <= EXTRAPOLATED_S)


def is_traced(ans) -> np.ndarray:
    """Rays the exact tracer answered (TRACED, OUTSIDE)."""
    ans = np.asarray(ans)
    return (ans == TRACED) | (ans == OUTSIDE)


class COL:
    """Columns of the sample table (``SampleTable.vals``, ``RITree.blend_vals``: (S, N) float32),
    one row per sample. Object-space units; directions and normals unit length (in
    ``blend_vals`` OUT_D is multiplied by the sample's perspective weight)."""

    OUT_O = slice(0, 3)      # output ray origin
    OUT_D = slice(3, 6)      # output ray direction
    POINT = slice(6, 9)      # first hit point
    NORMAL = slice(9, 12)    # surface normal at the first hit
    UV = slice(12, 14)       # the first hit's normalized patch parameters (u, v) in [0, 1]
    N = 14
