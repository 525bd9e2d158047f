"""The sample scenes (core/scene/samples.py, sample_scenes/*.json): they build, validate and
round-trip through the JSON format; the teapot data is Newell's (32 patches that join along
shared edges, 4-fold symmetric body); the solids of revolution are closed and outward-oriented;
every object stands on the table inside the room; every camera sees its object."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest

from riray.geometry.nurbs import evaluate
from riray.geometry.primitives import revolve
from riray.scene.camera import project_points
from riray.scene import samples
from riray.scene.io import load_scene, save_scene, scene_from_dict, scene_to_dict
from riray.scene.model import ObjectMaterial

SOLIDS = {"vase_mirror": ["vase"], "vase_glass": ["vase"], "glass_sphere": ["sphere"],
          "bowl": ["bowl", "lid", "knob"]}


@pytest.fixture(scope="module")
def scenes():
    return {name: samples.build(name) for name in samples.SAMPLES}


def _by_name(scene):
    return {p.name: p for p in scene.object.patches}


def _grid(surf, n):
    u0, u1, v0, v1 = surf.domain
    uu, vv = np.meshgrid(np.linspace(u0, u1, n), np.linspace(v0, v1, n), indexing="ij")
    return evaluate(surf, uu.ravel(), vv.ravel(), derivatives=0)[0].reshape(n, n, 3)


def _gauss(knots, order=8):
    """Gauss-Legendre nodes and weights over every non-empty knot span."""
    x, w = np.polynomial.legendre.leggauss(order)
    k = np.unique(np.asarray(knots, dtype=np.float64))
    a, b = k[:-1, None], k[1:, None]
    return ((a + b) / 2 + (b - a) / 2 * x).ravel(), ((b - a) / 2 * w).ravel()


def _enclosed_volume(surf):
    """(1/3) integral of S . (Su x Sv): the volume inside a closed surface whose Su x Sv points
    outward (negative if it points inward, not a volume at all if the surface is open)."""
    (u, wu), (v, wv) = _gauss(surf.knots_u), _gauss(surf.knots_v)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    s, su, sv = evaluate(surf, uu.ravel(), vv.ravel())
    f = np.einsum("ij,ij->i", s, np.cross(su, sv)).reshape(uu.shape)
    return float(wu @ f @ wv) / 3.0


def _profile_volume(surf):
    """Volume of the solid of revolution of the profile S(0, v) by Green's theorem:
    the closed (r, z) loop (profile + axis) encloses V = contour integral of pi r^2 dz."""
    v, wv = _gauss(surf.knots_v)
    s, _, sv = evaluate(surf, np.zeros_like(v), v)
    axis = surf.points[0, 0, :2]          # pole control point: on the axis
    r = np.linalg.norm(s[:, :2] - axis, axis=1)
    return float(np.sum(wv * np.pi * r ** 2 * sv[:, 2]))


# --------------------------------------------------------------------------- all samples
@pytest.mark.parametrize("name", samples.SAMPLES)
def test_sample_builds_validates_and_round_trips(name, scenes, tmp_path):
    scene = scenes[name]
    d = scene_to_dict(scene)
    scene_from_dict(d)                                   # validates (raises SceneError)
    path = tmp_path / f"{name}.json"
    save_scene(scene, path)
    assert scene_to_dict(load_scene(path)) == d          # save -> load is exact
    assert path.stat().st_size < 300_000
    assert scene.render.width == scene.render.height == 300
    assert scene.render.max_events == 8
    assert [c.name for c in scene.cameras] == ["far", "close", "zoom"]
    assert all(c.kind == "perspective" for c in scene.cameras)
    assert scene.lights and scene.meshes
    assert all(not p.is_mesh for p in scene.object.patches)


# sin, cos and matmul may differ in the last bit between CPUs and numpy builds, so a freshly
# built scene matches its shipped file to a few ulps, not bit for bit; a real change of the
# builder moves numbers by far more than this.
BUILD_RTOL = BUILD_ATOL = 1e-12


def assert_close_tree(got, want, path="scene"):
    """Equal JSON-like trees: same keys, lengths, types and non-float values; floats within
    BUILD_RTOL / BUILD_ATOL."""
    assert type(got) is type(want), f"{path}: {type(got).__name__} != {type(want).__name__}"
    if isinstance(want, dict):
        assert list(got) == list(want), f"{path}: keys {list(got)} != {list(want)}"
        for k in want:
            assert_close_tree(got[k], want[k], f"{path}.{k}")
    elif isinstance(want, list):
        assert len(got) == len(want), f"{path}: length {len(got)} != {len(want)}"
        for i, (g, w) in enumerate(zip(got, want)):
            assert_close_tree(g, w, f"{path}[{i}]")
    elif isinstance(want, float):
        assert math.isclose(got, want, rel_tol=BUILD_RTOL, abs_tol=BUILD_ATOL), \
            f"{path}: {got!r} != {want!r}"
    else:
        assert got == want, f"{path}: {got!r} != {want!r}"


@pytest.mark.parametrize("name", samples.SAMPLES)
def test_shipped_file_matches_build(name, scenes):
    """sample_scenes/<name>.json is what build() makes (rerun build_scenes.py if not), up to
    last-bit differences of the machine's floating point."""
    path = samples.sample_path(name)
    assert_close_tree(scene_to_dict(load_scene(path)), scene_to_dict(scenes[name]))


