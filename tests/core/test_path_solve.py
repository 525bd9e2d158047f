"""Rays solved exactly along a sample's path (ritree/query/paths.py), against the exact tracer.

These trees are baked for viewpoint cells, not cameras, so no viewpoint cell is measured: kept
to its tolerance (no fallback angle), the query refuses every located ray that hits, and each
goes to the path solver or the tracer. What the solver answers must be the traced answer
(same events, same output ray to Newton's tolerance), and what it cannot match must be traced,
never answered wrongly: a glass sphere (two refractions, one patch), a glass slab of six faces
(paths through different faces, total internal reflections at the sides) and a mirror corner
(one or two reflections).
"""

from dataclasses import replace

import numpy as np
import pytest

from riray.geometry.primitives import bilinear, box_faces, sphere
from riray.ritree.bake import bake
from riray.ritree.query import paths
from riray.ritree.query import SOLVED, TRACED, QueryOptions, TreeQuery
from riray.ritree.region import Region
from riray.ritree.tree import BakeParams
from riray.scene.model import ObjectMaterial, Patch, RenderSettings, Scene, SpecularObject
from riray.trace.scene_tracer import SceneTracer

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")


REFUSE_ALL = QueryOptions(max_error_deg=0.0, fallback_angle_deg=None)
# Newton stops within NEWTON_TOL_REL (1e-9) of the diagonal; through a few events that stays far
# below these (radians, and fractions of the box diagonal).
DIR_TOL = 1e-6
POS_TOL = 1e-6


def P(x, y, z):
    return np.array([x, y, z], float)


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def scene_of(obj, max_events=8):
    return SceneTracer(Scene(objects=[obj], render=RenderSettings(max_events=max_events)))


def top_cells(depth, lo, hi):
    """The viewpoint cells of the +Z face whose index range is [lo, hi) * 2^depth per axis."""
    n = 1 << depth
    cells = np.zeros((6, n, n), bool)
    cells[5, int(lo * n):int(hi * n), int(lo * n):int(hi * n)] = True
    region = Region(cells=cells)
    region.describe = lambda: {"kind": "cells", "cells": int(cells.sum())}
    return region


def down_rays(st, n, seed, frac=(0.3, 0.7), spread=0.6):
    """Rays entering the top of the object's box inside ``frac`` of it, going down."""
    rng = np.random.default_rng(seed)
    lo, hi = st.box_lo, st.box_hi
    f = rng.uniform(frac[0], frac[1], (n, 2))
    q = np.c_[lo[:2] + (hi[:2] - lo[:2]) * f, np.full(n, hi[2])]
    d = unit(np.c_[rng.uniform(-spread, spread, (n, 2)), -np.ones(n)])
    return q - 0.05 * d, d


def aimed_rays(st, n, seed, frac):
    """Rays entering the top of the object's box inside ``frac`` of it, aimed at points
    spread through the box (hits all over the upper half of a sphere, not only its pole)."""
    rng = np.random.default_rng(seed)
    lo, hi = st.box_lo, st.box_hi
    f = rng.uniform(frac[0], frac[1], (n, 2))
    q = np.c_[lo[:2] + (hi[:2] - lo[:2]) * f, np.full(n, hi[2])]
    d = unit(lo + (hi - lo) * rng.uniform(0.0, 1.0, (n, 3)) * [1, 1, 0.6] - q)
    return q - 0.05 * d, d


def answers(st, tree, o, d):
    """(tree result, answer codes, exact result) with every interpolation refused."""
    res, ans, _, stats = TreeQuery(tree, st, REFUSE_ALL)(o, d)
    assert stats["solved_along_path"] == np.sum(ans == SOLVED)
    return res, ans, st.object_function(o, d)


def assert_exact(res, ex, rows):
    """The solved rows carry the traced answer (a trapped ray's null direction included)."""
    assert np.array_equal(res.hit[rows], ex.hit[rows])
    assert np.array_equal(res.null[rows], ex.null[rows])
    assert np.array_equal(res.events[rows], ex.events[rows])
    assert np.array_equal(res.tree[rows], ex.tree[rows])
    assert np.abs(res.out_dir[rows] - ex.out_dir[rows]).max(initial=0) < DIR_TOL
    out = rows[~ex.null[rows]]         # a trapped ray's output origin means nothing
    assert np.abs(res.out_origin[out] - ex.out_origin[out]).max(initial=0) < POS_TOL
    assert np.abs(res.point[rows] - ex.point[rows]).max(initial=0) < POS_TOL
    assert np.all(np.isfinite(res.out_dir[rows]))


