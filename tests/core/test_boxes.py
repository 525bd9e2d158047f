"""trace/boxes.slab_intervals against a plain per-ray, per-axis reference, zero direction
components (inside and outside their slab, and on its boundary) included: never NaN."""

import numpy as np

from riray.trace.boxes import slab_intervals


def reference(o, d, lo, hi):
    tn = np.empty((len(o), 3))
    tf = np.empty((len(o), 3))
    for i in range(len(o)):
        for a in range(3):
            if d[i, a] == 0.0:
                inside = lo[a] <= o[i, a] <= hi[a]
                tn[i, a], tf[i, a] = (-np.inf, np.inf) if inside else (np.inf, -np.inf)
            else:
                t1, t2 = (lo[a] - o[i, a]) / d[i, a], (hi[a] - o[i, a]) / d[i, a]
                tn[i, a], tf[i, a] = min(t1, t2), max(t1, t2)
    return tn, tf


def test_slab_intervals_match_the_reference():
    rng = np.random.default_rng(4)
    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([1.0, 0.5, 3.0])
    o = rng.uniform(-3, 4, (400, 3))
    d = rng.normal(size=(400, 3))
    d[::3, 0] = 0.0
    d[1::4, 1:] = 0.0
    o[::5, 1] = hi[1]                       # on the slab boundary with d = 0 there
    nonzero = np.flatnonzero(np.all(d != 0, axis=1))
    for rows in (slice(None), nonzero):              # with and without zero components
        got = slab_intervals(o[rows], d[rows], lo, hi)
        want = reference(o[rows], d[rows], lo, hi)
        for g, w in zip(got, want):
            assert not np.isnan(g).any()
            assert np.array_equal(g, w)
    assert 0 < len(nonzero) < len(d)