def test_close_tree_catches_real_differences(scenes):
    d = scene_to_dict(scenes["bowl"])
    ulp = json.loads(json.dumps(d))
    m = ulp["cameras"][0]["matrix_world"]
    m[0][0] = math.nextafter(m[0][0], 2.0)
    assert_close_tree(ulp, d)                            # an ulp is tolerated
    for edit in (lambda e: e["cameras"][0]["matrix_world"][0].__setitem__(0, m[0][0] + 1e-9),
                 lambda e: e["object"]["patches"].pop(),
                 lambda e: e["render"].__setitem__("width", 301),
                 lambda e: e["object"]["material"].__setitem__("kind", "glass"),
                 lambda e: e["render"].__setitem__("width", 300.0)):
        bad = json.loads(json.dumps(d))
        edit(bad)
        with pytest.raises(AssertionError):
            assert_close_tree(bad, d)


def test_default_materials(scenes):
    for name in ("teapot", "vase_mirror", "bowl"):
        m = scenes[name].object.material
        assert m.kind == "mirror" and 0 < m.specular <= 0.5
    for name in ("vase_glass", "glass_sphere"):
        m = scenes[name].object.material
        assert m.kind == "glass" and m.ior == 1.5


def test_material_override():
    assert samples.build("teapot", material="dielectric").object.material.kind == "dielectric"
    mat = ObjectMaterial(kind="glass", ior=1.33)
    assert samples.build("bowl", material=mat).object.material is mat
    assert samples.build("vase_glass", material="mirror").object.material.kind == "mirror"
    with pytest.raises(ValueError, match="material"):
        samples.build("teapot", material="chrome")
    with pytest.raises(ValueError, match="unknown sample"):
        samples.build("teacup")


def test_sample_path(monkeypatch, tmp_path):
    assert samples.sample_path("teapot").name == "teapot.json"
    assert samples.sample_path("teapot").parent == samples.SAMPLE_DIR
    monkeypatch.setattr(samples, "SAMPLE_DIR", tmp_path)
    with pytest.raises(FileNotFoundError, match="build_scenes.py"):
        samples.sample_path("bowl")
    with pytest.raises(ValueError, match="unknown sample"):
        samples.sample_path("teacup")


# --------------------------------------------------------------------------- placement, cameras
@pytest.mark.parametrize("name", samples.SAMPLES)
def test_object_on_table_inside_room(name, scenes):
    scene = scenes[name]
    lo, hi = samples.patches_bbox(scene.object.patches)        # control points: conservative
    pts = samples.sample_points(scene.object.patches, 17)
    top = samples.table_top()
    tx, ty, _ = samples.TABLE_SIZE
    assert pts[:, 2].min() >= top[2]                            # above the table top ...
    assert pts[:, 2].min() < top[2] + 0.005                     # ... and standing on it
    assert np.all(np.abs(lo[:2] - top[:2]) < (tx / 2, ty / 2))  # over the table
    assert np.all(np.abs(hi[:2] - top[:2]) < (tx / 2, ty / 2))
    rlo, rhi = samples.room_bounds()
    assert np.all(lo > rlo) and np.all(hi < rhi)
    table = next(m for m in scene.meshes if m.name == "table_top")
    assert table.vertices[:, 2].max() == pytest.approx(top[2])


