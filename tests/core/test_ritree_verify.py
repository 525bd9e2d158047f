"""The bake's measured errors: per direction node and per viewpoint cell, against
independent truths.

- A planar mirror: reflection is linear in the direction and independent of the ray's origin,
  so every interpolation the renderer does of its output directions is exact (perspective-
  weighted blend of cube points): every error the bake measures is at the storage precision.
- The glass sphere (sample scene, close camera): a leaf's recorded error equals the error of
  its midpoint ray recomputed here (exact trace from the leaf's viewpoint against a plain
  bilinear blend of its four stored corner samples); the flags say what the corners hold; a
  cell's recorded viewpoint-level error bounds the renderer's error on the camera ray through
  its centre (computed here from the camera); error-driven viewpoint splitting leaves no
  failing cell above the maximum viewpoint depth and lowers the error of the cameras' rays.
- An old-layout file is refused with "re-bake".

Trees are tiny (viewpoint depth <= 3, direction depth <= 4), images 48 x 48, one worker.
"""

import json

import numpy as np
import pytest

from riray.geometry.primitives import bilinear
from riray.scene.camera import camera_rays, pixel_rays, project_points
from riray.trace.scene_tracer import SceneTracer
from riray.ritree import cache
from riray.ritree import tree as ritree
from riray.ritree.bake import bake
from riray.ritree.dircube import CUBE, N_SLOTS, cube_to_dir
from riray.ritree.interp import angle_between
from riray.ritree.query import EXTRAPOLATED_S, FULL, WHY_TOLERANCE, QueryOptions, TreeQuery
from riray.ritree.region import region_for_cameras
from riray.ritree.tree import BOUNDARY, UNVERIFIED, BakeParams
from riray.scene.io import look_at_matrix
from riray.scene.model import (Camera, ObjectMaterial, Patch, RenderSettings, Scene,
                               SpecularObject)
from riray.scene.samples import build


def paper(**kw) -> QueryOptions:
    """The paper's rules (no baked-error tolerance, mirror rays blended), refused rays traced
    (not solved along a path), with options ``kw``."""
    return QueryOptions(**{"max_error_deg": None, "mirror_rays": "interpolate",
                           "solve_paths": False, **kw})


pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

SIZE = 48
# Storage precision of a blended output direction: octahedral codes (6.5e-5 rad each, a convex
# blend keeps the bound) plus float32 blending, in degrees, with a margin.
STORED_DEG = 0.02
NO_THRESHOLDS = paper(angle_deg=None)


def leaves_in_rect(tree):
    return np.flatnonzero((tree.dir_forest.child < 0) & tree.leaf_ok)


def vp_cells(tree):
    f = tree.vp_forest
    return np.flatnonzero((f.child < 0) & np.all(f.corner >= 0, axis=1))


@pytest.fixture(scope="module")
def mirror():
    obj = SpecularObject("mirror", [Patch("m", 0, surface=bilinear(
        np.array([-1.0, -1, 0]), np.array([1.0, -1, 0]), np.array([-1.0, 1, 0]),
        np.array([1.0, 1, 0])))], ObjectMaterial(kind="mirror"))
    cam = Camera("cam", look_at_matrix((0.4, -2.5, 2.2), (0.0, 0.0, 0.0)), lens=30.0)
    scene = Scene(objects=[obj], cameras=[cam], render=RenderSettings(width=SIZE, height=SIZE))
    st = SceneTracer(scene)
    params = BakeParams(viewpoint_depth=2, direction_depth=3, viewpoint_refine=1, pad=0.2)
    return st, bake(st, params, region_for_cameras(st, params, [cam], SIZE, SIZE), workers=1)


def sphere_bake(viewpoint_tolerance_deg):
    scene = build("glass_sphere")
    st = SceneTracer(scene)
    params = BakeParams(viewpoint_depth=3, direction_depth=4, viewpoint_refine=1,
                        viewpoint_tolerance_deg=viewpoint_tolerance_deg)
    cam = scene.camera("close")
    return st, cam, bake(st, params, region_for_cameras(st, params, [cam], SIZE, SIZE), workers=1)


@pytest.fixture(scope="module")
def sphere():
    return sphere_bake(0.3)


@pytest.fixture(scope="module")
def sphere_loose():
    return sphere_bake(1e9)          # viewpoint cells split only where rays lack interpolants


