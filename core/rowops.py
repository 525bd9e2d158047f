"""Reductions along a short last axis (3-16 elements), done as whole-column operations, and
the unique rows of a table by one sort of its columns.

Numpy reduces a short axis with an inner loop per row, which costs 10-200x more per element
than column-wise ufuncs over the long axis (measured on (55K, 3-4) arrays: ``min(axis=1)``
1.2 ms against 0.06 ms, ``all(axis=1)`` 0.7 ms against 0.004 ms). The results are the same
as numpy's (``argmax3`` keeps the first maximum; ``norm3`` may differ from
``np.linalg.norm`` by an ulp).
"""

from __future__ import annotations

import numpy as np

_WORD = {1: np.uint8, 2: np.uint16, 4: np.uint32, 8: np.uint64}


def _words(b: np.ndarray) -> np.ndarray | None:
    """Each row of a C-contiguous bool array (..., k), k in 1, 2, 4, 8, as one integer."""
    k = b.shape[-1]
    if k not in _WORD:
        return None
    b = np.ascontiguousarray(b, dtype=bool)
    return b.view(_WORD[k])[..., 0]


def all_last(b) -> np.ndarray:
    """np.all(b, axis=-1) for a bool array."""
    w = _words(np.asarray(b))
    if w is None:
        return np.all(b, axis=-1)
    return w == w.dtype.type(int("01" * w.dtype.itemsize, 16))


def any_last(b) -> np.ndarray:
    """np.any(b, axis=-1) for a bool array."""
    w = _words(np.asarray(b))
    return np.any(b, axis=-1) if w is None else w != 0


def min3(x: np.ndarray) -> np.ndarray:
    """x.min(axis=1) for (n, 3)."""
    return np.minimum(np.minimum(x[:, 0], x[:, 1]), x[:, 2])


def argmax3(x: np.ndarray) -> np.ndarray:
    """np.argmax(x, axis=1) for (n, 3) without NaN: the first maximum."""
    i = (x[:, 1] > x[:, 0]).astype(np.int64)
    i[x[:, 2] > np.maximum(x[:, 0], x[:, 1])] = 2
    return i


def norm3(x: np.ndarray) -> np.ndarray:
    """Euclidean length of each row of (n, 3)."""
    return np.sqrt(np.einsum("ij,ij->i", x, x))


def unique_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unique rows sorted lexicographically, inverse) of a 2-D array, as
    ``np.unique(a, axis=0, return_inverse=True)`` gives them but by one lexsort of the columns
    (numpy's row unique sorts the rows as opaque byte strings: ten times slower on a 200k-face
    mesh's corners). Rows are equal where every column compares equal (so -0.0 == 0.0)."""
    a = np.asarray(a)
    if len(a) == 0:
        return a.copy(), np.zeros(0, np.int64)
    order = np.lexsort(a.T[::-1])
    s = a[order]
    new = np.ones(len(s), bool)
    new[1:] = any_last(s[1:] != s[:-1])
    inv = np.empty(len(a), np.int64)
    inv[order] = np.cumsum(new) - 1
    return s[new], inv
