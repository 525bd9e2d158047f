"""Rays solved along a sample's path on smooth glass meshes (ritree/query/meshpaths.py: each
event walked from the triangle the sample met), against the exact tracer: every located ray
that hits is refused by the tolerance (no viewpoint cell measured, as in test_path_solve.py),
so each is solved or traced, and what is solved must be what the tracer answers."""

from dataclasses import replace

import numpy as np
import pytest

from riray.ritree.bake import bake
from riray.ritree.answers import is_interpolated
from riray.ritree.query import SOLVED, TRACED, QueryOptions, TreeQuery
from riray.ritree.region import Region
from riray.ritree.tree import BakeParams
from riray.scene.model import ObjectMaterial, Patch, RenderSettings, Scene, SpecularObject
from riray.trace.scene_tracer import SceneTracer

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

REFUSE_ALL = QueryOptions(max_error_deg=0.0, fallback_angle_deg=None)
TOL = 1e-9          # a walked hit is Moller-Trumbore's, as the tracer's: rounding apart


def smooth_sphere(n_lat, n_lon, cap_rows=0):
    """A unit UV sphere mesh with its true normals at the corners; ``cap_rows`` rows of
    triangles around the top pole left out (an open bowl)."""
    th = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    ring = np.stack([np.sin(th)[:, None] * np.cos(ph), np.sin(th)[:, None] * np.sin(ph),
                     np.cos(th)[:, None] * np.ones_like(ph)], axis=-1).reshape(-1, 3)
    verts = np.vstack([[0, 0, 1], ring, [0, 0, -1]])
    idx = lambda i, j: 1 + i * n_lon + j % n_lon
    rows = [[[0, idx(0, j), idx(0, j + 1)] for j in range(n_lon)]]
    for i in range(n_lat - 2):
        rows.append([t for j in range(n_lon) for t in
                     ([idx(i, j), idx(i + 1, j), idx(i, j + 1)],
                      [idx(i, j + 1), idx(i + 1, j), idx(i + 1, j + 1)])])
    rows.append([[len(verts) - 1, idx(n_lat - 2, j + 1), idx(n_lat - 2, j)]
                 for j in range(n_lon)])
    tris = np.array([t for r in rows[cap_rows:] for t in r], np.int64)
    return verts, tris, verts[tris]


def glass_mesh(cap_rows, kind="glass"):
    verts, tris, nrm = smooth_sphere(16, 32, cap_rows)
    obj = SpecularObject("m", [Patch("m", 0, vertices=verts, triangles=tris, normals=nrm)],
                         ObjectMaterial(kind=kind, ior=1.5))
    st = SceneTracer(Scene(objects=[obj], render=RenderSettings(max_events=8)))
    cells = np.zeros((6, 8, 8), bool)
    cells[5, 2:6, 2:6] = True                       # the middle of the box's top face
    region = Region(cells=cells)
    region.describe = lambda: {"kind": "cells", "cells": int(cells.sum())}
    return st, bake(st, BakeParams(viewpoint_depth=3, direction_depth=4), region=region,
                    workers=1)


@pytest.fixture(scope="module")
def closed():
    return glass_mesh(0)


@pytest.fixture(scope="module")
def bowl():
    return glass_mesh(3)


def down_rays(st, n, seed):
    """Rays entering the middle of the top of the object's box, going down at up to ~30 deg."""
    rng = np.random.default_rng(seed)
    lo, hi = st.box_lo, st.box_hi
    f = rng.uniform(0.3, 0.7, (n, 2))
    q = np.c_[lo[:2] + (hi[:2] - lo[:2]) * f, np.full(n, hi[2])]
    d = np.c_[rng.uniform(-0.6, 0.6, (n, 2)), -np.ones(n)]
    d /= np.linalg.norm(d, axis=1)[:, None]
    return q - 0.05 * d, d


@pytest.mark.parametrize("name", ["closed", "bowl"])
def test_mesh_rays_are_solved_as_traced(name, request):
    """A closed smooth glass sphere mesh and an open one (its top cap left out: rays meet the
    inside of the bowl's far wall from behind, and the side rule applies): most hits are
    solved, each with the traced answer (events, path, output ray, first hit), the rest
    traced."""
    st, tree = request.getfixturevalue(name)
    o, d = down_rays(st, 3000, 4)
    res, ans, _, stats = TreeQuery(tree, st, REFUSE_ALL)(o, d)
    ex = st.object_function(o, d)
    solved = np.flatnonzero(ans == SOLVED)
    assert stats["solved_along_path"] == len(solved) > 0.5 * ex.hit.sum()
    for f in ("hit", "null", "events", "tree", "patch"):
        assert np.array_equal(getattr(res, f)[solved], getattr(ex, f)[solved]), f
    out = solved[~ex.null[solved]]
    assert np.abs(res.out_dir[out] - ex.out_dir[out]).max() < TOL
    assert np.abs(res.out_origin[out] - ex.out_origin[out]).max() < TOL
    assert np.abs(res.point[solved] - ex.point[solved]).max() < TOL
    if name == "bowl":                           # paths of up to max_events, trapped ones too
        assert len(np.unique(ex.events[solved])) >= 4 and res.null[solved].any()
    traced = ans == TRACED
    assert np.array_equal(res.hit[traced], ex.hit[traced])


def test_solved_dielectric_rays_carry_the_traced_fresnel_tree():
    """A dielectric bowl: a solved ray's output ray keeps the traced share of the light and
    its Fresnel tree's other branches the traced colour (the environment's), as exact
    rendering traces them."""
    st, tree = glass_mesh(3, "dielectric")
    o, d = down_rays(st, 1500, 6)
    res, ans, _, _ = TreeQuery(tree, st, REFUSE_ALL)(o, d)
    ex = st.object_function(o, d, fresnel_tree=True)
    solved = np.flatnonzero(ans == SOLVED)
    assert len(solved) > 0.5 * ex.hit.sum()
    assert np.abs(res.out_weight[solved] - ex.out_weight[solved]).max() < TOL
    assert np.abs(res.branch_color[solved] - ex.branch_color[solved]).max() < TOL
    assert np.any(res.out_weight[solved] < 1.0) and np.any(res.branch_color[solved] > 0)


def test_interpolated_dielectric_rays_are_solved_to_carry_the_fresnel_tree():
    """With the tolerance off the tree interpolates a glass bowl's rays; a dielectric's are
    solved along their samples' paths instead (the same answer as traced, Fresnel tree
    included), where the chain is solved; the rest keep their interpolated answer."""
    opts = QueryOptions(max_error_deg=None, fallback_angle_deg=None)
    st, tree = glass_mesh(3)
    o, d = down_rays(st, 1500, 7)
    _, ans, _, _ = TreeQuery(tree, st, opts)(o, d)
    interp = is_interpolated(ans)
    assert interp.mean() > 0.5
    st, tree = glass_mesh(3, "dielectric")
    _, off, _, _ = TreeQuery(tree, st, replace(opts, fresnel_tree=False))(o, d)
    assert np.array_equal(off, ans)                  # off: the glass's answers
    res, ans, _, _ = TreeQuery(tree, st, opts)(o, d)
    ex = st.object_function(o, d, fresnel_tree=True)
    assert np.mean(ans[interp] == SOLVED) > 0.8
    solved = np.flatnonzero(ans == SOLVED)
    assert np.array_equal(res.tree[solved], ex.tree[solved])
    assert np.abs(res.out_weight[solved] - ex.out_weight[solved]).max() < TOL
    assert np.abs(res.branch_color[solved] - ex.branch_color[solved]).max() < TOL
