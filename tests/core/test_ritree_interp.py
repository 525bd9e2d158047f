"""RI-Tree building blocks against independent truths: the direction cube and the hemicube
slot table (paper 3.1-3.2), Forest.locate against a brute-force leaf search, and the
interpolation rules (paper 4.1-4.3, 5.1, 5.3) against exact affine/bilinear fields, linear
solves and double loops."""

import itertools

import numpy as np
import pytest

from riray.ritree.dircube import CUBE, DOMAIN, N_SLOTS, SLOT, UV_AXES, cube_to_dir, dir_to_cube
from riray.ritree.interp import (BILINEAR, EXTRAPOLATED, FAIL, TRIANGLE, UNIT_CORNERS,
                                 barycentric, cell_weights, drop_outlier, drop_outlier_units,
                                 far_pairs, pick_triangle,
                                 triangle_status)
from riray.ritree.quadtree import DenseLocator, Forest

RNG = np.random.default_rng(20240611)


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def expected_face(d):
    """Independent dominant-axis rule: the lowest axis among those of largest |component|."""
    a = np.abs(d)
    out = []
    for row, arow in zip(d, a):
        axis = min(k for k in range(3) if arow[k] == arow.max())
        out.append(2 * axis + (row[axis] > 0))
    return np.array(out)


def tie_directions():
    """Every direction with components in {-1, 0, 1} (cube face centres, edges, corners) and
    random |dx| = |dy|, |dx| = |dz|, |dy| = |dz| ties, in several scalings."""
    base = [p for p in itertools.product((-1.0, 0.0, 1.0), repeat=3) if any(p)]
    ties = []
    for _ in range(200):
        a = RNG.uniform(0.1, 2.0)
        b = RNG.uniform(-a, a)
        s1, s2 = RNG.choice([-1.0, 1.0], 2)
        i, j = RNG.choice(3, 2, replace=False)
        k = 3 - i - j
        v = np.zeros(3)
        v[i], v[j], v[k] = s1 * a, s2 * a, b
        ties.append(v)
    d = np.concatenate([np.array(base), np.array(ties)])
    return np.concatenate([d, 0.37 * d, 3.0 * d, unit(d)])


# --------------------------------------------------------------------------- direction cube
def test_dir_to_cube_round_trip_random():
    d = unit(RNG.normal(size=(20000, 3)))
    face, u, v = dir_to_cube(d)
    assert np.array_equal(face, expected_face(d))
    assert np.all(np.abs(u) <= 1) and np.all(np.abs(v) <= 1)
    assert np.allclose(cube_to_dir(face, u, v), d, atol=1e-15, rtol=0)
    # (u, v) are the world components named by UV_AXES divided by the dominant |component|
    axis = face // 2
    rows = np.arange(len(d))
    m = np.abs(d[rows, axis])
    ua = np.array([p[0] for p in UV_AXES])[axis]
    va = np.array([p[1] for p in UV_AXES])[axis]
    assert np.allclose(u, d[rows, ua] / m, atol=1e-15)
    assert np.allclose(v, d[rows, va] / m, atol=1e-15)


def test_cube_to_dir_round_trip_interior():
    face = RNG.integers(0, 6, 20000)
    u, v = RNG.uniform(-0.999, 0.999, (2, 20000))
    d = cube_to_dir(face, u, v)
    assert np.allclose(np.linalg.norm(d, axis=1), 1, atol=1e-15)
    f2, u2, v2 = dir_to_cube(d)
    assert np.array_equal(f2, face)
    assert np.allclose(u2, u, atol=1e-14) and np.allclose(v2, v, atol=1e-14)