@pytest.mark.parametrize("name", samples.SAMPLES)
def test_cameras_see_the_object(name, scenes):
    scene = scenes[name]
    w, h = scene.render.width, scene.render.height
    pts = samples.sample_points(scene.object.patches, 65 if name != "teapot" else 33)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    rlo, rhi = samples.room_bounds()
    spans = {}
    for cam in scene.cameras:
        loc = cam.matrix_world[:3, 3]
        assert np.all(loc > rlo) and np.all(loc < rhi), cam.name          # inside the room
        assert not np.all((loc > lo) & (loc < hi)), cam.name               # outside the object
        px, py, depth = project_points(cam, w, h, ((lo + hi) / 2)[None])
        assert depth[0] > cam.clip_start, cam.name
        px, py, depth = project_points(cam, w, h, pts)
        assert np.all(depth > cam.clip_start), cam.name
        inside = (px >= 0) & (px <= w) & (py >= 0) & (py <= h)
        near_centre = (np.abs(px - w / 2) < 0.1 * w) & (np.abs(py - h / 2) < 0.1 * h)
        assert near_centre.any(), cam.name              # the object is at the frame centre
        spans[cam.name] = max(np.ptp(px), np.ptp(py)) / w
        if cam.name == "zoom":
            assert not inside.all()                     # a section: the object exceeds the frame
        else:
            assert inside.all(), cam.name               # the whole object is in the frame
            px, py, _ = project_points(cam, w, h, ((lo + hi) / 2)[None])
            assert 0 < px[0] < w and 0 < py[0] < h
    assert 0.6 < spans["close"] <= 1.0                  # close: the object fills most of it
    assert spans["far"] < 0.6 * spans["close"]
    assert spans["zoom"] > 1.5 * spans["close"]


# --------------------------------------------------------------------------- teapot
def test_teapot_data():
    raw = json.loads(samples.TEAPOT_DATA.read_text())
    assert "Newell" in raw["source"] and "public-domain" in raw["source"]
    data = samples.load_teapot_data()
    assert data["vertices"].shape == (306, 3) and data["patches"].shape == (32, 16)
    sizes = {g: len(ids) for g, ids in data["groups"].items()}
    assert sizes == {"rim": 4, "body": 8, "handle": 4, "spout": 4, "lid_knob": 4, "lid": 4,
                     "bottom": 4}
    assert sorted(itertools.chain(*data["groups"].values())) == list(range(32))
    v = data["vertices"]
    assert v[:, 2].min() == 0.0 and v[:, 2].max() == 3.15      # Newell's units
    assert v[:, 0].min() == -3.0 and v[:, 0].max() == 3.525    # handle .. spout tip


def test_teapot_classes(scenes):
    patches = scenes["teapot"].object.patches
    assert len(patches) == 32
    cls = {}
    for p in patches:
        cls.setdefault(p.name.rsplit("_", 1)[0], set()).add(p.class_id)
    assert all(len(c) == 1 for c in cls.values())
    cls = {g: c.pop() for g, c in cls.items()}
    assert cls["rim"] == cls["body"]
    own = [cls[g] for g in ("body", "handle", "spout", "lid_knob", "lid", "bottom")]
    assert len(set(own)) == 6


def _edges(surf, n=9):
    g = _grid(surf, n)
    return [g[0], g[-1], g[:, 0], g[:, -1]]