@pytest.fixture(scope="module")
def ball():
    st = scene_of(SpecularObject("ball", [Patch("s", 0, surface=sphere((0, 0, 0), 0.15))],
                                 ObjectMaterial(kind="glass", ior=1.5)))
    return st, bake(st, BakeParams(viewpoint_depth=3, direction_depth=4),
                    region=top_cells(3, 0.0, 0.25), workers=1)


def glass_slab(max_events):
    """A glass block of six faces, one class each, baked over the middle of its top face."""
    faces = box_faces((-1, -1, 0), (1, 1, 1.2))
    st = scene_of(SpecularObject("slab", [Patch(f"f{i}", i, surface=f)
                                          for i, f in enumerate(faces)],
                                 ObjectMaterial(kind="glass", ior=1.5)), max_events)
    return st, bake(st, BakeParams(viewpoint_depth=2, direction_depth=4),
                    region=top_cells(2, 0.25, 0.75), workers=1)


@pytest.fixture(scope="module")
def slab():
    return glass_slab(8)


@pytest.fixture(scope="module")
def trapping_slab():
    """The slab with max_events 2: rays with a third hit are trapped (null)."""
    return glass_slab(2)


@pytest.fixture(scope="module")
def corner():
    """Two mirrors at right angles: a floor and a wall, so rays reflect once or twice."""
    floor = bilinear(P(-1, -1, 0), P(1, -1, 0), P(-1, 1, 0), P(1, 1, 0))
    wall = bilinear(P(1, -1, 0), P(1, 1, 0), P(1, -1, 1), P(1, 1, 1))
    st = scene_of(SpecularObject("corner", [Patch("floor", 0, surface=floor),
                                            Patch("wall", 1, surface=wall)],
                                 ObjectMaterial(kind="mirror")))
    return st, bake(st, BakeParams(viewpoint_depth=2, direction_depth=4),
                    region=top_cells(2, 0.25, 0.75), workers=1)


@pytest.fixture(scope="module")
def blocked():
    """The mirror corner with a strip of mirror floating over the floor: rays meet it on the
    way in or on their way up from the floor, between samples that do not."""
    floor = bilinear(P(-1, -1, 0), P(1, -1, 0), P(-1, 1, 0), P(1, 1, 0))
    wall = bilinear(P(1, -1, 0), P(1, 1, 0), P(1, -1, 1), P(1, 1, 1))
    strip = bilinear(P(0.1, -1, 0.5), P(0.3, -1, 0.5), P(0.1, 1, 0.5), P(0.3, 1, 0.5))
    st = scene_of(SpecularObject("blocked", [Patch("floor", 0, surface=floor),
                                             Patch("wall", 1, surface=wall),
                                             Patch("strip", 2, surface=strip)],
                                 ObjectMaterial(kind="mirror")))
    return st, bake(st, BakeParams(viewpoint_depth=2, direction_depth=4),
                    region=top_cells(2, 0.25, 0.75), workers=1)


def test_glass_sphere_rays_are_solved_exactly(ball):
    """Two refractions on one patch: nearly every hit is solved, each exactly as traced."""
    st, tree = ball
    o, d = aimed_rays(st, 3000, 1, (0.02, 0.23))
    res, ans, ex = answers(st, tree, o, d)
    solved = np.flatnonzero(ans == SOLVED)
    assert len(solved) > 0.8 * ex.hit.sum()
    assert_exact(res, ex, solved)
    assert np.all(ex.events[solved] == 2)


@pytest.mark.parametrize("name", ["slab", "corner", "blocked"])
def test_solved_paths_are_the_traced_paths(name, request):
    """Paths over several patches, with total internal reflections (slab), a second reflection
    (corner) or a patch in the way of some rays' samples' paths (blocked): the solved rays are
    exact, the rest are traced, none answered by another path; and both kinds occur."""
    st, tree = request.getfixturevalue(name)
    o, d = down_rays(st, 4000, 2, (0.3, 0.7), 1.5)
    res, ans, ex = answers(st, tree, o, d)
    solved = np.flatnonzero(ans == SOLVED)
    assert len(solved) > 0.5 * ex.hit.sum()
    assert_exact(res, ex, solved)
    assert len(np.unique(ex.tree[solved])) >= 3          # several distinct paths solved
    traced = ans == TRACED
    assert np.array_equal(res.hit[traced], ex.hit[traced])


