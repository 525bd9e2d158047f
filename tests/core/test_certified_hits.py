"""Exact first hits certified without the full search (ritree/query/certify.py), against the
tracer's full search: a Newton root is a ray's first hit only where the occlusion proxy finds
nothing in front of it, and a ray without a root misses only where the proxy finds nothing
at all; every other ray gets the full search."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from riray.geometry.primitives import sphere
from riray.ritree.bake import bake
from riray.ritree.locate import locate
from riray.ritree.query import QueryOptions, TreeQuery
from riray.ritree.query.batch import Batch
from riray.ritree.query import certify
from riray.ritree.query.certify import first_hits
from riray.ritree.tree import BakeParams
from riray.scene.model import ObjectMaterial, Patch, SpecularObject

# the path solver's test helpers (--import-mode=importlib: tests/core is not on sys.path)
_spec = importlib.util.spec_from_file_location(
    "riray_tests_path_solve", Path(__file__).with_name("test_path_solve.py"))
_ps = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_ps)
P, down_rays, scene_of, top_cells = _ps.P, _ps.down_rays, _ps.scene_of, _ps.top_cells

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

# Newton stops within 1e-9 of the diagonal: a certified hit is the full search's to far below.
POS_TOL = 1e-6


# A mirror floor (class 0) and wall (class 1) with a floating mirror strip (class 2): rays
# down through the strip's span meet it before the floor (the path solver's scene).
blocked = _ps.blocked


@pytest.fixture(scope="module")
def ball():
    st = scene_of(SpecularObject("ball", [Patch("s", 0, surface=sphere((0, 0, 0), 0.15))],
                                 ObjectMaterial(kind="glass", ior=1.5)))
    return st, bake(st, BakeParams(viewpoint_depth=3, direction_depth=4),
                    region=top_cells(3, 0.0, 0.25), workers=1)


def certified(st, tree, o, d, classes):
    """(first hits of rays o, d given candidate ``classes`` (n, K) for each, the number
    certified); every ray must be located in the tree."""
    q = TreeQuery(tree, st)
    b = Batch.of(o, d, np.full(len(o), np.inf))
    loc, outside = locate(tree, o, d, b.tmax)
    assert len(loc) == len(o) and len(outside) == 0
    order = np.argsort(loc.ray)
    hit = first_hits(q, b, loc.ray[order], loc.take(order), classes)
    return hit, b.certified_first_hits


def assert_full_search(st, hit, o, d):
    """``hit`` is the full search's first hit of every ray."""
    full = st.tracer.intersect(o, d)
    assert np.array_equal(hit.hit, full.hit)
    assert np.array_equal(hit.patch, full.patch)
    assert np.abs(hit.point - full.point).max(initial=0) < POS_TOL


def test_a_root_behind_something_nearer_is_not_certified(blocked):
    """Rays straight down under the strip, given only the floor's class: Newton finds the
    floor, the proxy finds the strip in front, so the full search answers (the strip); rays
    beside the strip are certified on the floor."""
    st, tree = blocked
    x = np.linspace(-0.4, 0.45, 35)
    o = np.c_[x, np.zeros_like(x), np.full_like(x, 1.5)]
    d = np.tile(P(0.0, 0.0, -1.0), (len(x), 1))
    hit, n_cert = certified(st, tree, o, d, np.zeros((len(x), 1), np.int64))
    assert_full_search(st, hit, o, d)
    under = (x > 0.1) & (x < 0.3)
    assert np.all(hit.patch[under] == 2) and np.all(hit.patch[~under] == 0)
    assert 0 < n_cert <= np.sum(~under)


def test_no_root_is_a_miss_only_where_the_proxy_sees_nothing(ball):
    """Rays down through the sphere's box, given no candidate class: none has a Newton root,
    so those meeting the proxy are searched (they hit) and the rest are certified misses."""
    st, tree = ball
    o, d = down_rays(st, 400, 3, (0.02, 0.23), 0.1)
    hit, n_cert = certified(st, tree, o, d, np.full((len(o), 2), -1, np.int64))
    assert_full_search(st, hit, o, d)
    assert 50 < hit.hit.sum() < len(o) - 50
    assert 0.9 * np.sum(~hit.hit) < n_cert <= np.sum(~hit.hit)


def test_grazing_roots_get_the_full_search(ball, monkeypatch):
    """A root where the ray meets the surface at a grazing angle (its untested end stretch
    would be long) is not certified; steep ones are. The roots here are the full search's own
    hits, so only the angle can refuse them."""
    st, tree = ball
    monkeypatch.setattr(certify, "_nearest_roots",
                        lambda q, o, d, tmax, loc, classes: st.tracer.intersect(o, d, tmax=tmax))
    r, y = 0.15, -0.08                      # inside the baked corner of the box's top
    sine = np.array([0.01, 0.02, 0.4, 0.6])
    # a ray down at distance rho from the axis meets the sphere at sine sqrt(1 - (rho/r)^2)
    x = -np.sqrt(r ** 2 * (1.0 - sine ** 2) - y ** 2)
    o = np.c_[x, np.full_like(x, y), np.full_like(x, 0.4)]
    d = np.tile(P(0.0, 0.0, -1.0), (len(x), 1))
    hit, n_cert = certified(st, tree, o, d, np.zeros((len(x), 1), np.int64))
    assert_full_search(st, hit, o, d)
    assert hit.hit.all() and n_cert == 2


def test_queries_answer_the_same_with_and_without_certified_hits(blocked):
    """Through the whole query (classes, tolerance misses), certification changes no answer and
    replaces many full searches."""
    st, tree = blocked
    o, d = down_rays(st, 3000, 5, (0.1, 0.9), 1.2)
    res, ans, _, stats = TreeQuery(tree, st)(o, d)
    off, ans_off, _, stats_off = TreeQuery(tree, st, QueryOptions(certify_first_hits=False))(o, d)
    assert stats["exact_first_hits"] > 100 and stats_off["certified_first_hits"] == 0
    assert stats["certified_first_hits"] > 0.3 * stats["exact_first_hits"]
    assert np.array_equal(ans, ans_off)
    assert np.array_equal(res.patch, off.patch)
    assert np.abs(res.out_dir - off.out_dir).max() < 1e-9
    assert np.all(np.isfinite(res.out_dir)) and np.all(np.isfinite(res.point))
