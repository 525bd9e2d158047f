"""core/rowops.py against numpy's own reductions (random arrays, ties, non-contiguous input)."""

import numpy as np
import pytest

from riray.rowops import all_last, any_last, argmax3, min3, norm3

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