def test_mirror_errors_are_at_storage_precision(mirror):
    _, tree = mirror
    leaves = leaves_in_rect(tree)
    e = tree.dir_err[leaves]
    assert np.isfinite(e).sum() > 50
    assert np.nanmax(e) < STORED_DEG
    cells = vp_cells(tree)
    ev = tree.vp_err[cells]
    assert np.isfinite(ev).sum() >= 4
    assert np.nanmax(ev) < STORED_DEG


def test_leaf_error_is_its_midpoint_error(sphere):
    """Recorded leaf errors recomputed: the exact ray from the leaf's viewpoint through the
    leaf's centre direction against the bilinear blend of the four stored corner samples
    (output directions weighted by |(1, u, v)|), for leaves whose corners and midpoint share
    one class and none is null."""
    st, _, tree = sphere
    f = tree.dir_forest
    leaves = leaves_in_rect(tree)
    tr = f.tree_of_nodes()[leaves]
    vp, slot = tr // N_SLOTS, tr % N_SLOTS
    dom = f.domain[tr]
    size = np.exp2(-f.level[leaves].astype(float))
    u = dom[:, 0] + (dom[:, 1] - dom[:, 0]) * (f.ix[leaves] + 0.5) * size
    v = dom[:, 2] + (dom[:, 3] - dom[:, 2]) * (f.iy[leaves] + 0.5) * size
    d = cube_to_dir(CUBE[tree.vp_face[vp], slot], u, v)
    ex = st.object_function(tree.vp_pos[vp], d)
    ids = f.corner[leaves]
    s = tree.samples
    ok = ex.hit & ~ex.null & np.all(tree.sample_class(ids) == ex.cls[:, None], axis=1) \
        & ~np.any(np.asarray(s.null)[ids], axis=1)
    assert ok.sum() > 100
    span_u, span_v = (dom[:, 1] - dom[:, 0])[:, None], (dom[:, 3] - dom[:, 2])[:, None]
    uc = dom[:, 0, None] + span_u * (f.ix[leaves][:, None] + [0, 1, 0, 1]) * size[:, None]
    vc = dom[:, 2, None] + span_v * (f.iy[leaves][:, None] + [0, 0, 1, 1]) * size[:, None]
    scale = np.sqrt(1 + uc ** 2 + vc ** 2)
    od = (s.out_d[ids] * scale[..., None]).sum(axis=1)
    od /= np.linalg.norm(od, axis=1, keepdims=True)
    want = np.degrees(angle_between(od[ok], ex.out_dir[ok]))
    got = tree.dir_err[leaves][ok]
    assert np.all(np.abs(got - want) < STORED_DEG), np.abs(got - want).max()
    assert want.max() > 10 * STORED_DEG        # the comparison sees real errors


def test_leaf_flags(sphere):
    _, _, tree = sphere
    f = tree.dir_forest
    M = tree.params.direction_depth
    tol = tree.params.tolerance_deg
    leaves = leaves_in_rect(tree)
    lv, e, fl = f.level[leaves], tree.dir_err[leaves], tree.dir_flags[leaves]
    # a shallower leaf stopped because it passed its test; only the maximum depth fails
    assert np.all(lv[(fl & UNVERIFIED) > 0] == M)
    assert np.all(e[lv < M] <= tol)
    unv = (fl & UNVERIFIED) > 0
    assert np.all(unv[(lv == M) & (e > tol)]) and np.sum((lv == M) & (e > tol)) > 10
    # corners that both hit and miss the object: a boundary leaf
    hit = np.asarray(tree.samples.patch)[f.corner[leaves]] >= 0
    mixed = hit.any(axis=1) & ~hit.all(axis=1)
    assert mixed.sum() > 10 and np.all(fl[mixed] & BOUNDARY)