def test_teapot_patches_join_along_shared_edges(scenes):
    """Adjacent patches' boundary curves coincide (evaluated, forward or reversed); the counted
    seams are exactly the 52 of the data set, and no non-degenerate edge of the rotational
    groups is left open except the rim's inner lip and the lid's outer edge."""
    patches = scenes["teapot"].object.patches
    edges = [_edges(p.surface) for p in patches]
    scale = 0.6
    seams, partner = 0, {}
    for (i, ei), (j, ej) in itertools.combinations(enumerate(edges), 2):
        for a, ca in enumerate(ei):
            if np.ptp(ca, axis=0).max() < 1e-9:            # collapsed edge (pole)
                continue
            for b, cb in enumerate(ej):
                err = min(np.abs(ca - cb).max(), np.abs(ca - cb[::-1]).max())
                if err < 1e-12 * scale:
                    seams += 1
                    partner.setdefault((i, a), []).append(j)
                    partner.setdefault((j, b), []).append(i)
                else:
                    # near misses would be typos in the data: edges meet exactly or not at all
                    assert err > 1e-3 * scale or np.ptp(cb, axis=0).max() < 1e-9, (i, a, j, b)
    assert seams == 52
    group = {i: p.name.rsplit("_", 1)[0] for i, p in enumerate(patches)}
    for i, g in group.items():
        for a, curve in enumerate(edges[i]):
            degenerate = np.ptp(curve, axis=0).max() < 1e-9
            if g in ("handle", "spout"):
                assert all(group[j] == g for j in partner.get((i, a), []))   # no seam w/ body
                continue
            open_lip = (g == "rim" and a == 2) or (g == "lid" and a == 3)
            assert degenerate or open_lip or (i, a) in partner, (g, i, a)


def test_teapot_body_rotational_symmetry(scenes):
    """Rim, body, knob, lid and bottom: each quadrant is the previous one turned by 90 degrees
    about the pot's axis (evaluated surfaces, not just control points)."""
    data = samples.load_teapot_data()
    patches = scenes["teapot"].object.patches
    body = np.concatenate([patches[i].surface.points.reshape(-1, 3)
                           for i in data["groups"]["body"]])
    axis = np.array([(body[:, 0].min() + body[:, 0].max()) / 2,
                     (body[:, 1].min() + body[:, 1].max()) / 2])
    for g in ("rim", "body", "lid_knob", "lid", "bottom"):
        ids = data["groups"][g]
        for ring in range(0, len(ids), 4):
            quad = [_grid(patches[i].surface, 7) for i in ids[ring:ring + 4]]
            for k in range(4):
                a, b = quad[k], quad[(k + 1) % 4]
                best = np.inf
                for ang in (np.pi / 2, -np.pi / 2):
                    c, s = np.cos(ang), np.sin(ang)
                    xy = a[..., :2] - axis
                    rot = np.stack([c * xy[..., 0] - s * xy[..., 1],
                                    s * xy[..., 0] + c * xy[..., 1]], -1) + axis
                    best = min(best, max(np.abs(rot - b[..., :2]).max(),
                                         np.abs(a[..., 2] - b[..., 2]).max()))
                assert best < 1e-12, (g, ids[ring + k])


def test_teapot_size_and_outward_normals(scenes):
    patches = scenes["teapot"].object.patches
    pts = samples.sample_points(patches, 17)
    assert np.ptp(pts[:, 0]) == pytest.approx(samples.TEAPOT_WIDTH, rel=0.02)
    # body patches: Su x Sv points away from the axis
    body = [p for p in patches if p.name.startswith("body")]
    ctr = np.mean([p.surface.points.reshape(-1, 3).mean(axis=0) for p in body], axis=0)
    for p in body:
        s, su, sv = evaluate(p.surface, [0.3, 0.5, 0.7], [0.5, 0.3, 0.7])
        radial = s[:, :2] - ctr[:2]
        assert np.all(np.einsum("ij,ij->i", np.cross(su, sv)[:, :2], radial) > 0), p.name


# --------------------------------------------------------------------------- solids of revolution
@pytest.mark.parametrize("name", sorted(SOLIDS))
def test_solids_are_closed_and_outward(name, scenes):
    scene = scenes[name]
    for pname in SOLIDS[name]:
        surf = _by_name(scene)[pname].surface
        u0, u1, v0, v1 = surf.domain
        axis = surf.points[0, 0, :2]
        # the profile starts and ends on the axis: both v ends are poles
        assert np.allclose(surf.points[:, 0, :2], axis, atol=1e-15)
        assert np.allclose(surf.points[:, -1, :2], axis, atol=1e-15)
        u = np.linspace(u0, u1, 13)
        for v in (v0, v1):
            s = evaluate(surf, u, np.full_like(u, v), derivatives=0)[0]
            assert np.abs(s[:, :2] - axis).max() < 1e-12
            assert np.ptp(s[:, 2]) < 1e-12
        # the circle closes: u = u0 and u = u1 give the same profile
        v = np.linspace(v0, v1, 41)
        a = evaluate(surf, np.full_like(v, u0), v, derivatives=0)[0]
        b = evaluate(surf, np.full_like(v, u1), v, derivatives=0)[0]
        assert np.abs(a - b).max() < 1e-12
        # closed and outward: the divergence-theorem volume is positive and equals the volume
        # of revolution of the profile loop
        vol = _enclosed_volume(surf)
        assert vol > 0, pname
        assert vol == pytest.approx(_profile_volume(surf), rel=1e-6), pname


