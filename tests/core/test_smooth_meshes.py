"""Mesh patches as Blender renders them: smooth shading from corner normals, each crossing of a
glass mesh entering or leaving by the side of the face it crosses, sound events where the
shading normal would send a ray the wrong way, and the scene format's optional normals."""

import copy
import json

import numpy as np
import pytest

from riray.geometry.nurbs import NurbsSurface
from riray.scene.io import SceneError, scene_from_dict, scene_to_dict
from riray.scene.model import ObjectMaterial, Patch, SpecularObject
from riray.trace.eventnormal import REFLECT_MARGIN, event_normal, oriented
from riray.trace.objectfn import trace_object
from riray.trace.patches import PatchTracer

IOR = 1.5


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def uv_sphere(n_lat=12, n_lon=24, r=1.0):
    """A closed UV sphere mesh, outward winding: (vertices, triangles)."""
    th = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    ring = np.stack([np.sin(th)[:, None] * np.cos(ph), np.sin(th)[:, None] * np.sin(ph),
                     np.cos(th)[:, None] * np.ones_like(ph)], axis=-1).reshape(-1, 3)
    verts = r * np.vstack([[0, 0, 1], ring, [0, 0, -1]])
    tris = []
    idx = lambda i, j: 1 + i * n_lon + j % n_lon
    for j in range(n_lon):
        tris.append([0, idx(0, j), idx(0, j + 1)])
        tris.append([len(verts) - 1, idx(n_lat - 2, j + 1), idx(n_lat - 2, j)])
    for i in range(n_lat - 2):
        for j in range(n_lon):
            a, b, c, d = idx(i, j), idx(i, j + 1), idx(i + 1, j), idx(i + 1, j + 1)
            tris += [[a, c, b], [b, c, d]]
    return verts, np.array(tris, np.int64)


def mesh_tracer(verts, tris, normals=None):
    obj = SpecularObject("m", [Patch("m", 0, vertices=np.asarray(verts, float),
                                     triangles=np.asarray(tris, np.int64), normals=normals)])
    return PatchTracer(obj)


def glass():
    return ObjectMaterial(kind="glass", ior=IOR)


def angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", unit(a), unit(b)), -1, 1)))


def sphere_rays(n=400, seed=3):
    """Rays from far away aimed at points spread over the unit sphere's visible disc."""
    rng = np.random.default_rng(seed)
    target = np.c_[rng.uniform(-0.9, 0.9, (n, 2)), np.zeros(n)]
    target = target[np.linalg.norm(target, axis=1) < 0.95]
    o = target + np.array([0.0, 0.0, 5.0])
    d = np.tile([0.0, 0.0, -1.0], (len(o), 1))
    tilt = unit(rng.normal(size=(len(o), 3))) * 0.2
    return o - 5 * tilt, unit(d + tilt)


# --------------------------------------------------------------------------- smooth shading
def test_smooth_sphere_normal_is_within_tessellation_error_of_the_true_normal():
    verts, tris = uv_sphere()
    normals = unit(verts[tris])                       # the true sphere normal at each corner
    o, d = sphere_rays()
    smooth = mesh_tracer(verts, tris, normals).intersect(o, d)
    flat = mesh_tracer(verts, tris).intersect(o, d)
    assert smooth.hit.all() and flat.hit.all()
    true_n = unit(smooth.point)
    err_s, err_f = angle_deg(smooth.normal, true_n), angle_deg(flat.normal, true_n)
    # a blend of exact corner normals errs by O(h^2) of the triangle's angular size h (here
    # 15 degrees = 0.26 rad): h^2 / 8 rad = 0.49 degrees; a flat face errs by O(h)
    h = np.radians(15.0)
    assert err_s.max() < np.degrees(h * h / 8) * 1.5
    assert err_s.mean() < 0.1 * err_f.mean()
    # the geometric normal stays the triangle's own
    assert np.allclose(smooth.geo_normal, flat.normal)