def test_cell_error_bounds_the_centre_camera_ray(sphere):
    st, cam, tree = sphere
    f = tree.vp_forest
    cells = vp_cells(tree)
    cells = cells[np.isfinite(tree.vp_err[cells])]
    face = f.tree_of_nodes()[cells]
    axis = face // 2
    size = np.exp2(-f.level[cells].astype(float))
    p = np.zeros((len(cells), 3))
    rows = np.arange(len(cells))
    p[rows, axis] = np.where(face % 2 == 1, tree.box_hi[axis], tree.box_lo[axis])
    for k, idx in ((0, f.ix), (1, f.iy)):
        ax = np.array([[1, 2], [0, 2], [0, 1]])[axis, k]       # the face's (u, v) world axes
        lo, hi = tree.box_lo[ax], tree.box_hi[ax]
        p[rows, ax] = lo + (hi - lo) * (idx[cells] + 0.5) * size
    px, py, depth = project_points(cam, SIZE, SIZE, p)
    seen = (depth > 0) & (px >= 0) & (px <= SIZE) & (py >= 0) & (py <= SIZE)
    o, d = pixel_rays(cam, SIZE, SIZE, px[seen], py[seen])
    tmax = st.env.hit_distance(o, d)
    ex = st.object_function(o, d, tmax)
    res, ans, _, _ = TreeQuery(tree, st, NO_THRESHOLDS)(o, d, tmax)
    interp = (ans >= FULL) & (ans <= EXTRAPOLATED_S) & ex.hit & ~ex.null
    err = np.degrees(angle_between(res.out_dir[interp], ex.out_dir[interp]))
    bound = tree.vp_err[cells[seen]][interp]
    assert interp.sum() > 30
    assert np.all(err <= bound + STORED_DEG)
    assert err.max() > 10 * STORED_DEG


def test_error_driven_viewpoint_split(sphere, sphere_loose):
    st, cam, tight = sphere
    _, _, loose = sphere_loose
    dmax = tight.params.viewpoint_depth + tight.params.viewpoint_refine
    cells = vp_cells(tight)
    fail = tight.vp_err[cells] > tight.params.viewpoint_tolerance_deg
    assert fail.any()
    assert np.all(tight.vp_forest.level[cells[fail]] == dmax)      # split as far as allowed
    assert np.all(tight.vp_flags[cells[fail]] & UNVERIFIED)
    assert tight.meta["viewpoints"] > loose.meta["viewpoints"]
    o, d = camera_rays(cam, SIZE, SIZE)
    tmax = st.env.hit_distance(o, d)
    ex = st.object_function(o, d, tmax)
    mean = []
    for tree in (tight, loose):
        res, ans, _, _ = TreeQuery(tree, st, NO_THRESHOLDS)(o, d, tmax)
        ok = (ans >= FULL) & (ans <= EXTRAPOLATED_S) & ex.hit & ~ex.null
        mean.append(np.degrees(angle_between(res.out_dir[ok], ex.out_dir[ok])).mean())
    assert mean[0] < mean[1]


def test_old_layout_is_refused(tmp_path, sphere):
    _, _, tree = sphere
    path = tmp_path / "old.rit"
    arrays = {k: v for k, v in tree.arrays().items()
              if k not in ("dir_err", "dir_flags", "vp_err", "vp_flags")}
    cache.save_tree(path, json.loads(json.dumps({**tree.header(), "layout": 1})), arrays)
    with pytest.raises(cache.TreeCacheError, match="layout 1 is not supported.*re-bake"):
        ritree.load(path)
    # the current layout without the measurements is refused too
    cache.save_tree(path, json.loads(json.dumps(tree.header())), arrays)
    with pytest.raises(cache.TreeCacheError, match="dir_err.*missing.*re-bake"):
        ritree.load(path)


def test_tolerance_tightens_monotonically(sphere):
    """--max-error: each tighter tolerance interpolates a subset of the rays of the looser one,
    with the same answers, so the exact error of the interpolated rays (max and mean) never
    grows and the rays it traces (tolerance) never shrink."""
    st, cam, tree = sphere
    o, d = camera_rays(cam, SIZE, SIZE)
    tmax = st.env.hit_distance(o, d)
    ex = st.object_function(o, d, tmax)
    prev = None
    for tol in (None, 8.0, 4.0, 2.0, 1.0, 0.5, 0.25):
        res, ans, why, _ = TreeQuery(tree, st, QueryOptions(
            angle_deg=None, max_error_deg=tol, solve_paths=False))(o, d, tmax)
        interp = (ans >= FULL) & (ans <= EXTRAPOLATED_S)
        ok = interp & ex.hit & ~ex.null
        err = np.degrees(angle_between(res.out_dir[ok], ex.out_dir[ok]))
        cur = dict(interp=interp, out=res.out_dir, max=err.max(), mean=err.mean(),
                   traced=np.sum(why == WHY_TOLERANCE))
        if prev is not None:
            assert not np.any(interp & ~prev["interp"])
            assert np.array_equal(cur["out"][interp], prev["out"][interp])
            assert cur["max"] <= prev["max"] and cur["mean"] <= prev["mean"]
            assert cur["traced"] >= prev["traced"]
        prev = cur
    first = TreeQuery(tree, st, NO_THRESHOLDS)(o, d, tmax)[1]
    assert prev["traced"] > 0.5 * np.sum((first >= FULL) & (first <= EXTRAPOLATED_S))