def test_trapped_rays_are_solved_trapped(trapping_slab):
    """A trapped sample's path answers a ray trapped along it, null as the tracer says."""
    st, tree = trapping_slab
    o, d = down_rays(st, 4000, 5, (0.3, 0.7), 1.5)
    res, ans, ex = answers(st, tree, o, d)
    solved = np.flatnonzero(ans == SOLVED)
    assert ex.null.sum() > 100 and res.null[solved].sum() > 0.5 * ex.null.sum()
    assert_exact(res, ex, solved)


def test_solving_off_traces(slab):
    """QueryOptions(solve_paths=False) traces the same rays instead."""
    st, tree = slab
    o, d = down_rays(st, 1000, 3)
    _, ans, _, _ = TreeQuery(tree, st, replace(REFUSE_ALL, solve_paths=False))(o, d)
    _, ans_on, _ = answers(st, tree, o, d)
    assert not np.any(ans == SOLVED)
    assert np.array_equal(ans == TRACED, (ans_on == TRACED) | (ans_on == SOLVED))


def test_a_ray_is_solved_only_along_its_samples_recorded_path(slab):
    """The solved chain must reproduce the sample's ray-tree hash: with every sample's hash
    altered (as if their paths differed in a patch or an event kind), nothing is solved."""
    st, tree = slab
    o, d = down_rays(st, 1000, 4, (0.3, 0.7), 1.5)
    _, ans, _ = answers(st, tree, o, d)
    assert np.any(ans == SOLVED)
    saved = tree.table.tree.copy()
    try:
        tree.table.tree ^= np.uint32(1)
        _, ans, _ = answers(st, tree, o, d)
    finally:
        tree.table.tree[:] = saved
    assert not np.any(ans == SOLVED)


def test_the_first_stretch_is_checked_unless_the_full_search_found_the_hit(blocked):
    """A ray down through the strip to the floor crosses the object before its floor hit; that
    first stretch is not looked at where the full first-hit search found the hit (it would
    have been the strip's), and is otherwise."""
    st, tree = blocked
    q = TreeQuery(tree, st, REFUSE_ALL)
    o, d = P(0.2, 0.0, 2.0)[None], P(0.0, 0.0, -1.0)[None]
    pts, nrms = P(0.2, 0.0, 0.0)[None, None], P(0.0, 0.0, 1.0)[None, None]
    dirs, n_ev = P(0.0, 0.0, 1.0)[None, None], np.array([1])
    assert paths._crossed(q, o, d, pts, nrms, dirs, n_ev, np.array([False]))[0]
    assert not paths._crossed(q, o, d, pts, nrms, dirs, n_ev, np.array([True]))[0]
    # the second stretch (floor -> up through the strip) is checked either way
    two = np.array([[[0.2, 0.0, 0.0], [0.2, 0.0, 1.0]]])
    assert paths._crossed(q, o, d, two, np.repeat(nrms, 2, axis=1), np.repeat(dirs, 2, axis=1),
                          np.array([2]), np.array([True]))[0]


def test_rays_with_too_few_usable_samples_are_solved(trapping_slab):
    """Without a tolerance, a ray among null (trapped) samples has too few usable ones to
    blend: it is solved along a sample's path (a null one included) instead of traced."""
    st, tree = trapping_slab
    o, d = down_rays(st, 4000, 7, (0.3, 0.7), 1.5)
    opts = QueryOptions(max_error_deg=None, fallback_angle_deg=None)
    res, ans, why, _ = TreeQuery(tree, st, opts)(o, d)
    _, ans_off, why_off, _ = TreeQuery(tree, st, replace(opts, solve_paths=False))(o, d)
    ex = st.object_function(o, d)
    usable = why_off == paths.WHY_USABLE
    solved = np.flatnonzero(ans == SOLVED)
    assert usable.sum() > 50 and np.all(usable[solved])
    assert len(solved) > 0.5 * usable.sum()
    assert_exact(res, ex, solved)