def test_split_normals_keep_each_face_normal_at_a_sharp_edge():
    # a roof: two quads meeting at a 90 degree ridge along y; the ridge's vertices are shared
    verts = np.array([[-1, 0, 0], [-1, 1, 0], [0, 0, 1], [0, 1, 1], [1, 0, 0], [1, 1, 0]], float)
    tris = np.array([[0, 2, 1], [1, 2, 3], [2, 4, 3], [3, 4, 5]])
    n_left, n_right = unit([-1, 0, 1]), unit([1, 0, 1])
    normals = np.array([[n_left] * 3, [n_left] * 3, [n_right] * 3, [n_right] * 3])
    eps = 1e-4
    o = np.array([[-eps, 0.5, 3.0], [eps, 0.5, 3.0], [-0.5, 0.5, 3.0]])
    d = np.tile([0.0, 0.0, -1.0], (3, 1))
    h = mesh_tracer(verts, tris, normals).intersect(o, d)
    assert np.allclose(h.normal, [n_left, n_right, n_left], atol=1e-12)
    # the same mesh shaded by its vertex normals (no split) blends across the ridge
    sm = np.array([unit([-1, 0, 1]), unit([-1, 0, 1]), [0, 0, 1], [0, 0, 1], unit([1, 0, 1]),
                   unit([1, 0, 1])])[tris]
    hv = mesh_tracer(verts, tris, sm).intersect(o, d)
    assert angle_deg(hv.normal[:2], h.normal[:2]).min() > 40


def test_smooth_mirror_sphere_reflects_about_the_blended_normal():
    verts, tris = uv_sphere(24, 48)
    o, d = sphere_rays(200)
    out = trace_object(mesh_tracer(verts, tris, unit(verts[tris])), ObjectMaterial(kind="mirror"),
                       o, d)
    keep = out.hit & (out.events == 1)
    n = unit(out.point[keep])                         # the true sphere's reflection
    want = d[keep] - 2 * np.einsum("ij,ij->i", d[keep], n)[:, None] * n
    assert keep.sum() > 100
    assert angle_deg(out.out_dir[keep], want).max() < 0.5


# --------------------------------------------------------------------------- open meshes
def sheet(z=0.0, up=True):
    """A 4 x 4 square at height z, its winding normal +z (up) or -z."""
    v = np.array([[-2, -2, z], [2, -2, z], [2, 2, z], [-2, 2, z]], float)
    t = np.array([[0, 1, 2], [0, 2, 3]]) if up else np.array([[0, 2, 1], [0, 3, 2]])
    return v, t


def snell_dir(d, n, eta):
    """Refraction of unit d through unit n facing against d (plain formula, one ray)."""
    c = -d @ n
    k = 1 - eta * eta * (1 - c * c)
    return eta * d + (eta * c - np.sqrt(k)) * n


def test_open_sheet_refracts_in_through_its_front_and_out_through_its_back():
    v, t = sheet(up=True)
    tracer = mesh_tracer(v, t)
    d_front = unit([0.3, 0.0, -1.0])        # from above: meets the front, enters the glass
    d_back = unit([0.3, 0.0, 1.0])          # from below: meets the back, leaves the glass
    o = np.array([[0, 0, 1.0], [0, 0, -1.0]])
    out = trace_object(tracer, glass(), o, np.array([d_front, d_back]))
    assert out.hit.all() and (out.events == 1).all()
    up = np.array([0, 0, 1.0])
    assert np.allclose(out.out_dir[0], snell_dir(d_front, up, 1 / IOR), atol=1e-12)
    assert np.allclose(out.out_dir[1], snell_dir(d_back, -up, IOR), atol=1e-12)
    # Snell's law as angles: sin(out) = sin(in) / 1.5 entering, * 1.5 leaving
    sin = lambda x: np.hypot(x[0], x[1])
    assert sin(out.out_dir[0]) == pytest.approx(sin(d_front) / IOR, rel=1e-12)
    assert sin(out.out_dir[1]) == pytest.approx(sin(d_back) * IOR, rel=1e-12)


def test_open_sheet_reflects_totally_from_behind_past_the_critical_angle():
    v, t = sheet(up=True)
    d = unit([2.0, 0.0, 1.0])               # 63 degrees from the normal, inside: past 41.8
    out = trace_object(mesh_tracer(v, t), glass(), np.array([[0, 0, -1.0]]), d[None])
    assert np.allclose(out.out_dir[0], d * [1, 1, -1], atol=1e-12)


def test_open_slab_of_two_sheets_shifts_a_ray_by_the_inner_snell_angle():
    # top sheet faces up, bottom sheet faces down: a slab 0.5 thick, open at its sides
    vt, tt = sheet(0.5, up=True)
    vb, tb = sheet(0.0, up=False)
    obj = SpecularObject("slab", [Patch("top", 0, vertices=vt, triangles=tt),
                                  Patch("bottom", 1, vertices=vb, triangles=tb)])
    d = unit([0.5, 0.2, -1.0])
    out = trace_object(PatchTracer(obj), glass(), np.array([[0, 0, 2.0]]), d[None])
    assert out.events[0] == 2
    assert np.allclose(out.out_dir[0], d, atol=1e-12)          # parallel faces: same direction
    sin_i = np.hypot(d[0], d[1])
    tan_t = np.tan(np.arcsin(sin_i / IOR))
    entry = np.array([0, 0, 2.0]) + d * (1.5 / -d[2])
    lateral = np.linalg.norm(out.out_origin[0][:2] - entry[:2])
    assert lateral == pytest.approx(0.5 * tan_t, rel=1e-9)
    assert out.out_origin[0][2] == pytest.approx(0.0, abs=1e-12)