def test_refinement_does_not_follow_the_render_time_default(sphere_loose, monkeypatch):
    """A refinement pass splits the cells whose camera rays the paper's rule (20-degree angle
    threshold, bake.refine_rule) traces; changing QueryOptions' defaults (the render-time
    default, here to a 90-degree threshold) leaves the baked tree as it was."""
    import dataclasses
    from riray.ritree import query
    _, _, tree = sphere_loose
    fields = [f.name for f in dataclasses.fields(query.QueryOptions)]
    defaults = list(query.QueryOptions.__init__.__defaults__)
    defaults[fields.index("angle_deg")] = 90.0
    defaults[fields.index("max_error_deg")] = None
    monkeypatch.setattr(query.QueryOptions.__init__, "__defaults__", tuple(defaults))
    assert query.QueryOptions().angle_deg == 90.0
    _, _, again = sphere_bake(1e9)
    assert len(again.vp_forest.child) == len(tree.vp_forest.child)
    assert len(again.samples) == len(tree.samples)
    assert np.array_equal(again.vp_forest.corner, tree.vp_forest.corner)


def test_viewpoint_errors_do_not_follow_the_render_time_mirror_rule(mirror, monkeypatch):
    """The bake measures its viewpoint cells with one mirror rule (verify's pinned
    MEASURE_MIRROR_RAYS, recorded in the tree's meta), whatever QueryOptions' default is: a
    tree's stored errors do not depend on the defaults of the code that baked it."""
    import dataclasses
    from riray.ritree import query, verify
    st, tree = mirror
    assert tree.meta["viewpoint_mirror_rays"] == verify.MEASURE_MIRROR_RAYS == "reflect"
    cams = [(st.scene.cameras[0], SIZE, SIZE)]
    err, flags = verify.viewpoint_errors(tree, st, cams)
    fields = [f.name for f in dataclasses.fields(query.QueryOptions)]
    defaults = list(query.QueryOptions.__init__.__defaults__)
    defaults[fields.index("mirror_rays")] = "interpolate"
    monkeypatch.setattr(query.QueryOptions.__init__, "__defaults__", tuple(defaults))
    again, flags2 = verify.viewpoint_errors(tree, st, cams)
    assert np.isfinite(err).sum() >= 4
    assert np.array_equal(err, again, equal_nan=True) and np.array_equal(flags, flags2)
    # and the two rules do measure differently here (so the check above can fail)
    other = TreeQuery(tree, st, paper(angle_deg=None,
                                      mirror_rays="interpolate"))
    mine = TreeQuery(tree, st, paper(angle_deg=None, mirror_rays=verify.MEASURE_MIRROR_RAYS))
    o, d, _ = verify.test_rays(tree, vp_cells(tree), cams)
    assert not np.array_equal(other(o, d)[0].out_dir, mine(o, d)[0].out_dir)


def finest_bake(k, spy=None):
    """The glass sphere's close view baked with ``finest_min_traced`` k (viewpoint depth 2 +
    2 refinement levels); ``spy(baker, cells)`` sees each finest-level pass's choice."""
    from riray.ritree import bake as bake_mod
    scene = build("glass_sphere")
    st = SceneTracer(scene)
    params = BakeParams(viewpoint_depth=2, direction_depth=3, viewpoint_refine=2,
                        finest_min_traced=k)
    cam = scene.camera("close")
    region = region_for_cameras(st, params, [cam], SIZE, SIZE)
    orig = bake_mod.Baker._traced_cells

    def traced_cells(self, tree, o, d, tmax):
        cells = orig(self, tree, o, d, tmax)
        if spy is not None:
            spy(self, st, (o, d, tmax), cells)
        return cells
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(bake_mod.Baker, "_traced_cells", traced_cells)
        return bake(st, params, region, workers=1)


