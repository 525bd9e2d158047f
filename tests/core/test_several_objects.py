"""Scenes of several specular objects: a mirror sphere above a square plane mirror under a
gradient sky (no meshes, no lights, no local shading), so every camera ray's colour is the sky
along the ray's last direction times the tints of the mirrors it met. The truth is a plain
per-ray reference: ray-sphere and ray-plane in closed form, the nearest hit first, each ray
reflected until it escapes or has met MAX_OBJECT_CHAIN objects. Rendered exactly and through
one RI-Tree per object; the scene format's list of objects and its older single object."""

import json

import numpy as np
import pytest

from riray.geometry.primitives import bilinear, sphere
from riray.ritree import tree as ritree
from riray.ritree.bake import bake
from riray.ritree.region import region_for_cameras
from riray.render.exact import render_exact
from riray.render.frame import (MAX_OBJECT_CHAIN, ExactAnswerer, Specular, TreeAnswerer,
                                shade_share)
from riray.render.interpolated import render_tree
from riray.ritree.query import TreeQuery
from riray.scene.camera import Shot, camera_rays
from riray.scene.format import scene_to_dict
from riray.scene.io import load_scene, scene_from_dict
from riray.scene.model import (Camera, ObjectMaterial, Patch, RenderSettings, Scene,
                               SpecularObject, World)
from riray.scene.parse import look_at_matrix
from riray.scene.validate import SceneError
from riray.trace.scene_tracer import object_tracers

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

CENTER, RADIUS = np.array([0.0, 0.0, 1.0]), 0.6      # the mirror sphere
HALF = 3.0                                           # the plane mirror: |x|, |y| <= HALF at z = 0
SPHERE_TINT, PLANE_TINT = (0.25, 1.0, 0.5), (1.0, 0.5, 0.25)
W = H = 32
GRAZE = 1e-3          # rays this close (relative) to a silhouette or the plane's edge are skipped


def _mirror(tint):
    return ObjectMaterial(kind="mirror", tint=tint, diffuse=0.0, specular=0.0)


def two_mirrors(order=("ball", "floor")) -> Scene:
    objs = {"ball": SpecularObject("ball", [Patch("s", 0, surface=sphere(CENTER, RADIUS))],
                                   _mirror(SPHERE_TINT)),
            "floor": SpecularObject("floor", [Patch("p", 0, surface=bilinear(
                (-HALF, -HALF, 0), (HALF, -HALF, 0), (-HALF, HALF, 0), (HALF, HALF, 0)))],
                _mirror(PLANE_TINT))}
    cam = Camera("cam", look_at_matrix((0.4, -3.5, 2.6), (0.0, 0.0, 0.7)), lens=30.0)
    return Scene(objects=[objs[n] for n in order], world=World(
        kind="gradient", color=(0.0, 0.0, 0.0), zenith=(1.0, 1.0, 1.0)), cameras=[cam],
        render=RenderSettings(width=W, height=H), name="two_mirrors")


def _sky(d):
    return np.clip(d[2], 0.0, 1.0) * np.ones(3)


def _sphere_t(o, d):
    oc = o - CENTER
    b, c = oc @ d, oc @ oc - RADIUS ** 2
    disc = b * b - c
    if disc < 0:
        return np.inf, disc / RADIUS ** 2 > -GRAZE
    t = -b - np.sqrt(disc)
    return (t, disc / RADIUS ** 2 < GRAZE) if t > 1e-9 else (np.inf, False)


def _plane_t(o, d):
    if abs(d[2]) < 1e-12:
        return np.inf, False
    t = -o[2] / d[2]
    if t <= 1e-9:
        return np.inf, False
    p = o + t * d
    edge = np.abs(np.abs(p[:2]) - HALF).min() < GRAZE * HALF
    return (t, edge) if np.all(np.abs(p[:2]) <= HALF) else (np.inf, edge)


def reference(o, d):
    """(colour, grazing, links) of one camera ray: the nearest mirror first, reflected (its
    tint applied) until it escapes or has met MAX_OBJECT_CHAIN mirrors, then the sky."""
    tint, left, graze, links = np.ones(3), None, False, []
    while len(links) < MAX_OBJECT_CHAIN:
        ts, gs = _sphere_t(o, d) if left != "ball" else (np.inf, False)
        tp, gp = _plane_t(o, d) if left != "floor" else (np.inf, False)
        graze |= gs or gp
        if min(ts, tp) == np.inf:
            break
        left = "ball" if ts < tp else "floor"
        o = o + min(ts, tp) * d
        n = (o - CENTER) / RADIUS if left == "ball" else np.array([0.0, 0.0, 1.0])
        d = d - 2.0 * (d @ n) * n
        tint = tint * (SPHERE_TINT if left == "ball" else PLANE_TINT)
        links.append(left)
    return tint * _sky(d), graze, links


@pytest.fixture(scope="module")
def scene():
    return two_mirrors()


@pytest.fixture(scope="module")
def truth(scene):
    o, d = camera_rays(scene.cameras[0], W, H)
    rows = [reference(a, b) for a, b in zip(o, d)]
    col = np.array([r[0] for r in rows])
    ok = ~np.array([r[1] for r in rows])
    links = [r[2] for r in rows]
    return o, d, col, ok, links


def test_reference_view_has_every_chain(truth):
    """The view holds rays meeting one, two and three mirrors (so each rule below is seen),
    and few grazing ones."""
    _, _, _, ok, links = truth
    lengths = np.array([len(x) for x in links])
    for k in range(1, MAX_OBJECT_CHAIN + 1):
        assert np.count_nonzero(lengths[ok] == k) >= 3, k
    assert ok.mean() > 0.95