def bilinear(p00, p10, p01, p11):
    pts = np.array([[p00, p01], [p10, p11]], float)
    return NurbsSurface(1, 1, np.array([0, 0, 1, 1.0]), np.array([0, 0, 1, 1.0]), pts,
                        np.ones((2, 2)))


def test_closed_flat_mesh_traces_as_the_same_box_of_nurbs_faces():
    """On a closed, outward mesh the side of each face says what parity says: a glass box
    traces the same as a mesh (face side) and as six bilinear NURBS faces (parity)."""
    c = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], float) * [2, 1, 1.5]
    faces = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    tris = np.array([t for a, b, cc, dd in faces for t in ((a, b, cc), (a, cc, dd))])
    nurbs = [Patch(f"f{i}", i, surface=bilinear(c[a], c[b], c[dd], c[cc]))
             for i, (a, b, cc, dd) in enumerate(faces)]
    rng = np.random.default_rng(7)
    target = rng.uniform(0, 1, (300, 3)) * [2, 1, 1.5]
    o = [1, 0.5, 0.75] + 4 * unit(rng.normal(size=(300, 3)))
    d = unit(target - o)
    a = trace_object(mesh_tracer(c, tris), glass(), o, d, max_events=6)
    b = trace_object(PatchTracer(SpecularObject("box", nurbs)), glass(), o, d, max_events=6)
    assert a.hit.sum() > 50 and np.array_equal(a.hit, b.hit)
    assert np.array_equal(a.events, b.events) and np.array_equal(a.null, b.null)
    assert np.allclose(a.out_dir, b.out_dir, atol=1e-9)
    assert np.allclose(a.out_origin, b.out_origin, atol=1e-9)


# --------------------------------------------------------------------------- sound events
def test_event_normal_keeps_reflections_above_and_refractions_below_the_face():
    rng = np.random.default_rng(1)
    n = 4000
    ng = np.tile([0.0, 0.0, 1.0], (n, 1))
    ns = unit(ng + rng.normal(scale=0.5, size=(n, 3)) * [1, 1, 0])     # up to ~60 degrees off
    d = unit(rng.normal(size=(n, 3)) * [1, 1, 0.3] - [0, 0, 0.2])
    d[:, 2] = -np.abs(d[:, 2]) - 1e-3                                  # all meet the front
    d = unit(d)
    ns, ng, back = oriented(d, ns, ng)
    assert not back.any()
    cos_g = -d[:, 2]
    r = d - 2 * np.einsum("ij,ij->i", d, (m := event_normal(d, ns, ng)))[:, None] * m
    assert (r[:, 2] >= np.minimum(REFLECT_MARGIN, 0.5 * cos_g) - 1e-9).all()
    for eta in (1 / IOR, IOR):
        e = np.full(n, eta)
        m = event_normal(d, ns, ng, e)
        c = -np.einsum("ij,ij->i", d, m)
        assert (c > 0).all()
        k = 1 - eta * eta * (1 - c * c)
        t = eta * d + (eta * c - np.sqrt(np.maximum(k, 0)))[:, None] * m
        refl = d + 2 * c[:, None] * m
        out = np.where((k < 0)[:, None], refl, t)
        assert (np.where(k < 0, out[:, 2] > 0, out[:, 2] < 0)).all()
    # where the shading normal is sound it is used as is
    sound = (np.einsum("ij,ij->i", d, ns) < 0) & \
        ((d - 2 * np.einsum("ij,ij->i", d, ns)[:, None] * ns)[:, 2] >= np.minimum(
            REFLECT_MARGIN, 0.5 * cos_g))
    assert sound.sum() > n / 2
    assert np.array_equal(event_normal(d, ns, ng)[sound], ns[sound])


def test_event_normal_tilts_just_far_enough():
    # a grazing ray whose reflection about the shading normal dives below the face
    ng = np.array([[0.0, 0.0, 1.0]])
    ns = unit([[0.4, 0.0, 1.0]])
    d = unit([[1.0, 0.0, -0.2]])
    m = event_normal(d, *oriented(d, ns, ng)[:2])
    r = d - 2 * (d @ m[0]) * m
    margin = min(REFLECT_MARGIN, 0.5 * 0.2 / np.linalg.norm([1, 0, -0.2]))
    assert r[0, 2] == pytest.approx(margin, abs=1e-4)       # raised to the margin, no further
    assert 0 < angle_deg(m, ns)[0] < angle_deg(ng, ns)[0]