def test_viewpoint_errors_do_not_follow_the_render_time_null_rule(monkeypatch):
    """Likewise for null rays (verify's pinned MEASURE_NULL_INTERP): on a glass sphere that
    traps every ray (max_events 1) the cells' errors stay the same when QueryOptions'
    default answers null rays, and that rule would measure them (0 deg) where the pinned one
    traces the test rays and measures nothing."""
    import dataclasses
    from riray.ritree import query, verify
    scene = build("glass_sphere")
    scene.render.max_events = 1
    st = SceneTracer(scene)
    params = BakeParams(viewpoint_depth=2, direction_depth=3, viewpoint_refine=0)
    cam = scene.camera("close")
    tree = bake(st, params, region_for_cameras(st, params, [cam], SIZE, SIZE), workers=1)
    cams = [(cam, SIZE, SIZE)]
    err, flags = verify.viewpoint_errors(tree, st, cams)
    fields = [f.name for f in dataclasses.fields(query.QueryOptions)]
    defaults = list(query.QueryOptions.__init__.__defaults__)
    defaults[fields.index("null_interp")] = True
    monkeypatch.setattr(query.QueryOptions.__init__, "__defaults__", tuple(defaults))
    again, flags2 = verify.viewpoint_errors(tree, st, cams)
    assert np.array_equal(err, again, equal_nan=True) and np.array_equal(flags, flags2)
    monkeypatch.setattr(verify, "MEASURE_NULL_INTERP", True)
    other, _ = verify.viewpoint_errors(tree, st, cams)
    assert np.sum(other == 0) > np.sum(err == 0)


def test_finest_level_goes_where_rays_are_traced():
    """With finest_min_traced k, the pass that makes the finest viewpoint level splits exactly
    the cells through which at least k of the camera's rays are traced at the 2-degree
    tolerance: counted here from the rays' box entry points (not the query's locator); with k
    too large for any cell, no cell reaches the finest level; with k = 0 the finest level is
    made by the other levels' rule."""
    from riray.ritree.bake import finest_rule
    from riray.ritree.locate import entry_points
    from riray.ritree.query import TRACED
    seen = []

    def spy(baker, st, rays, cells):
        o, d, tmax = rays
        tree = baker.tree()
        ans = TreeQuery(tree, st, finest_rule())(o, d, tmax)[1]
        tr = ans == TRACED
        _, face, x, y, _ = entry_points(tree, o[tr], d[tr])
        leaf, _, _ = baker.vpf.locate(face, x, y)
        count = np.bincount(leaf[leaf >= 0], minlength=len(baker.vpf.child))
        seen.append((count, cells))

    probe = finest_bake(1, spy)
    count, cells = seen[0]
    positive = np.sort(count[count > 0])
    assert len(positive) >= 4
    k = int(positive[len(positive) // 2])               # a count some cell has exactly
    seen.clear()
    tree = finest_bake(k, spy)
    count, cells = seen[0]
    assert np.array_equal(cells, np.flatnonzero(count >= k)) and np.any(count == k)
    assert 0 < len(cells) < np.sum(count > 0)
    finest = tree.vp_forest.level.max()
    assert finest == 4 and probe.vp_forest.level.max() == 4
    assert finest_bake(0).vp_forest.level.max() == 4
    assert finest_bake(1 << 30).vp_forest.level.max() == 3


def test_finest_pass_over_several_levels_leaves_no_ray_outside():
    """The finest pass may split cells of several levels at once (a coarse cell the earlier
    passes left alone can still hold traced rays): each new viewpoint gets the direction
    rectangles that the rays through cells of its own level need, so every camera ray of the
    region is located in the tree, none answered outside it. (Before, the finest level's
    narrow rectangles went to every new viewpoint: 9 of these 863 rays were outside.)"""
    from riray.ritree import bake as bake_mod
    from riray.ritree.locate import locate
    scene = build("teapot")
    st = SceneTracer(scene)
    params = BakeParams(viewpoint_depth=2, direction_depth=3, viewpoint_refine=3,
                        viewpoint_tolerance_deg=45.0, finest_min_traced=1)
    region = region_for_cameras(st, params, [scene.camera("close")], 40, 40)
    split_levels = []
    orig = bake_mod.Baker._traced_cells

    def traced_cells(self, tree, o, d, tmax):
        cells = orig(self, tree, o, d, tmax)
        split_levels.extend(np.unique(self.vpf.level[cells]))
        return cells
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(bake_mod.Baker, "_traced_cells", traced_cells)
        tree = bake(st, params, region, workers=1)
    assert len(split_levels) >= 3                      # cells of three levels split at once
    o, d, tmax = region.rays
    loc, outside = locate(tree, o, d, tmax)
    assert len(outside) == 0 and len(loc) == len(o) > 800
