"""Interleaved tree-against-exact runs of the same camera rays (``riray render --tree`` and the
RI-Tree benchmark share it).

Each share is rendered twice in the same process, once through the RI-Tree and once exactly,
the order alternating from share to share, so the *object-only* times compare the same rays
under the same machine load (paper, section 6). The angular error is measured on the rays the
tree interpolated or solved along a sample's path and the exact tracer also finds leaving the
object.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..ritree.answers import SOLVED, is_interpolated
from ..ritree.interp import angle_between
from .frame import ShareResult, shade_share


@dataclass
class ComparedShare:
    """One share through the tree and (when asked) exactly."""
    tree: ShareResult
    exact: ShareResult | None
    err_deg: np.ndarray      # (n,) angle between tree and exact output rays, NaN where none
    interpolated: np.ndarray  # (handed,) bool: measured rays (interpolated or solved)
    hit_disagree: int        # handed rays answered hit / miss against the exact answer
    null_disagree: int       # handed rays answered null / not null against the exact answer


def disagreements(ri, rx) -> tuple[int, int]:
    """(hit, null) disagreements of the answers ``ri`` with the exact results ``rx`` of the
    same rays (ObjectRays): rays answered as hitting the object that miss it, or the other way
    round; rays answered null (trapped inside) that leave it, or the other way round."""
    return int(np.sum(ri.hit != rx.hit)), int(np.sum(ri.null != rx.null))


def compare_share(st, origins, dirs, tree_answerer, exact_answerer=None,
                  exact_first: bool = False) -> ComparedShare:
    """Render one share through ``tree_answerer`` and, when ``exact_answerer`` is given,
    exactly (first when ``exact_first``); measure the tree's answers against the exact ones."""
    runs = [tree_answerer] + ([exact_answerer] if exact_answerer is not None else [])
    order = runs[::-1] if exact_first else runs
    done = {id(a): shade_share(st, origins, dirs, a) for a in order}
    tree = done[id(tree_answerer)]
    err = np.full(len(origins), np.nan)
    if exact_answerer is None:
        return ComparedShare(tree, None, err, np.zeros(len(tree.handed), bool), 0, 0)
    exact = done[id(exact_answerer)]
    ri, rx = tree.answer.rays, exact.answer.rays
    ans = tree.answer.answer
    interp = (is_interpolated(ans) | (ans == SOLVED)) & ri.hit & rx.hit & ~rx.null & ~ri.null
    err[tree.handed[interp]] = np.degrees(angle_between(ri.out_dir[interp], rx.out_dir[interp]))
    hit_d, null_d = disagreements(ri, rx)
    return ComparedShare(tree, exact, err, interp, hit_d, null_d)