def test_smooth_glass_sphere_mesh_has_no_dark_rays():
    """Every ray into a coarse smooth glass sphere leaves it (no trapped or null rays the flat
    and true spheres do not have) and leaves near where the true sphere sends it."""
    verts, tris = uv_sphere(8, 16)
    o, d = sphere_rays(500, seed=5)
    out = trace_object(mesh_tracer(verts, tris, unit(verts[tris])), glass(), o, d)
    assert out.hit.all() and not out.null.any()
    assert (out.events <= 4).all()


# --------------------------------------------------------------------------- scene format
def mesh_scene(normals=None):
    patch = {"kind": "mesh", "name": "tri", "class_id": 0,
             "vertices": [[0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1.2]],
             "triangles": [[0, 1, 2]], "quads": []}
    patch["quads"] = [[1, 3, 2, 0]]
    if normals is not None:
        patch["normals"] = normals
    return {"format": "riray-scene", "version": 1,
            "object": {"material": {"kind": "glass"}, "patches": [patch]}}


def three_normals(k):
    return [[unit([0.1 * i, 0.05 * j, 1.0]).tolist() for j in range(3)] for i in range(k)]


def test_scene_file_normals_round_trip_and_old_files_load_flat():
    old = scene_from_dict(mesh_scene())
    assert old.object.patches[0].normals is None
    assert "normals" not in scene_to_dict(old)["object"]["patches"][0]
    s = scene_from_dict(mesh_scene(three_normals(3)))
    nm = s.object.patches[0].normals
    assert nm.shape == (3, 3, 3) and np.allclose(nm, three_normals(3))
    again = scene_from_dict(json.loads(json.dumps(scene_to_dict(s))))
    assert np.array_equal(again.object.patches[0].normals, nm)


@pytest.mark.parametrize("change, message", [
    (lambda n: n[:2], r"patches\[0\]\.normals: expected 3 entries \(got 2\)"),
    (lambda n: [n[0], n[1], [n[2][0], n[2][1]]], r"normals\[2\]: expected 3 entries"),
    (lambda n: [n[0], [n[1][0], [0, 0, 0.5], n[1][2]], n[2]],
     r"normals\[1\]\[1\]: a normal must have unit length \(got length 0\.5\)"),
    (lambda n: [n[0], n[1], [n[2][0], n[2][1], [0, "x", 1]]], r"normals\[2\]\[2\]\[1\]"),
])
def test_scene_file_bad_normals_are_one_line_errors(change, message):
    d = mesh_scene(change(copy.deepcopy(three_normals(3))))
    with pytest.raises(SceneError, match=message) as e:
        scene_from_dict(d)
    assert "\n" not in str(e.value)


def test_open_slab_fresnel_tree_leaves_one_reflection_each_way():
    """A dielectric slab of two open sheets: every crossing of the parallel faces reflects the
    same Fresnel R (the entry's, at the entry angle), so past the entry the output ray carries
    1 - R, and at the default weight floor the tree's one kept branch (R, reflected off the
    bottom sheet from inside) leaves through the top with R (1 - R), upward; its own
    reflection (R^2 < FRESNEL_MIN_WEIGHT) is dropped."""
    vt, tt = sheet(0.5, up=True)
    vb, tb = sheet(0.0, up=False)
    obj = SpecularObject("slab", [Patch("top", 0, vertices=vt, triangles=tt),
                                  Patch("bottom", 1, vertices=vb, triangles=tb)])
    d = unit([0.5, 0.2, -1.0])
    up_down = lambda o, dd: np.stack([dd[:, 2] > 0, dd[:, 2] < 0, 0 * dd[:, 2]], 1).astype(float)
    out = trace_object(PatchTracer(obj), ObjectMaterial(kind="dielectric", ior=IOR),
                       np.array([[0, 0, 2.0]]), d[None], shade=up_down)
    cos_i = -d[2]
    cos_t = np.sqrt(1 - (1 - cos_i ** 2) / IOR ** 2)
    rs = (cos_i - IOR * cos_t) / (cos_i + IOR * cos_t)
    rp = (IOR * cos_i - cos_t) / (IOR * cos_i + cos_t)
    r = 0.5 * (rs ** 2 + rp ** 2)
    assert out.fresnel[0] == pytest.approx(r, abs=1e-12)
    assert out.out_weight[0] == pytest.approx(1 - r, abs=1e-12)
    assert np.abs(out.branch_color[0] - [r * (1 - r), 0.0, 0.0]).max() < 1e-12
