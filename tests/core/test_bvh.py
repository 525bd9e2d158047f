"""BVH against brute-force slab tests: candidates, closest hit and any hit."""

import numpy as np
import pytest

from riray.trace.bvh import BVH


def brute_boxes(o, d, tmin, tmax, lo, hi):
    """(N, M) overlap mask and entry t, slab by slab with explicit zero-direction cases."""
    near = np.broadcast_to(tmin[:, None], (len(o), len(lo))).copy()
    far = np.broadcast_to(tmax[:, None], (len(o), len(lo))).copy()
    for ax in range(3):
        oa, da = o[:, ax:ax + 1], d[:, ax:ax + 1]
        la, ha = lo[None, :, ax], hi[None, :, ax]
        zero = da == 0
        with np.errstate(divide="ignore", invalid="ignore"):
            a, b = (la - oa) / da, (ha - oa) / da
        inside = (la <= oa) & (oa <= ha)
        n_ax = np.where(zero, np.where(inside, -np.inf, np.inf), np.minimum(a, b))
        f_ax = np.where(zero, np.where(inside, np.inf, -np.inf), np.maximum(a, b))
        near, far = np.maximum(near, n_ax), np.minimum(far, f_ax)
    return near <= far, near


def random_case(seed, m=300, n=400):
    rng = np.random.default_rng(seed)
    c = rng.uniform(-5, 5, (m, 3))
    s = rng.uniform(0, 1, (m, 3))
    s[::5, rng.integers(0, 3)] = 0.0                       # flat boxes (axis-aligned triangles)
    lo, hi = c - s, c + s
    o = rng.uniform(-7, 7, (n, 3))
    o[::4] = c[rng.integers(0, m, len(o[::4]))]            # rays starting inside boxes
    k = rng.integers(0, m, len(o[3::6]))                   # origins exactly on a box's
    o[3::6] = c[k]                                         # x slab plane, d_x = 0 there
    o[3::6, 0] = np.where(np.arange(len(k)) % 2, lo[k, 0], hi[k, 0])
    d = rng.normal(size=(n, 3))
    d[::3, 0] = 0.0                                        # axis-parallel rays
    d[::7, 1:] = 0.0
    d[2::9, 0] = -0.0
    d[np.all(d == 0, axis=1)] = (0.0, 0.0, -1.0)
    d /= np.linalg.norm(d, axis=1)[:, None]
    tmin = rng.uniform(-2, 1, n)
    tmax = tmin + rng.uniform(0, 10, n)                    # cut-offs
    tmax[::11] = np.inf
    return lo, hi, o, d, tmin, tmax


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("leaf_size", [1, 4])
def test_candidates_equal_brute_force(seed, leaf_size):
    lo, hi, o, d, tmin, tmax = random_case(seed)
    bvh = BVH.build(lo, hi, leaf_size=leaf_size)
    r, p, te = bvh.candidates(o, d, tmin, tmax, max_pairs=97)   # exercises chunking
    mask, near = brute_boxes(o, d, tmin, tmax, lo, hi)
    rr, pp = np.nonzero(mask)
    assert len(r) == len(rr)
    assert set(zip(r.tolist(), p.tolist())) == set(zip(rr.tolist(), pp.tolist()))
    np.testing.assert_allclose(te, near[r, p], rtol=1e-12, atol=1e-12)
    assert not np.isnan(te).any()
    order = np.lexsort((te, r))
    assert np.array_equal(order, np.arange(len(r)))               # sorted by ray, then t


