"""The paper's query rules, each pinned by a hand-built tree whose right answer is known
independently (through the public API only: TreeQuery's outputs and answer codes).

The trees have one viewpoint cell over the +Z face of the box [-1, 1]^2 x [-0.5, 0.5]: four
viewpoints at (+-1, +-1, 0.5), each with one direction leaf over the slot-0 domain
(u, v) in [-1, 1]^2, so every query ray entering the top face has the same 16 samples: corner j
of viewpoint k is sample 4 k + j, corners (0,0), (1,0), (0,1), (1,1) in cell coordinates
(lx, ly) = ((u + 1) / 2, (v + 1) / 2); the viewpoint level's (alpha, beta) is the entry point
scaled the same way. Samples carry the affine field of FIELD_O / FIELD_P with a constant
direction FIELD_DIR, which is not what the scene's mirrors do: an interpolated answer equals the
field exactly, an exactly traced one equals the tracer's f - so each answer's origin tells which
of the two produced it.

- two-patch rule (4.2): more than two classes among the 16 samples -> traced exactly;
- two classes -> the exact first hit against the candidate patches picks the class (and a miss
  there is a miss), whose samples alone are interpolated;
- a direction cell with one or two usable corners interpolates from its extra samples over the
  triangle of the cell holding the query (4.3, Figure 12).
"""

from dataclasses import replace

import numpy as np
import pytest

from riray.geometry.primitives import bilinear
from riray.trace.scene_tracer import SceneTracer
from riray.ritree.dircube import DOMAIN, N_SLOTS, UV_AXES
from riray.ritree.quadtree import Forest
from riray.ritree.query import (EXTRA_S, FULL, MISS, REDUCED, TRACED, WHY_CLASSES,
                                WHY_UNSAMPLED, WHY_USABLE,
                                QueryOptions, TreeQuery)
from riray.ritree.tree import BakeParams, RITree, Samples
from riray.scene.model import ObjectMaterial, Patch, RenderSettings, Scene, SpecularObject


def paper(**kw) -> QueryOptions:
    """The paper's rules (no baked-error tolerance, mirror rays blended), refused rays traced
    (not solved along a path), with options ``kw``."""
    return QueryOptions(**{"max_error_deg": None, "mirror_rays": "interpolate",
                            "many_classes": "trace", "solve_paths": False, **kw})


pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

BOX_LO, BOX_HI = np.array([-1.0, -1.0, -0.5]), np.array([1.0, 1.0, 0.5])
VIEWPOINTS = np.array([[-1, -1, 0.5], [1, -1, 0.5], [-1, 1, 0.5], [1, 1, 0.5]], float)
CELL = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], float)         # corner j at (lx, ly)
FIELD_O = np.array([[0.3, -0.2, 0.1], [0.05, 0.4, -0.3], [0.7, 0.1, 0.2], [-0.1, 0.25, 0.6]])
FIELD_P = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.5, 0.0]])
FIELD_DIR = np.array([1.0, 0.0, 0.0])       # sideways: never a reflection off z = 0
# Samples are stored in float32; affine fields come back to this (measured ~1e-7).
FIELD_TOL = 1e-5
# Rays closer than this to a boundary of a rule's region (cell coordinates) may go either way.
MARGIN = 1e-6
OPTS = paper(angle_deg=None)         # the pairwise thresholds are not the rules here


def field(x, y, lx, ly):
    """(out_o, out_d, point, normal) of the samples' affine field at viewpoint (x, y) and cell
    coordinates (lx, ly)."""
    X = np.stack([x, y, 2 * lx - 1, 2 * ly - 1], -1)
    n = X.shape[0]
    return (X @ FIELD_O + 0.1, np.tile(FIELD_DIR, (n, 1)), X @ FIELD_P,
            np.tile([0.0, 0.0, 1.0], (n, 1)))


