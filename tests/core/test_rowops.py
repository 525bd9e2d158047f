"""core/rowops.py against numpy's own reductions (random arrays, ties, non-contiguous input)."""

import numpy as np
import pytest

from riray.rowops import all_last, any_last, argmax3, min3, norm3, unique_rows

RNG = np.random.default_rng(3)


@pytest.mark.parametrize("k", [1, 2, 3, 4, 6, 8, 16])
def test_all_and_any_match_numpy(k):
    for p in (0.05, 0.7, 0.97):
        b = RNG.random((500, k)) < p
        assert np.array_equal(all_last(b), b.all(axis=-1))
        assert np.array_equal(any_last(b), b.any(axis=-1))
        b3 = RNG.random((20, 5, k)) < p
        assert np.array_equal(all_last(b3), b3.all(axis=-1))
    strided = (RNG.random((300, 2 * k)) < 0.8)[:, ::2]
    assert np.array_equal(all_last(strided), strided.all(axis=-1))
    assert np.array_equal(any_last(strided), strided.any(axis=-1))


def test_argmax3_keeps_the_first_maximum_and_min3_norm3():
    x = RNG.integers(0, 3, (2000, 3)).astype(np.float64)      # many ties
    x[::5] = np.inf
    x[1::7, 2] = -np.inf
    assert np.array_equal(argmax3(x), np.argmax(x, axis=1))
    assert np.array_equal(min3(x), x.min(axis=1))
    y = RNG.normal(size=(2000, 3)) * 10.0 ** RNG.integers(-150, 150, (2000, 1))
    assert np.allclose(norm3(y), np.linalg.norm(y, axis=1), rtol=4e-16, atol=0)


def test_unique_rows_match_numpys_row_unique():
    """The same unique rows, in the same order, with the same inverse as np.unique(axis=0), on
    mesh corners (vertex id, u, v) full of repeats; an empty table gives empty results."""
    rng = np.random.default_rng(5)
    vid = rng.integers(0, 300, 5000).astype(np.float64)
    uv = rng.integers(0, 4, (5000, 2)) * 0.25
    a = np.c_[vid, uv]
    want, want_inv = np.unique(a, axis=0, return_inverse=True)
    got, inv = unique_rows(a)
    assert got.shape == want.shape and np.array_equal(got, want)
    assert np.array_equal(inv, want_inv.ravel())
    assert np.array_equal(got[inv], a)
    empty, inv0 = unique_rows(np.zeros((0, 3)))
    assert empty.shape == (0, 3) and len(inv0) == 0