def test_zero_direction_on_slab_plane():
    bvh = BVH.build(np.array([[0.0, 0.0, 0.0]]), np.array([[1.0, 1.0, 0.0]]))
    o = np.array([[0.0, 0.5, -1.0], [1.0, 0.5, -1.0], [1.0 + 1e-9, 0.5, -1.0], [0.5, 0.5, 0.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    r, p, te = bvh.candidates(o, d, np.zeros(4), np.full(4, 5.0))
    assert r.tolist() == [0, 1, 3]
    np.testing.assert_array_equal(te, [1.0, 1.0, 0.0])


def test_build_structure():
    rng = np.random.default_rng(3)
    lo = rng.uniform(0, 10, (1000, 3))
    hi = lo + rng.uniform(0, 0.5, (1000, 3))
    bvh = BVH.build(lo, hi, leaf_size=4)
    leaf = bvh.child < 0
    assert np.all(bvh.prim_count[leaf] <= 4)
    assert sorted(bvh.perm.tolist()) == list(range(1000))
    assert bvh.prim_count[leaf].sum() == 1000
    for i in np.flatnonzero(~leaf):                       # children inside their parent
        for c in (bvh.child[i], bvh.child[i] + 1):
            assert np.all(bvh.node_lo[:, c] >= bvh.node_lo[:, i])
            assert np.all(bvh.node_hi[:, c] <= bvh.node_hi[:, i])
    for i in np.flatnonzero(leaf):                        # leaves contain their primitives
        ps = bvh.perm[bvh.prim_start[i]:bvh.prim_start[i] + bvh.prim_count[i]]
        assert np.all(lo[ps] >= bvh.node_lo[:, i]) and np.all(hi[ps] <= bvh.node_hi[:, i])


def test_identical_and_empty_boxes():
    lo = np.zeros((50, 3))
    bvh = BVH.build(lo, lo + 1.0, leaf_size=2)            # no SAH plane separates: median split
    r, p, _ = bvh.candidates(np.array([[0.5, 0.5, -1.0]]), np.array([[0.0, 0.0, 1.0]]), 0.0, 9.0)
    assert sorted(p.tolist()) == list(range(50))
    empty = BVH.build(np.zeros((0, 3)), np.zeros((0, 3)))
    r, p, te = empty.candidates(np.zeros((3, 3)), np.ones((3, 3)), 0.0, 1.0)
    assert len(r) == len(p) == len(te) == 0
    with pytest.raises(ValueError, match="lo > hi"):
        BVH.build(np.ones((1, 3)), np.zeros((1, 3)))


@pytest.mark.parametrize("seed", [0, 1])
def test_closest_and_any_hit_with_callback(seed):
    """Primitives 'hit' at their box entry beyond a per-primitive offset (so box order and hit
    order differ); compared with the brute-force minimum."""
    lo, hi, o, d, tmin, tmax = random_case(seed)
    extra = np.random.default_rng(seed).uniform(0, 3, len(lo))
    mask, near = brute_boxes(o, d, tmin, tmax, lo, hi)
    t_hit = np.where(mask & (near + extra <= tmax[:, None]), near + extra, np.inf)
    bvh = BVH.build(lo, hi)
    fn = lambda r, p: t_hit[r, p]
    t, prim = bvh.closest_hit(o, d, tmin, tmax, fn, max_pairs=101)
    np.testing.assert_array_equal(t, t_hit.min(axis=1))
    found = np.isfinite(t)
    assert np.array_equal(prim >= 0, found)
    np.testing.assert_array_equal(t_hit[np.flatnonzero(found), prim[found]], t[found])
    assert np.array_equal(bvh.any_hit(o, d, tmin, tmax, fn), found)


@pytest.mark.parametrize("seed", [0, 1])
def test_any_box_equals_brute_force(seed):
    """any_box with a box-overlap predicate (one that a node box passes whenever a box inside
    it does) finds the same queries as testing every primitive box."""
    lo, hi, _, _, _, _ = random_case(seed)
    rng = np.random.default_rng(seed + 10)
    c = rng.uniform(-6, 6, (500, 3))
    qlo, qhi = c - rng.uniform(0, 0.6, (500, 3)), c + rng.uniform(0, 0.6, (500, 3))

    def meets(q, blo, bhi):
        return np.all((blo <= qhi[q]) & (bhi >= qlo[q]), axis=1)

    bvh = BVH.build(lo, hi, leaf_size=4)
    got = bvh.any_box(len(c), meets, max_pairs=101)             # exercises chunking
    want = np.all((lo[None] <= qhi[:, None]) & (hi[None] >= qlo[:, None]), axis=2).any(1)
    assert 0 < want.sum() < len(c)
    np.testing.assert_array_equal(got, want)