def _exact(sts):
    return [Specular(s, ExactAnswerer(s)) for s in sts]


@pytest.mark.parametrize("order", [("ball", "floor"), ("floor", "ball")])
def test_exact_frame_matches_closed_form(truth, order):
    """Exactly traced, each ray sees the nearest mirror, then what that mirror's reflection
    meets, up to the chain's end, whatever order the scene lists the objects in."""
    o, d, want, ok, links = truth
    objs = _exact(object_tracers(two_mirrors(order)))
    got = shade_share(objs[0].st, o, d, objs[0].answerer, objs[1:])
    assert np.abs(got.color[ok] - want[ok]).max() < 1e-6
    first = np.array([x[0] if x else "" for x in links])
    for name, share in zip(order, got.objects):
        mine = np.zeros(len(o), bool)
        mine[share.hit] = True
        assert np.array_equal(mine[ok], first[ok] == name)


def test_render_exact_has_both_objects(scene, truth):
    """render_exact over the film (one sample: the pixel centres) gives the same colours."""
    _, _, want, ok, _ = truth
    sts = object_tracers(scene)
    res = render_exact(sts[0], Shot(width=W, height=H), workers=1, others=sts[1:])
    img = res.image.reshape(-1, 3)
    assert np.abs(img[ok] - want[ok]).max() < 1e-6


@pytest.fixture(scope="module")
def trees(scene):
    """A small RI-Tree per mirror, each baked for the camera alone (no other object in it)."""
    params = ritree.BakeParams(viewpoint_depth=2, viewpoint_refine=1, direction_depth=3)
    out = []
    for st in object_tracers(scene):
        region = region_for_cameras(st, params, scene.cameras, W, H)
        out.append(bake(st, params, region, workers=1))
    return out


def test_trees_frame_matches_closed_form(scene, truth, trees):
    """Through one tree per object (rays leaving one mirror meet the other's tree) the frame
    stays within interpolation error of the closed form, and render_tree reports each
    object's own pixels and traced share."""
    o, d, want, ok, links = truth
    sts = object_tracers(scene)
    objs = [Specular(s, TreeAnswerer(TreeQuery(t, s))) for s, t in zip(sts, trees)]
    got = shade_share(objs[0].st, o, d, objs[0].answerer, objs[1:])
    err = np.abs(got.color[ok] - want[ok]).max(axis=1)
    assert np.median(err) < 1e-6 and np.mean(err < 0.02) > 0.97
    res = render_tree(sts[0], trees[0], Shot(width=W, height=H), reference=True, workers=1,
                      others=[(sts[1], trees[1])])
    per = res.stats["summary"]["objects"]
    first = np.array([x[0] if x else "" for x in links])
    for name in ("ball", "floor"):
        assert per[name]["through"] == "tree"
        assert per[name]["object_pixels"] == pytest.approx(np.sum(first == name), abs=3)
    assert res.stats["summary"]["object_pixels"] == sum(p["object_pixels"] for p in per.values())


def test_one_object_makes_no_extra_pass(scene):
    """With one object the environment's closest hits are looked for once, for the camera
    rays (the output rays' colours find theirs while shading): no pass looks for other
    objects along the rays leaving it."""
    st = object_tracers(scene)[0]
    o, d = camera_rays(scene.cameras[0], W, H)
    calls = []
    closest = st.env.closest
    st.env.closest = lambda *a, **k: calls.append(len(a[0])) or closest(*a, **k)
    try:
        shade_share(st, o, d, ExactAnswerer(st))
    finally:
        del st.env.closest
    assert calls == [len(o)]


def test_format_lists_objects_and_reads_the_single_object(scene, tmp_path):
    d = scene_to_dict(scene)
    assert [o["name"] for o in d["objects"]] == ["ball", "floor"] and "object" not in d
    again = scene_from_dict(json.loads(json.dumps(d)))
    assert [o.name for o in again.objects] == ["ball", "floor"]
    with pytest.raises(ValueError, match="2 specular objects"):
        again.object
    one = dict(d)
    one["object"] = one.pop("objects")[1]
    old = scene_from_dict(one)
    assert [o.name for o in old.objects] == ["floor"] and old.object.name == "floor"
    assert "objects" not in scene_to_dict(old)


@pytest.mark.parametrize("change,pattern", [
    (lambda d: d["objects"][1]["patches"][0]["weights"][0].__setitem__(0, -1.0),
     r"^specular object 'floor': objects\[1\]\.patches\[0\]\.weights\[0\]\[0\]: weight"),
    (lambda d: d["objects"][1].__setitem__("name", "ball"),
     r"objects\[1\]\.name: duplicate specular object name 'ball'"),
    (lambda d: d["objects"][0].pop("name"), r"objects\[0\]: missing required key 'name'"),
    (lambda d: d.__setitem__("objects", []), r"objects: the scene needs at least one"),
    (lambda d: d.__setitem__("object", d["objects"][0]), r"not both"),
])
def test_bad_object_is_named(scene, change, pattern):
    d = json.loads(json.dumps(scene_to_dict(scene)))
    change(d)
    with pytest.raises(SceneError, match=pattern):
        scene_from_dict(d)


def test_scene_file_round_trip(scene, tmp_path):
    from riray.scene.io import save_scene
    save_scene(scene, tmp_path / "two.json")
    back = load_scene(tmp_path / "two.json")
    assert [o.material.tint for o in back.objects] == [SPHERE_TINT, PLANE_TINT]
