"""Interleaved tree-against-exact runs of the same camera rays (``riray render --tree`` and the
RI-Tree benchmark share it).

Each share is rendered twice in the same process, once through the RI-Tree and once exactly,
the order alternating from share to share, so the *object-only* times compare the same rays
under the same machine load (paper, section 6). The angular error is measured on the rays the
tree interpolated or solved along a sample's path and the exact tracer also finds leaving the
object, that object the ray's nearest in both runs.
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
    interpolated: np.ndarray  # (handed,) bool: the first object's measured rays (interpolated
                              # or solved)
    hit_disagree: int        # rays handed to an object in both runs answered hit / miss
                             # against the exact answer
    null_disagree: int       # ... answered null / not null against the exact answer


def disagreements(ri, rx) -> tuple[int, int]:
    """(hit, null) disagreements of the answers ``ri`` with the exact results ``rx`` of the
    same rays (ObjectRays): rays answered as hitting the object that miss it, or the other way
    round; rays answered null (trapped inside) that leave it, or the other way round."""
    return int(np.sum(ri.hit != rx.hit)), int(np.sum(ri.null != rx.null))


def compare_share(st, origins, dirs, tree_answerer, exact_answerer=None,
                  exact_first: bool = False, others_tree: tuple = (),
                  others_exact: tuple = ()) -> ComparedShare:
    """Render one share through ``tree_answerer`` and, when ``exact_answerer`` is given,
    exactly (first when ``exact_first``); measure the tree's answers against the exact ones.
    A scene's other specular objects are ``others_tree`` (Specular: through their trees where
    they have one) and ``others_exact`` (the same objects traced exactly)."""
    runs = [(tree_answerer, others_tree)] + (
        [(exact_answerer, others_exact)] if exact_answerer is not None else [])
    order = runs[::-1] if exact_first else runs
    done = {id(a): shade_share(st, origins, dirs, a, more) for a, more in order}
    tree = done[id(tree_answerer)]
    err = np.full(len(origins), np.nan)
    if exact_answerer is None:
        return ComparedShare(tree, None, err, np.zeros(len(tree.handed), bool), 0, 0)
    exact = done[id(exact_answerer)]
    hit_d = null_d = 0
    for k, (ot, ox) in enumerate(zip(tree.objects, exact.objects)):
        rows, it, ix = np.intersect1d(ot.handed, ox.handed, assume_unique=True,
                                      return_indices=True)
        ri, rx = ot.answer.rays.take(it), ox.answer.rays.take(ix)
        ans = ot.answer.answer[it]
        measured = (is_interpolated(ans) | (ans == SOLVED)) & ot.won[it] & ox.won[ix] \
            & ~rx.null & ~ri.null
        err[rows[measured]] = np.degrees(angle_between(ri.out_dir[measured],
                                                       rx.out_dir[measured]))
        if k == 0:
            interp = np.zeros(len(ot.handed), bool)
            interp[it] = measured
        hd, nd = disagreements(ri, rx)
        hit_d, null_d = hit_d + hd, null_d + nd
    return ComparedShare(tree, exact, err, interp, hit_d, null_d)