def test_ties_map_to_exactly_one_face_consistently():
    d = tie_directions()
    face, u, v = dir_to_cube(d)
    assert np.array_equal(face, expected_face(d))           # lowest tied axis, its sign
    assert np.all(np.abs(u) <= 1) and np.all(np.abs(v) <= 1)
    assert np.all(np.isfinite(u)) and np.all(np.isfinite(v))
    # the dominant component really is the face's axis, with the face's sign
    rows = np.arange(len(d))
    dom = d[rows, face // 2]
    assert np.all(np.abs(dom) == np.abs(d).max(axis=1))
    assert np.all((dom > 0) == (face % 2 == 1))
    # scaling never changes the face or (u, v)
    n = len(d) // 4
    for k in range(1, 4):
        assert np.array_equal(face[k * n:(k + 1) * n], face[:n])
        assert np.allclose(u[k * n:(k + 1) * n], u[:n], atol=1e-15)
        assert np.allclose(v[k * n:(k + 1) * n], v[:n], atol=1e-15)
    # and the cube point maps back to the same direction
    assert np.allclose(cube_to_dir(face, u, v), unit(d), atol=1e-15)
    # a tie lands on the edge of the chosen face: some coordinate is exactly +-1
    edge = np.sum(np.abs(d) == np.abs(d).max(axis=1, keepdims=True), axis=1) > 1
    assert np.all(np.maximum(np.abs(u), np.abs(v))[edge] == 1.0)


def inward_directions(f):
    """Random, tied and axis-aligned directions entering the box through face f."""
    a, inward = f // 2, (-1.0 if f % 2 == 1 else 1.0)
    d = np.concatenate([RNG.normal(size=(5000, 3)), tie_directions(),
                        np.array(list(itertools.product((-1.0, 0.0, 1.0), repeat=3)))])
    d[:, a] = inward * np.abs(d[:, a])
    d = d[d[:, a] * inward > 0]
    # grazing directions (tiny inward component) too
    g = RNG.normal(size=(500, 3))
    g[:, a] = inward * 1e-9
    return np.concatenate([d, g])


@pytest.mark.parametrize("f", range(6))
def test_hemicube_slot_table(f):
    a = f // 2
    outward = f                       # the cube face along the box face's outward normal
    # the table is a bijection between the 5 slots and the 5 non-outward cube faces
    assert SLOT[f, outward] == -1
    assert sorted(CUBE[f].tolist()) == sorted(set(range(6)) - {outward})
    assert CUBE[f, 0] == outward ^ 1                              # slot 0: the opposite face
    for s in range(N_SLOTS):
        assert SLOT[f, CUBE[f, s]] == s
        u0, u1, v0, v1 = DOMAIN[f, s]
        area = (u1 - u0) * (v1 - v0)
        assert area == (4.0 if s == 0 else 2.0)
    # every inward direction has a valid slot and its (u, v) lies in that slot's DOMAIN
    d = inward_directions(f)
    c, u, v = dir_to_cube(d)
    s = SLOT[f, c]
    assert np.all(s >= 0)
    dom = DOMAIN[f, s]
    assert np.all((u >= dom[:, 0]) & (u <= dom[:, 1]) & (v >= dom[:, 2]) & (v <= dom[:, 3]))
    # conversely: every point of a slot's DOMAIN is an inward (or grazing, on its rim) direction
    for s in range(N_SLOTS):
        u0, u1, v0, v1 = DOMAIN[f, s]
        uu, vv = RNG.uniform(0, 1, (2, 2000))
        uu = np.concatenate([u0 + (u1 - u0) * uu, [u0, u1, u0, u1]])
        vv = np.concatenate([v0 + (v1 - v0) * vv, [v0, v0, v1, v1]])
        dd = cube_to_dir(np.full(len(uu), CUBE[f, s]), uu, vv)
        inward = -1.0 if f % 2 == 1 else 1.0
        assert np.all(dd[:, a] * inward >= 0)
        assert np.all(dd[:-4, a] * inward > 0)                    # interior: strictly inward


# --------------------------------------------------------------------------- quadtree forest
def random_forest(domains, max_depth, p_split, rng, corner_ids=True):
    """A random adaptive forest; returns (forest, leaves: list of (node, tree))."""
    f = Forest.empty(np.asarray(domains, np.float64))
    T = len(domains)
    built = np.flatnonzero(rng.random(T) < 0.85)
    if len(built) == 0:
        built = np.array([0])
    nodes = f.add_roots(built)
    tree_of = dict(zip(nodes.tolist(), built.tolist()))
    leaves = list(nodes)
    for _ in range(max_depth):
        split = [n for n in leaves if rng.random() < p_split]
        if not split:
            break
        kids = f.split(np.array(split, np.int64))
        for n, k in zip(split, kids):
            for kk in k:
                tree_of[int(kk)] = tree_of[n]
        leaves = [n for n in leaves if n not in set(split)] + kids.ravel().tolist()
    if corner_ids:
        f.corner[:] = np.arange(4 * len(f.child)).reshape(-1, 4)
    return f, tree_of


def brute_locate(f, tree_of, trees, x, y):
    """Scan every leaf: the half-open cell [i, i+1) / 2^l containing the clamped point, the
    upper end of the domain closed."""
    leaves = [n for n in range(len(f.child)) if f.child[n] < 0]
    out = np.full(len(trees), -1)
    lx = np.full(len(trees), np.nan)
    ly = np.full(len(trees), np.nan)
    for i, (t, xx, yy) in enumerate(zip(trees, x, y)):
        if f.root[t] < 0:
            continue
        d = f.domain[t]
        fx = min(max((xx - d[0]) / (d[1] - d[0]), 0.0), 1.0)
        fy = min(max((yy - d[2]) / (d[3] - d[2]), 0.0), 1.0)
        hits = []
        for n in leaves:
            if tree_of[n] != t:
                continue
            s = 2.0 ** int(f.level[n])
            ix, iy = int(f.ix[n]), int(f.iy[n])

            def inside(p, k):
                return (k / s <= p < (k + 1) / s) or (p == 1.0 and k + 1 == s)
            if inside(fx, ix) and inside(fy, iy):
                hits.append(n)
        assert len(hits) == 1, (t, xx, yy, hits)
        out[i] = hits[0]
        s = 2.0 ** int(f.level[hits[0]])
        lx[i] = fx * s - f.ix[hits[0]]
        ly[i] = fy * s - f.iy[hits[0]]
    return out, lx, ly


def check_locate(f, tree_of, trees, x, y):
    node, lx, ly = f.locate(trees, x, y)
    want, wlx, wly = brute_locate(f, tree_of, trees, x, y)
    assert np.array_equal(node, want)
    ok = node >= 0
    assert np.all(np.isfinite(lx[ok])) and np.all(np.isfinite(ly[ok]))
    assert np.all((lx[ok] >= 0) & (lx[ok] <= 1) & (ly[ok] >= 0) & (ly[ok] <= 1))
    assert np.allclose(lx[ok], wlx[ok], atol=1e-12) and np.allclose(ly[ok], wly[ok], atol=1e-12)
    assert np.all(f.child[node[ok]] < 0)
    return node, lx, ly


@pytest.mark.parametrize("seed", range(4))
def test_locate_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    T = 7
    lo = rng.uniform(-3, 3, (T, 2))
    size = rng.uniform(0.01, 5, (T, 2))
    doms = np.stack([lo[:, 0], lo[:, 0] + size[:, 0], lo[:, 1], lo[:, 1] + size[:, 1]], 1)
    doms[0] = (0.0, 1.0, 0.0, 1.0)                      # dyadic-exact domains too
    doms[1] = (-1.0, 1.0, -2.0, 2.0)
    f, tree_of = random_forest(doms, 7, 0.45, rng)
    n = 600
    trees = rng.integers(0, T, n)
    d = f.domain[trees]
    fx, fy = rng.uniform(0, 1, (2, n))
    # exactly on cell boundaries of the finest grid (k / 2^L), on domain edges and corners
    L = f.max_level
    gx = rng.integers(0, (1 << L) + 1, n) / (1 << L)
    gy = rng.integers(0, (1 << L) + 1, n) / (1 << L)
    kinds = rng.integers(0, 4, n)
    fx = np.where(kinds == 1, gx, fx)
    fy = np.where(kinds >= 1, gy, fy)
    fx = np.where(kinds == 3, rng.choice([0.0, 1.0], n), fx)
    fy = np.where(kinds == 3, rng.choice([0.0, 1.0], n), fy)
    x = d[:, 0] + (d[:, 1] - d[:, 0]) * fx
    y = d[:, 2] + (d[:, 3] - d[:, 2]) * fy
    node, lx, ly = check_locate(f, tree_of, trees, x, y)
    assert np.all(node[f.root[trees] >= 0] >= 0)
    assert np.all(node[f.root[trees] < 0] == -1)


@pytest.mark.parametrize("budget", [64 << 20, 4 * 7 * 4 ** 3])
def test_dense_locator_one_point_in_four_trees_matches_brute_force(budget):
    """DenseLocator with one point per row looked up in four trees at once ((n, 1) points
    against (n, 4) trees, as the query locates a ray's four direction leaves): each column is
    the brute-force leaf of that tree. A small budget makes the table shallower than the
    forest, so the table's nodes are descended further."""
    rng = np.random.default_rng(1)                  # two of the seven trees unbuilt
    T = 7
    doms = np.tile([0.0, 1.0, 0.0, 1.0], (T, 1))
    f, tree_of = random_forest(doms, 6, 0.5, rng)
    loc = DenseLocator(f, budget_bytes=budget)
    assert (loc.level < f.max_level) == (budget < 64 << 20)
    n = 400
    trees = rng.integers(0, T, (n, 4))
    L = f.max_level
    fx = np.where(rng.random(n) < 0.3, rng.integers(0, (1 << L) + 1, n) / (1 << L), rng.random(n))
    fy = rng.random(n)
    node, lx, ly = loc.locate_normalized(trees, fx[:, None], fy[:, None])
    assert node.shape == lx.shape == ly.shape == (n, 4)
    assert np.any(f.root[trees] < 0) and np.all(node[f.root[trees] < 0] == -1)   # unbuilt trees
    for k in range(4):
        want, wlx, wly = brute_locate(f, tree_of, trees[:, k], fx, fy)
        assert np.array_equal(node[:, k], want)
        ok = want >= 0
        assert np.allclose(lx[ok, k], wlx[ok], atol=1e-12)
        assert np.allclose(ly[ok, k], wly[ok], atol=1e-12)


def test_locate_outside_domain_is_clamped():
    rng = np.random.default_rng(7)
    doms = np.array([(0.0, 1.0, 0.0, 1.0), (-2.0, 6.0, 1.0, 1.5)])
    f, tree_of = random_forest(doms, 6, 0.6, rng)
    f.root[:] = np.maximum(f.root, -1)
    trees = np.repeat(np.flatnonzero(f.root >= 0), 12)
    d = f.domain[trees]
    span = np.array([-1e300, -np.inf, -5.0, -1e-12, 1e-12, 5.0, np.inf, 1e300])
    x = d[:, 0] + (d[:, 1] - d[:, 0]) * np.resize(np.r_[span, 0.5, 0.5, 0.25, 1.0], len(trees))
    y = d[:, 2] + (d[:, 3] - d[:, 2]) * np.resize(np.r_[0.5, 0.0, 1.0, 0.3, span], len(trees))
    node, lx, ly = check_locate(f, tree_of, trees, x, y)
    assert np.all(node >= 0)
    # exactly the domain's corners
    for cx, cy in itertools.product((0, 1), (0, 1)):
        t = trees[:1]
        dd = f.domain[t]
        check_locate(f, tree_of, t, dd[:, cx], dd[:, 2 + cy])


def test_locate_uniform_grid_and_unbuilt_tree():
    """A uniform depth-3 grid: every grid line point goes to the upper cell (doc), the last
    line to the last cell; an unbuilt tree answers -1."""
    f = Forest.empty(np.array([(0.0, 8.0, 0.0, 8.0), (0.0, 1.0, 0.0, 1.0)]))
    nodes = f.add_roots(np.array([0]))
    for _ in range(3):
        nodes = f.split(nodes).ravel()
    k = np.arange(9.0)
    x, y = np.meshgrid(k, k, indexing="ij")
    x, y = x.ravel(), y.ravel()
    node, lx, ly = f.locate(np.zeros(len(x), np.int64), x, y)
    ix = np.minimum(x, 7).astype(int)
    iy = np.minimum(y, 7).astype(int)
    assert np.array_equal(f.ix[node], ix) and np.array_equal(f.iy[node], iy)
    assert np.array_equal(lx, (x - ix).astype(float)) and np.array_equal(ly, (y - iy).astype(float))
    node, lx, ly = f.locate(np.array([1]), np.array([0.5]), np.array([0.5]))
    assert node[0] == -1 and np.isfinite(lx[0]) and np.isfinite(ly[0])


# --------------------------------------------------------------------------- interpolation
def affine_field(n_out=5, rng=RNG):
    A = rng.normal(size=(2, n_out))
    b = rng.normal(size=n_out)
    return lambda p: b + p @ A


def bilinear_field(n_out=5, rng=RNG):
    aff = affine_field(n_out, rng)
    c = rng.normal(size=n_out)
    return lambda p: aff(p) + (p[:, 0] * p[:, 1])[:, None] * c


PATTERNS = [np.array(p, bool) for p in itertools.product((False, True), repeat=4)]


def solve_bary(q, tri):
    """Barycentric coordinates by a 3x3 linear solve per point (independent of interp)."""
    out = []
    for qq, t in zip(q, tri):
        M = np.vstack([t.T, np.ones(3)])
        out.append(np.linalg.solve(M, np.r_[qq, 1.0]))
    return np.array(out)


@pytest.mark.parametrize("usable", PATTERNS, ids=lambda p: "".join("1" if x else "0" for x in p))
def test_cell_weights_every_pattern(usable):
    cnt = int(usable.sum())
    n = 400
    q = np.concatenate([UNIT_CORNERS, RNG.uniform(0, 1, (n, 2)),
                        [[0.5, 0.5], [0.25, 0.75], [0.75, 0.25], [0.5, 0.0], [1.0, 0.5]]])
    us = np.broadcast_to(usable, (len(q), 4))
    w, st = cell_weights(us, q[:, 0], q[:, 1])
    assert w.shape == (len(q), 4) and np.all(np.isfinite(w))
    if cnt < 3:
        assert np.all(st == FAIL) and np.all(w == 0)
        return
    good = st != FAIL
    assert np.all(w[:, ~usable] == 0)                                   # never an unusable corner
    assert np.allclose(w[good].sum(1), 1.0, atol=1e-14)
    assert np.all(w[~good] == 0)
    # corners: usable corners reproduce their own value exactly
    for k in np.flatnonzero(usable):
        assert st[k] in (BILINEAR, TRIANGLE)
        assert np.array_equal(w[k], np.eye(4)[k])
    field = bilinear_field() if cnt == 4 else affine_field()
    vals = field(UNIT_CORNERS)                                          # (4, 5)
    est = w @ vals
    assert np.allclose(est[good], field(q[good]), atol=1e-12)
    if cnt == 4:
        assert np.all(st == BILINEAR)
        return
    # three usable: TRIANGLE exactly inside the triangle of the usable corners (edges included)
    tri = UNIT_CORNERS[usable]
    lam = solve_bary(q, np.broadcast_to(tri, (len(q), 3, 2)))
    inside = lam.min(1) >= -1e-12
    assert np.array_equal(st == TRIANGLE, inside)
    assert np.all(st[~inside] == FAIL)                                  # extrapolation off
    missing = np.flatnonzero(~usable)[0]
    assert st[missing] == FAIL


@pytest.mark.parametrize("missing", range(4))
@pytest.mark.parametrize("thr", [0.0, 0.1, 0.35, 1.0, 2.0])
def test_cell_weights_extrapolation_threshold(missing, thr):
    usable = np.ones(4, bool)
    usable[missing] = False
    q = np.concatenate([RNG.uniform(-0.2, 1.2, (3000, 2)), UNIT_CORNERS])
    us = np.broadcast_to(usable, (len(q), 4))
    w, st = cell_weights(us, q[:, 0], q[:, 1], extrapolation=thr)
    lam = solve_bary(q, np.broadcast_to(UNIT_CORNERS[usable], (len(q), 3, 2)))
    mn = lam.min(1)
    sure_in = mn >= 1e-9
    sure_ext = (mn < -1e-9) & (mn >= -thr + 1e-9)
    sure_out = mn < -thr - 1e-9
    assert np.all(st[sure_in] == TRIANGLE)
    assert np.all(st[sure_ext] == EXTRAPOLATED)
    assert np.all(st[sure_out] == FAIL) and np.all(w[sure_out] == 0)
    assert np.all(st[mn < -thr - 1e-9] != EXTRAPOLATED)                # only within threshold
    # extrapolated values still reproduce an affine field exactly
    field = affine_field()
    good = st != FAIL
    assert np.allclose(w[good] @ field(UNIT_CORNERS), field(q[good]), atol=1e-11)
    assert np.array_equal(w[good][:, missing], np.zeros(good.sum()))
    # the missing corner itself lies at barycentric distance 1 from the triangle
    assert st[len(q) - 4 + missing] == (EXTRAPOLATED if thr >= 1.0 else FAIL)


def test_bilinear_reproduces_bilinear_fields_inside_cell():
    q = RNG.uniform(0, 1, (5000, 2))
    field = bilinear_field(7)
    w, st = cell_weights(np.ones((len(q), 4), bool), q[:, 0], q[:, 1])
    assert np.all(st == BILINEAR)
    assert np.allclose(w @ field(UNIT_CORNERS), field(q), atol=1e-12)
    assert np.all(w >= 0)


def cross2(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def degenerate_triangles(n, rng):
    a = rng.uniform(-1, 2, (n, 2))
    e = rng.normal(size=(n, 2))
    t = rng.uniform(-2, 2, (n, 2))
    tri = np.stack([a, a + t[:, :1] * e, a + t[:, 1:] * e], 1)         # collinear
    tri[: n // 4, 1] = tri[: n // 4, 0]                                  # coincident vertices
    tri[n // 4: n // 2] = tri[n // 4: n // 2, :1]                        # all three the same
    return tri


def test_barycentric_degenerate_no_nan():
    n = 400
    tri = degenerate_triangles(n, RNG)
    q = RNG.uniform(-1, 2, (n, 2))
    q[:50] = tri[:50, 0]                                                 # on the "triangle"
    lam, ok = barycentric(q, tri)
    assert not ok.any()
    assert np.all(lam == 0) and np.all(np.isfinite(lam))
    for extra in (None, 0.0, 10.0, 1e9):
        assert np.all(triangle_status(lam, ok, extra) == FAIL)
    # nearly collinear (area far below the degeneracy limit) is degenerate too
    tri2 = np.array([[[0, 0], [1, 0], [0.5, 1e-13]]] * 3, float)
    lam2, ok2 = barycentric(np.array([[0.5, 0.0], [0.2, 5.0], [3.0, 3.0]]), tri2)
    assert not ok2.any() and np.all(np.isfinite(lam2))


def test_barycentric_matches_linear_solve():
    n = 2000
    tri = RNG.uniform(-1, 2, (n, 3, 2))
    q = RNG.uniform(-1, 2, (n, 2))
    lam, ok = barycentric(q, tri)
    area2 = np.abs(cross2(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    big = area2 > 1e-3
    assert np.all(ok[big])
    assert np.allclose(lam[big], solve_bary(q[big], tri[big]), atol=1e-8)
    assert np.allclose(lam[big].sum(1), 1.0, atol=1e-12)


def test_pick_triangle_degenerate_and_rules():
    rng = np.random.default_rng(3)
    n = 3000
    good_tri = rng.uniform(-0.5, 1.5, (n, 3, 2))
    area2 = np.abs(cross2(good_tri[:, 1] - good_tri[:, 0], good_tri[:, 2] - good_tri[:, 0]))
    good_tri = good_tri[area2 > 0.05][:2000]
    n = len(good_tri)
    bad_tri = degenerate_triangles(n, rng)
    q = rng.uniform(-0.5, 1.5, (n, 2))
    for thr in (None, 0.3):
        # both degenerate: FAIL, no NaN
        tris = np.stack([bad_tri, bad_tri[::-1]], 1)
        which, lam, st = pick_triangle(q, tris, np.ones((n, 2), bool), thr)
        assert np.all(st == FAIL) and np.all(np.isfinite(lam))
        # first degenerate, second valid: answers come only from the valid one
        tris = np.stack([bad_tri, good_tri], 1)
        which, lam, st = pick_triangle(q, tris, np.ones((n, 2), bool), thr)
        assert np.all(np.isfinite(lam))
        ref = solve_bary(q, good_tri)
        mn = ref.min(1)
        ans = st != FAIL
        assert np.all(which[ans] == 1)
        assert np.allclose(lam[ans], ref[ans], atol=1e-8)
        assert np.all(st[mn > 1e-9] == TRIANGLE)
        if thr is None:
            assert np.all(st[mn < -1e-9] == FAIL)
        else:
            assert np.all(st[(mn < -1e-9) & (mn > -thr + 1e-9)] == EXTRAPOLATED)
            assert np.all(st[mn < -thr - 1e-9] == FAIL)
        # a valid triangle flagged invalid is never used
        tris = np.stack([good_tri, good_tri], 1)
        which, lam, st = pick_triangle(q, tris, np.zeros((n, 2), bool), thr)
        assert np.all(st == FAIL)


def test_pick_triangle_prefers_first_containing():
    rng = np.random.default_rng(4)
    n = 3000
    t0 = np.broadcast_to(np.array([[0, 0], [1, 0], [0, 1]], float), (n, 3, 2))
    t1 = np.broadcast_to(np.array([[1, 0], [0, 1], [1, 1]], float), (n, 3, 2))
    q = rng.uniform(0, 1, (n, 2))
    which, lam, st = pick_triangle(q, np.stack([t0, t1], 1), np.ones((n, 2), bool))
    lower = q.sum(1) < 1 - 1e-9
    upper = q.sum(1) > 1 + 1e-9
    assert np.all(st == TRIANGLE)
    assert np.all(which[lower] == 0) and np.all(which[upper] == 1)
    field = affine_field()
    verts = np.where((which == 0)[:, None, None], t0, t1)
    est = np.einsum("nk,nkc->nc", lam, field(verts.reshape(-1, 2)).reshape(n, 3, -1))
    assert np.allclose(est, field(q), atol=1e-12)


def brute_far(dirs, origins, used, max_angle, max_dist):
    """(N, K, K) far pairs by a double loop over arccos angles and Euclidean gaps."""
    n, k = used.shape
    out = np.zeros((n, k, k), bool)
    for i in range(n):
        idx = np.flatnonzero(used[i])
        for a in idx:
            for b in idx:
                if max_angle is not None:
                    c = np.clip(np.dot(dirs[i, a], dirs[i, b]), -1, 1)
                    out[i, a, b] |= np.arccos(c) > max_angle
                gap = np.linalg.norm(origins[i, a] - origins[i, b])
                out[i, a, b] |= max_dist is not None and gap > max_dist
    return out


def near_limit(dirs, origins, used, max_angle, max_dist, eps=1e-7):
    """Pairs (N, K, K) within eps of a threshold (either answer is right)."""
    amb = np.zeros(used.shape + used.shape[1:], bool)
    pair = used[:, :, None] & used[:, None, :]
    if max_angle is not None:
        ang = 2 * np.arctan2(np.linalg.norm(dirs[:, :, None] - dirs[:, None], axis=3),
                             np.linalg.norm(dirs[:, :, None] + dirs[:, None], axis=3))
        amb |= pair & (np.abs(ang - max_angle) < eps)
    if max_dist is not None:
        dd = np.linalg.norm(origins[:, :, None] - origins[:, None], axis=3)
        amb |= pair & (np.abs(dd - max_dist) < eps)
    return amb


@pytest.mark.parametrize("max_angle,max_dist", [(np.radians(20), None), (None, 0.3),
                                                (np.radians(5), 0.1), (None, None),
                                                (np.radians(179), 2.0), (0.0, None)])
def test_far_pairs_match_double_loop(max_angle, max_dist):
    rng = np.random.default_rng(5)
    N, K = 600, 24
    centre = unit(rng.normal(size=(N, 1, 3)))
    spread = rng.choice([0.01, 0.1, 0.3, 1.0], (N, 1, 1))
    dirs = unit(centre + spread * rng.normal(size=(N, K, 3))).astype(np.float32).astype(float)
    dirs = unit(dirs)
    origins = rng.normal(size=(N, 1, 3)) + rng.choice([0.01, 0.05, 0.2], (N, 1, 1)) * \
        rng.normal(size=(N, K, 3))
    used = rng.random((N, K)) < rng.choice([0.0, 0.1, 0.5, 1.0], (N, 1))
    used[:5] = False
    used[5:10, 0] = True                       # single interpolant rows
    used[5:10, 1:] = False
    if max_angle == 0.0:
        dirs[20:40] = dirs[20:40, :1]          # identical directions pass even at 0
    dirs[40:60, 1] = -dirs[40:60, 0]           # antipodal pairs (chord 2, angle pi)
    used[40:60, :2] = True
    rows, sub = far_pairs(dirs, origins, used, max_angle, max_dist)
    got = np.zeros((N, K, K), bool)
    got[rows] = sub
    want = brute_far(dirs, origins, used, max_angle, max_dist)
    amb = near_limit(dirs, origins, used, max_angle, max_dist)
    assert np.array_equal(got[~amb], want[~amb])
    assert not got[:10].any()                            # nothing or one interpolant used
    assert np.array_equal(got, got.transpose(0, 2, 1))
    rows = want.any(axis=(1, 2))
    assert 0 < rows.sum() < N or max_angle is None and max_dist is None or max_angle == 0.0
    if max_angle == np.radians(179):
        assert np.all(want[40:60, 0, 1])                 # antipodal pairs are far at 179 deg


def test_drop_outlier_rules():
    """Rows of four cell corners (positions UNIT_CORNERS) with hand-set far pairs."""
    def far_of(pairs):
        f = np.zeros((4, 4), bool)
        for a, b in pairs:
            f[a, b] = f[b, a] = True
        return f
    cases = [  # (far pairs, used, query) -> (usable after, changed)
        ([], [1, 1, 1, 1], (0.2, 0.2), [1, 1, 1, 1], False),
        ([(3, 0), (3, 1), (3, 2)], [1, 1, 1, 1], (0.2, 0.2), [1, 1, 1, 0], True),   # outlier
        ([(3, 0), (3, 1), (3, 2)], [1, 1, 1, 1], (0.9, 0.9), [1, 1, 1, 0], True),   # even nearest
        ([(0, 3)], [1, 1, 1, 1], (0.1, 0.2), [1, 1, 1, 0], True),   # tie: farthest from q goes
        ([(0, 3)], [1, 1, 1, 1], (0.9, 0.7), [0, 1, 1, 1], True),
        ([(0, 1), (2, 3)], [1, 1, 1, 1], (0.5, 0.5), [0, 0, 0, 0], True),   # two groups: none
        ([(0, 1), (0, 2), (1, 3), (2, 3)], [1, 1, 1, 1], (0.5, 0.5), [0, 0, 0, 0], True),
        ([(0, 3)], [1, 1, 1, 0], (0.5, 0.5), [1, 1, 1, 0], False),  # far pair with an unused
        ([(0, 1)], [1, 1, 0, 0], (0.1, 0.1), [1, 0, 0, 0], True),
    ]
    far = np.stack([far_of(c[0]) for c in cases])
    used = np.array([c[1] for c in cases], bool)
    q = np.array([c[2] for c in cases], float)
    out, changed = drop_outlier(far, used, UNIT_CORNERS, q)
    assert np.array_equal(out, np.array([c[3] for c in cases], bool))
    assert np.array_equal(changed, np.array([c[4] for c in cases]))
    assert np.array_equal(used, np.array([c[1] for c in cases], bool))   # input untouched


def test_drop_outlier_units_is_drop_outlier_per_row():
    """Per-unit degrees and leftovers give drop_outlier's answer on every row of every unit,
    asymmetric far matrices and exact distance ties included."""
    rng = np.random.default_rng(5)
    u = 400
    far = rng.random((u, 4, 4)) < 0.35
    sym = rng.random(u) < 0.5
    far[sym] |= np.transpose(far[sym], (0, 2, 1))
    far[:, np.arange(4), np.arange(4)] = False
    used = rng.random((u, 4)) < 0.8
    unit = rng.integers(0, u, 3000)
    q = rng.random((3000, 2))
    q[::7] = 0.5                                        # exact ties in the distance
    want = drop_outlier(far[unit], used[unit], UNIT_CORNERS, q)
    got = drop_outlier_units(far, used, unit, UNIT_CORNERS, q)
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    assert want[1].any() and (want[0] != used[unit]).any()


def test_group_rows_against_a_dictionary():
    """query.group_rows: groups numbered in sorted key order, each group's first row the
    smallest row index holding its key; runs of equal neighbours and scattered repeats."""
    from riray.ritree.query import group_rows
    rng = np.random.default_rng(11)
    for trial in range(60):
        # small keys; keys beyond 31 bits or negative (sorted as given, not packed in pairs);
        # 1-4 columns
        lo, hi = [(0, 4), (-3, 2), (0, 1 << 40)][trial % 3]
        base = rng.integers(lo, hi, (int(rng.integers(1, 30)), 1 + trial % 4))
        pick = base[rng.integers(0, len(base), 200)]
        keys = np.repeat(pick, rng.integers(1, 5, 200), axis=0)
        group, first = group_rows(keys)
        distinct = sorted({tuple(k) for k in keys})
        assert len(first) == len(distinct)
        for g, key in enumerate(distinct):
            rows = [i for i in range(len(keys)) if tuple(keys[i]) == key]
            assert first[g] == rows[0]
            assert np.array_equal(np.flatnonzero(group == g), rows)
    assert [len(a) for a in group_rows(np.zeros((0, 4), np.int64))] == [0, 0]
