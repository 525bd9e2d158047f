"""Walking a ray across a mesh's edges from a known triangle (trace.meshwalk), and the triangle
a path record keeps for a mesh hit (trace.objectfn.tri_params)."""

import importlib.util
from pathlib import Path

import numpy as np

from riray.ritree.codec import decode_params, encode_params
from riray.scene.model import Patch, SpecularObject
from riray.trace.meshwalk import WALK_STEPS, edge_neighbours, mesh_hits
from riray.trace.objectfn import params_tri, tri_params
from riray.trace.patches import PatchTracer

# the smooth-mesh tests' UV sphere (--import-mode=importlib: tests/core is not on sys.path)
_spec = importlib.util.spec_from_file_location(
    "riray_tests_smooth_meshes", Path(__file__).with_name("test_smooth_meshes.py"))
_sm = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_sm)


def uv_sphere(n_lat, n_lon):
    """A closed unit UV sphere: (vertices, triangles, corner normals = the true normals)."""
    verts, tris = _sm.uv_sphere(n_lat, n_lon)
    return verts, tris, verts[tris]


def test_edge_neighbours_of_two_triangles_and_a_fan():
    """Two triangles sharing edge (1, 2): each is the other's across it, the open edges have
    none; an edge of three triangles has none either."""
    nb = edge_neighbours(np.array([[0, 1, 2], [2, 1, 3]]))
    assert nb.tolist() == [[1, -1, -1], [-1, -1, 0]]          # opposite corner 0 / corner 2
    fan = edge_neighbours(np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]]))
    assert np.all(fan[:, 2] == -1)                           # edge (0, 1) of three triangles


def test_walk_finds_the_nearest_hit_from_a_triangle_nearby():
    """On a smooth UV sphere, rays walked from the triangle a neighbouring ray hit find the
    tracer's own closest hit (BVH search): the same triangle, t and shading normal."""
    verts, tris, nrm = uv_sphere(24, 48)
    tr = PatchTracer(SpecularObject("s", [Patch("s", 0, vertices=verts, triangles=tris,
                                                normals=nrm)]))
    rng = np.random.default_rng(5)
    n = 300
    d = -np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])
    o = 3 * -d + rng.uniform(-0.6, 0.6, (n, 3)) * [1, 1, 0]
    o2 = o + rng.normal(0, 0.03, (n, 3)) * [1, 1, 0]     # the neighbour a few triangles off
    dd = np.tile(d, (n, 1))
    seed = tr.intersect(o2, dd)
    exact = tr.intersect(o, dd)
    k = np.flatnonzero(seed.hit & exact.hit)
    got = mesh_hits(tr, o[k], dd[k], seed.tri[k], np.zeros(len(k)), np.full(len(k), np.inf))
    assert got.hit.all() and len(k) > 250
    assert np.array_equal(got.tri, exact.tri[k])
    assert np.abs(got.t - exact.t[k]).max() < 1e-12
    assert np.abs(got.normal - exact.normal[k]).max() < 1e-12
    assert np.all(got.patch == 0)
    assert np.any(seed.tri[k] != exact.tri[k])                # walks that moved


def test_walk_stops_at_an_open_edge_and_after_its_steps():
    """A ray that meets no triangle reachable from its seed gets no hit: off an open sheet's
    edge, or farther than WALK_STEPS triangles away."""
    xs = np.arange(WALK_STEPS + 3, dtype=float)
    verts = np.array([[x, y, 0.0] for x in xs for y in (0.0, 1.0)])
    tris = []
    for i in range(len(xs) - 1):
        a, b, c, e = 2 * i, 2 * i + 2, 2 * i + 1, 2 * i + 3
        tris += [[a, b, c], [c, b, e]]
    tr = PatchTracer(SpecularObject("strip", [Patch("strip", 0, vertices=verts,
                                                    triangles=np.array(tris))]))
    o = np.array([[0.4, 2.5, 1.0], [len(xs) - 1.5, 0.5, 1.0], [3.3, 0.5, 1.0]])
    d = np.tile([0.0, 0.0, -1.0], (3, 1))
    got = mesh_hits(tr, o, d, np.zeros(3, np.int64), np.zeros(3), np.full(3, np.inf))
    assert got.hit.tolist() == [False, False, True]
    assert \
        np.abs(got.point[2] - [3.3, 0.5, 0.0]).max() < 1e-12


def test_triangle_params_survive_the_cache_codes():
    """A mesh hit's triangle kept as normalized parameters comes back exactly through the
    cache's 16-bit parameter codes, up to 2^32 - 1."""
    tri = np.array([0, 1, 65534, 65535, 65536, 15743, 123456789, 2 ** 32 - 1])
    uv = tri_params(tri)
    assert np.all((uv >= 0) & (uv <= 1))
    assert np.array_equal(params_tri(decode_params(encode_params(uv.astype(np.float32)))), tri)