@pytest.mark.parametrize("profile", ["VASE_PROFILE", "BOWL_PROFILE", "LID_PROFILE"])
def test_profiles_are_simple_closed_loops(profile):
    """Ends on the axis with horizontal end legs (smooth poles), r >= 0, and the sampled profile
    curve does not cross itself (so the solid is well defined)."""
    prof = getattr(samples, profile)
    assert prof[0, 0] == 0 and prof[-1, 0] == 0
    assert prof[1, 1] == prof[0, 1] and prof[-2, 1] == prof[-1, 1]
    surf = revolve(prof)
    v0, v1 = surf.domain[2:]
    c = evaluate(surf, np.zeros(801), np.linspace(v0, v1, 801), derivatives=0)[0][:, [0, 2]]
    assert c[1:-1, 0].min() > 0
    a, b = c[:-1], c[1:]

    def orient(p, q, r):
        return np.sign((q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1])
                       - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0]))

    for i in range(len(a) - 2):
        j = np.arange(i + 2, len(a))
        hit = ((orient(a[i], b[i], a[j]) * orient(a[i], b[i], b[j]) < 0)
               & (orient(a[j], b[j], a[i]) * orient(a[j], b[j], b[i]) < 0))
        assert not hit.any(), (profile, i, j[hit][:3])


def test_vase_wall_and_shape(scenes):
    surf = _by_name(scenes["vase_mirror"])["vase"].surface
    assert np.array_equal(surf.points, _by_name(scenes["vase_glass"])["vase"].surface.points)
    pts = samples.sample_points([_by_name(scenes["vase_mirror"])["vase"]], 33)
    height = np.ptp(pts[:, 2])
    assert 0.4 < height < 0.5
    # a waist: the outer radius dips between the belly and the lip
    v = np.linspace(*surf.domain[2:], 2001)
    s = evaluate(surf, np.zeros_like(v), v, derivatives=0)[0]
    r = np.linalg.norm(s[:, :2] - surf.points[0, 0, :2], axis=1)
    top = np.argmax(s[:, 2])
    outer_r, outer_z = r[:top], s[:top, 2] - s[:, 2].min()
    belly = outer_r[outer_z < 0.25].max()
    waist = outer_r[(outer_z > 0.25) & (outer_z < 0.4)].min()
    lip = outer_r[outer_z > 0.4].max()
    assert waist < 0.6 * belly and lip > 1.4 * waist


def test_glass_sphere_is_exact(scenes):
    surf = _by_name(scenes["glass_sphere"])["sphere"].surface
    g = _grid(surf, 25).reshape(-1, 3)
    centre = samples.table_top() + (0, 0, samples.LIFT + samples.GLASS_SPHERE_RADIUS)
    assert np.abs(np.linalg.norm(g - centre, axis=1) - samples.GLASS_SPHERE_RADIUS).max() < 1e-13
    assert _enclosed_volume(surf) == pytest.approx(4 / 3 * np.pi * 0.15 ** 3, rel=1e-9)


def test_bowl_lid_and_knob_fit(scenes):
    parts = _by_name(scenes["bowl"])
    assert [p.name for p in scenes["bowl"].object.patches] == ["bowl", "lid", "knob"]
    assert len({p.class_id for p in parts.values()}) == 3
    pts = {n: samples.sample_points([p], 33) for n, p in parts.items()}
    # the lid rests on the bowl's rim with no gap (sunk slightly into it), and is wider
    assert pts["lid"][:, 2].min() < pts["bowl"][:, 2].max() < pts["lid"][:, 2].max()
    rad = {n: np.abs(p[:, 0] - samples.table_top()[0]).max() for n, p in pts.items()}
    assert rad["lid"] > rad["bowl"] > rad["knob"]
    # the knob sits on the lid's top, sunk into it a little
    assert pts["knob"][:, 2].min() < pts["lid"][:, 2].max() < pts["knob"][:, 2].max()