def test_seeds_blend_the_same_path_samples_except_across_a_seam():
    """Each event's seed is the weighted blend of the parameters of the ray's samples on the
    candidate path (same ray-tree hash, of the ray's class); where those lie far apart (a closed
    patch's seam between them) it is the candidate sample's own; other paths never count."""
    from types import SimpleNamespace
    from riray.ritree.answers import COL
    from riray.trace.objectfn import RECORDED_EVENTS
    n_s = 4
    vals = np.zeros((n_s, COL.N), np.float32)
    vals[:, COL.UV] = [[0.40, 0.5], [0.44, 0.5], [0.99, 0.5], [0.60, 0.5]]
    ev_uv = np.zeros((n_s, RECORDED_EVENTS, 2), np.float32)
    ev_uv[:, 0] = [[0.20, 0.1], [0.24, 0.1], [0.70, 0.1], [0.30, 0.1]]
    ev_uv[:, 1] = [[0.02, 0.3], [0.98, 0.3], [0.50, 0.3], [0.50, 0.3]]     # across a seam
    tab = SimpleNamespace(vals=vals, ev_uv=ev_uv, tree=np.array([7, 7, 9, 7], np.uint32))
    ids = np.array([[0, 1, 2, 3]])
    w = np.array([[0.5, 0.3, 0.2, -1.0]])           # sample 3: another class
    seeds = paths.seed_uvs(tab, ids, w, np.array([0]))
    # samples 0 and 1 (weights 0.5, 0.3) blend; 2 (another path) and 3 do not count
    assert np.allclose(seeds[0, 0], [(0.5 * 0.40 + 0.3 * 0.44) / 0.8, 0.5], atol=1e-6)
    assert np.allclose(seeds[0, 1], [(0.5 * 0.20 + 0.3 * 0.24) / 0.8, 0.1], atol=1e-6)
    assert np.allclose(seeds[0, 2], [0.02, 0.3], atol=1e-6)       # the seam: sample 0's own


def _refused_with_known_hits(st, q, o, d):
    """A query batch of rays ``o``, ``d`` all refused as unsampled, their exact first hits
    found (as the query's full search leaves them)."""
    from riray.ritree.query.batch import Batch
    b = Batch.of(o, d, np.full(len(o), np.inf))
    b.trace(np.arange(len(o)), paths.WHY_UNSAMPLED)
    b.known.add(np.arange(len(o)), st.tracer.intersect(o, d))
    return b


def test_mirror_rays_whose_reflection_leaves_are_answered_by_it(blocked):
    """A mirror ray still refused with a known first hit is answered by its one reflection
    where that leaves the object, exactly as traced; a ray reflected into the wall or the
    strip is left to the tracer."""
    st, tree = blocked
    q = TreeQuery(tree, st, REFUSE_ALL)
    o, d = down_rays(st, 2000, 8, (0.1, 0.9), 1.5)
    ex = st.object_function(o, d)
    b = _refused_with_known_hits(st, q, o, d)
    paths.one_reflection(q, b)
    solved = np.flatnonzero(b.ans == SOLVED)
    assert len(solved) > 0.3 * ex.hit.sum()
    assert_exact(b.res, ex, solved)
    assert np.all(ex.events[solved] == 1)
    many = np.flatnonzero(ex.hit & (ex.events > 1))
    assert len(many) > 50 and not np.any(b.ans[many] == SOLVED)


def test_a_reflection_meeting_a_crease_next_to_its_start_is_traced(corner):
    """The proxy does not look at the stretch next to a segment's start; a ray reflected off
    the floor right beside the wall meets the wall inside that stretch: the exact tracer looks
    there, and the ray (two reflections) is not answered by one."""
    st, tree = corner
    q = TreeQuery(tree, st, REFUSE_ALL)
    sine = 0.25                                         # the reflected ray's angle with the floor
    out = P(np.sqrt(1 - sine ** 2), 0.0, sine)
    t0 = q.proxy.end_stretch(out[None], P(0, 0, 1)[None])[0]
    gap = 0.5 * t0 * out[0]                             # the wall at half the untested stretch
    assert 0.5 * t0 > 1e-7 * st.tracer.diag             # a new event, not the start point
    hit = P(1.0 - gap, 0.0, 0.0)
    d = unit(P(out[0], 0.0, -sine))[None]
    o = hit[None] - 0.5 * d
    ex = st.object_function(o, d)
    assert ex.events[0] == 2
    b = _refused_with_known_hits(st, q, o, d)
    paths.one_reflection(q, b)
    assert b.ans[0] == TRACED