def mirrors(*rects):
    """A tracer for flat mirrors at z = 0, patch i = rectangle (x0, x1, y0, y1) of class i."""
    def flat(x0, x1, y0, y1):
        return bilinear(*(np.array([x, y, 0.0]) for y in (y0, y1) for x in (x0, x1)))

    patches = [Patch(f"m{i}", i, surface=flat(*r)) for i, r in enumerate(rects)]
    obj = SpecularObject("mirrors", patches, ObjectMaterial(kind="mirror"))
    return SceneTracer(Scene(objects=[obj], render=RenderSettings(max_events=4)))


def one_cell_tree(patch, null=None, extras=None, n_classes=1):
    """The hand-built tree. ``patch`` (16,): patch id of each corner sample (-1: a miss; patch
    i has class i). ``null`` (16,) marks null samples (their output ray garbage, as a bake
    stores them). ``extras``: {viewpoint k: (kind, corner slots, [(lx, ly, patch, null)] * 4)}
    (kind 1: one usable corner L, slots (L, -1, -1, -1), extras v1, v2 on the edges leaving L;
    kind 2: slots (A1, A2, B1, B2), v1, v2 on the edges leaving A1, A2, v3, v4 leaving B1, B2);
    extra samples carry the field at their own cell coordinates."""
    vp_dom = np.array([[BOX_LO[a], BOX_HI[a], BOX_LO[b], BOX_HI[b]] for f in range(6)
                       for a, b in [UV_AXES[f // 2]]])
    vpf = Forest.empty(vp_dom)
    cell = vpf.add_roots(np.array([5]))
    vpf.corner[cell] = [0, 1, 2, 3]
    dom = DOMAIN[np.full(4, 5)].reshape(4 * N_SLOTS, 4)
    dirf = Forest.empty(dom)
    leaves = dirf.add_roots(np.arange(4) * N_SLOTS)
    dirf.corner[leaves] = np.arange(16).reshape(4, 4)
    k_of = np.repeat(np.arange(4), 4)
    pos = np.tile(CELL, (4, 1))
    pts = [(k_of, pos, np.asarray(patch), np.zeros(16, bool) if null is None else null)]
    ex = {"node": [], "kind": [], "ids": [], "pos": [], "corner": []}
    for k, (kind, slots, items) in sorted((extras or {}).items()):
        first = 16 + 4 * len(ex["node"])
        ex["node"].append(leaves[k])
        ex["kind"].append(kind)
        ex["corner"].append(slots)
        ex["ids"].append(first + np.arange(4))
        ex["pos"].append([it[:2] for it in items])
        pts.append((np.full(4, k), np.array([it[:2] for it in items], float),
                    np.array([it[2] for it in items]), np.array([it[3] for it in items])))
    k_of, pos, pid, nul = (np.concatenate(a) for a in zip(*pts))
    oo, od, pt, nm = (np.array(a, np.float32) for a in field(VIEWPOINTS[k_of, 0],
                                                              VIEWPOINTS[k_of, 1],
                                                              pos[:, 0], pos[:, 1]))
    nul = nul.astype(bool)
    oo[nul], od[nul] = 1e6, 0.0
    miss = pid < 0
    pt[miss], nm[miss] = 0.0, 0.0
    samples = Samples(out_o=oo, out_d=od, point=pt, normal=nm, patch=pid.astype(np.int32),
                      null=nul, tree=np.full(len(pid), 7, np.uint32))
    e = len(ex["node"])
    return RITree(params=BakeParams(viewpoint_depth=1, direction_depth=1, min_direction_depth=0),
                  box_lo=BOX_LO, box_hi=BOX_HI, diag=float(np.linalg.norm(BOX_HI - BOX_LO)),
                  class_of=np.arange(n_classes, dtype=np.int64), vp_forest=vpf,
                  vp_pos=VIEWPOINTS.copy(), vp_face=np.full(4, 5, np.int64), dir_forest=dirf,
                  dir_rect=dom.copy(), samples=samples,
                  ex_node=np.array(ex["node"], np.int64).reshape(e),
                  ex_kind=np.array(ex["kind"], np.int8).reshape(e),
                  ex_ids=np.array(ex["ids"], np.int64).reshape(e, 4),
                  ex_pos=np.array(ex["pos"], np.float32).reshape(e, 4, 2),
                  ex_corner=np.array(ex["corner"], np.int64).reshape(e, 4))


def queries(n, seed):
    """Rays entering the top face, downwards with slot-0 directions (u, v, -1): (o, d, alpha,
    beta, lx, ly, where they cross z = 0)."""
    rng = np.random.default_rng(seed)
    q = np.c_[rng.uniform(-0.98, 0.98, (n, 2)), np.full(n, 0.5)]
    uv = rng.uniform(-0.95, 0.95, (n, 2))
    d = np.c_[uv, -np.ones(n)]
    d /= np.linalg.norm(d, axis=1)[:, None]
    ground = q[:, :2] + 0.5 * uv
    return (q - 0.3 * d, d, (q[:, 0] + 1) / 2, (q[:, 1] + 1) / 2, (uv[:, 0] + 1) / 2,
            (uv[:, 1] + 1) / 2, ground)


def reflected(d):
    return d * [1, 1, -1]


def assert_field(res, rows, al, be, lx, ly):
    """Interpolated answers: the field at the query's (alpha, beta, lx, ly), exactly."""
    oo, od, pt, _ = field(2 * al[rows] - 1, 2 * be[rows] - 1, lx[rows], ly[rows])
    assert np.abs(res.out_origin[rows] - oo).max(initial=0) < FIELD_TOL
    assert np.abs(res.point[rows] - pt).max(initial=0) < FIELD_TOL
    assert np.abs(res.out_dir[rows] - od).max(initial=0) < FIELD_TOL


def assert_traced(res, rows, d, ground):
    """Exactly traced answers off the z = 0 mirrors: the reflection at the ground point."""
    assert res.hit[rows].all()
    assert np.abs(res.out_dir[rows] - reflected(d[rows])).max(initial=0) < 1e-9
    assert np.abs(res.out_origin[rows][:, :2] - ground[rows]).max(initial=0) < 1e-9


# --------------------------------------------------------------------------- two-patch rule
def test_more_than_two_classes_are_traced():
    """14 samples of patch 0 (a mirror under the whole box), one each of patches 1 and 2
    (mirrors far off to the side, never hit): three classes, so every ray is traced exactly -
    although class 0 alone would leave enough samples to interpolate from."""
    patch = np.zeros(16, int)
    patch[7], patch[8] = 1, 2
    tree = one_cell_tree(patch, n_classes=3)
    st = mirrors((-3, 3, -3, 3), (5, 6, 5, 6), (7, 8, 7, 8))
    o, d, al, be, lx, ly, ground = queries(2000, 1)
    res, ans, why, _ = TreeQuery(tree, st, OPTS)(o, d)
    assert np.all(ans == TRACED) and np.all(why == WHY_CLASSES)
    assert_traced(res, np.arange(len(o)), d, ground)
    assert np.all(res.cls == 0)
    # the same tree with patches 1, 2 relabelled to patch 0 (one class) interpolates
    res1, ans1, _, _ = TreeQuery(one_cell_tree(np.zeros(16, int), n_classes=3), st, OPTS)(o, d)
    assert np.all(ans1 == FULL)
    assert_field(res1, np.arange(len(o)), al, be, lx, ly)

def test_more_than_two_classes_take_the_exact_first_hits_class():
    """The same three-class tree, many_classes "first_hit": every ray's exact first hit is on
    patch 0, so the 14 class-0 samples answer it (the field, exactly: interpolation of an
    affine field is exact wherever a corner is missing too); none is traced for its classes,
    only where the missing corners leave too few usable samples (paper 4.3's triangles)."""
    patch = np.zeros(16, int)
    patch[7], patch[8] = 1, 2
    st = mirrors((-3, 3, -3, 3), (5, 6, 5, 6), (7, 8, 7, 8))
    o, d, al, be, lx, ly, _ = queries(2000, 1)
    res, ans, why, stats = TreeQuery(one_cell_tree(patch, n_classes=3), st,
                                     replace(OPTS, many_classes="first_hit"))(o, d)
    assert not np.any(why == WHY_CLASSES)
    answered = np.flatnonzero(ans != TRACED)
    assert len(answered) > 0.4 * len(o)
    assert np.all(why[ans == TRACED] == WHY_USABLE)
    assert np.all((ans[answered] == FULL) | (ans[answered] == REDUCED))
    assert_field(res, answered, al, be, lx, ly)
    assert np.all(res.cls == 0) and stats["exact_first_hits"] == len(o)


def test_more_than_two_classes_exact_miss_and_unsampled_hit():
    """Three classes among the samples, first_hit: a ray whose exact first hit misses every
    patch is a miss (its output the input ray, not traced); one whose first hit is on a patch
    of a class none of its samples has (patch 3) is traced as an unsampled hit, exactly."""
    patch = np.zeros(16, int)
    patch[7], patch[8] = 1, 2
    # patch 0 under x < 0 only; patch 3 (class 3, no sample) under x > 0, y > 0.5
    st = mirrors((-3, 0, -3, 3), (5, 6, 5, 6), (7, 8, 7, 8), (0, 3, 0.5, 3))
    o, d, al, be, lx, ly, ground = queries(2000, 2)
    opts = replace(OPTS, many_classes="first_hit")
    res, ans, why, _ = TreeQuery(one_cell_tree(patch, n_classes=4), st, opts)(o, d)
    gx, gy = ground[:, 0], ground[:, 1]
    miss = (gx > MARGIN) & (gy < 0.5 - MARGIN)
    other = (gx > MARGIN) & (gy > 0.5 + MARGIN)
    assert miss.sum() > 100 and other.sum() > 100
    assert np.all(ans[miss] == MISS) and not res.hit[miss].any()
    assert np.array_equal(res.out_dir[miss], d[miss])
    assert np.all((ans[other] == TRACED) & (why[other] == WHY_UNSAMPLED))
    assert_traced(res, np.flatnonzero(other), d, ground)
    assert np.all(res.cls[other] == 3)



# --------------------------------------------------------------------------- exact first hit
@pytest.mark.parametrize("other", ["patch", "miss"])
def test_two_classes_exact_first_hit_picks_the_class(other):
    """Corners (0,0), (1,0), (0,1) of every leaf are samples of patch 0, the mirror x < 0;
    corner (1,1) is of patch 1, the mirror x > 0 ("patch"), or a miss ("miss": nothing at
    x > 0). Two classes: the exact first hit against the candidate patches decides.
    - hit x < 0 (class 0): three usable corners per leaf: inside their triangle
      (lx + ly < 1) the field, barycentric in every leaf (REDUCED); outside it traced;
    - hit x > 0 (class 1): one usable corner: traced, class 1;
    - "miss", x > 0: nothing there: a miss, the input ray unchanged.
    Taking either class without the exact hit answers some rays from the wrong samples."""
    patch = np.zeros(16, int)
    patch[[3, 7, 11, 15]] = 1 if other == "patch" else -1
    tree = one_cell_tree(patch, n_classes=2)
    rects = [(-3, 0, -3, 3)] + ([(0, 3, -3, 3)] if other == "patch" else [])
    st = mirrors(*rects)
    o, d, al, be, lx, ly, ground = queries(4000, 2)
    res, ans, _, _ = TreeQuery(tree, st, OPTS)(o, d)
    clear = np.abs(ground[:, 0]) > MARGIN
    left = clear & (ground[:, 0] < 0)
    right = clear & (ground[:, 0] > 0)
    inside = np.abs(lx + ly - 1) > MARGIN
    tri = left & inside & (lx + ly < 1)
    assert tri.sum() > 500 and (right & (lx + ly < 1)).sum() > 500
    assert np.all(ans[tri] == REDUCED)
    assert_field(res, tri, al, be, lx, ly)
    assert np.all(res.cls[tri] == 0)
    assert np.all(ans[left & inside & (lx + ly > 1)] == TRACED)
    assert_traced(res, left & inside & (lx + ly > 1), d, ground)
    if other == "patch":
        assert np.all(ans[right] == TRACED) and np.all(res.cls[right] == 1)
        assert_traced(res, right, d, ground)
    else:
        assert np.all(ans[right] == MISS) and not res.hit[right].any()
        assert np.array_equal(res.out_dir[right], d[right])


# --------------------------------------------------------------------------- extra samples
def test_one_interpolant_cell_uses_its_extras():
    """Viewpoint 0's leaf: only corner L = (0,0) usable (the others null), extras v1 = (0.5, 0)
    and v2 = (0, 0.5) on the edges leaving L. A query in the triangle (L, v1, v2)
    (lx + ly < 0.5) is interpolated from it and the other three full leaves (EXTRA_S, the
    field exactly); elsewhere viewpoint 0 fails: the other three viewpoints interpolate inside
    their triangle (alpha + beta > 1, REDUCED), the rest is traced."""
    null = np.zeros(16, bool)
    null[[1, 2, 3]] = True
    extras = {0: (1, (0, -1, -1, -1), [(0.5, 0.0, 0, False), (0.0, 0.5, 0, False),
                                        (0.0, 0.0, 0, True), (0.0, 0.0, 0, True)])}
    check_extra_rule(null, extras, lambda lx, ly: lx + ly - 0.5)


def test_two_interpolant_cell_uses_its_extras():
    """Viewpoint 0's leaf: corners A1 = (0,0), A2 = (1,0) usable, (0,1) and (1,1) null; extras
    ea = (0, 0.5), eb = (1, 0.5) on the edges leaving them (the other side's extras null).
    The triangles (A1, A2, ea) and (A2, ea, eb) cover ly < 0.5: interpolated there (EXTRA_S,
    the field exactly); elsewhere as for a failing leaf."""
    null = np.zeros(16, bool)
    null[[2, 3]] = True
    extras = {0: (2, (0, 1, 2, 3), [(0.0, 0.5, 0, False), (1.0, 0.5, 0, False),
                                     (0.0, 0.6, 0, True), (1.0, 0.6, 0, True)])}
    check_extra_rule(null, extras, lambda lx, ly: ly - 0.5)


def check_extra_rule(null, extras, edge):
    """``edge(lx, ly) < 0``: the queries viewpoint 0's extras answer."""
    tree = one_cell_tree(np.zeros(16, int), null=null, extras=extras)
    st = mirrors((-3, 3, -3, 3))
    o, d, al, be, lx, ly, ground = queries(4000, 3)
    res, ans, _, _ = TreeQuery(tree, st, OPTS)(o, d)
    e = edge(lx, ly)
    clear = (np.abs(e) > MARGIN) & (np.abs(al + be - 1) > MARGIN)
    by_extras = clear & (e < 0)
    assert by_extras.sum() > 300
    assert np.all(ans[by_extras] == EXTRA_S)
    assert_field(res, by_extras, al, be, lx, ly)
    rest = clear & (e > 0)
    three = rest & (al + be > 1)
    assert np.all(ans[three] == REDUCED)
    assert_field(res, three, al, be, lx, ly)
    assert np.all(ans[rest & (al + be < 1)] == TRACED)
    assert_traced(res, rest & (al + be < 1), d, ground)


def test_stage_clock_counts_a_nested_stage_once():
    """A stage run inside another is that stage's CPU time only: the outer stage keeps its own
    work, and the two add up to the whole."""
    from riray.ritree.query import StageClock
    import time

    def spin(s):
        t = time.process_time()
        while time.process_time() - t < s:
            pass
    clock = StageClock()
    t0 = time.process_time()
    with clock("outer"):
        spin(0.02)
        with clock("inner"):
            spin(0.08)
    whole = time.process_time() - t0
    assert clock.cpu["inner"] >= 0.08
    assert 0.02 <= clock.cpu["outer"] < clock.cpu["inner"]
    assert abs(clock.cpu["outer"] + clock.cpu["inner"] - whole) < 0.01
