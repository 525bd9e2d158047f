"""A camera region stays bounded at any render size: cameras are reduced one at a time (in
chunks of rays) and merged, the region keeps at most MAX_CAMERA_RAYS of a camera's rays for the
bake, and every ray of the image still lands in a baked cell and direction rectangle."""

import numpy as np
import pytest

import riray.ritree.region as region_mod
from riray.ritree.dircube import N_SLOTS, SLOT, U_AXIS, V_AXIS, dir_to_cube
from riray.ritree.locate import entry_points
from riray.ritree.region import region_for_cameras
from riray.ritree.tree import BakeParams
from riray.scene.camera import camera_rays
from riray.scene.samples import build
from riray.trace.scene_tracer import SceneTracer

PARAMS = BakeParams(viewpoint_depth=3, viewpoint_refine=1, direction_depth=4)


@pytest.fixture(scope="module")
def sphere():
    return SceneTracer(build("glass_sphere"))


def ray_keys(st, cams, w, h, level):
    """Plain reference: for every camera ray that reaches the object's box, the keys
    (viewpoint, slot) of the four corners of its level-``level`` cell, and its (u, v)."""
    pad = PARAMS.pad * st.tracer.diag + 1e-12

    class Box:
        box_lo, box_hi = st.tracer.lo - pad, st.tracer.hi + pad

    D, Dmax = PARAMS.viewpoint_depth, PARAMS.viewpoint_depth + PARAMS.viewpoint_refine
    G, m, step = (1 << Dmax) + 1, 1 << level, 1 << (Dmax - level)
    out = []
    for cam in cams:
        o, d = camera_rays(cam, w, h)
        t_in, face, x, y, _ = entry_points(Box, o, d)
        cf, u, v = dir_to_cube(d)
        sl = SLOT[face, cf]
        ok = np.isfinite(t_in) & (sl >= 0) & (t_in < st.env.hit_distance(o, d))
        for f, xx, yy, s, uu, vv in zip(face[ok], x[ok], y[ok], sl[ok], u[ok], v[ok]):
            ua, va = U_AXIS[f // 2], V_AXIS[f // 2]
            fx = min(max((xx - Box.box_lo[ua]) / (Box.box_hi[ua] - Box.box_lo[ua]), 0.0), 1.0)
            fy = min(max((yy - Box.box_lo[va]) / (Box.box_hi[va] - Box.box_lo[va]), 0.0), 1.0)
            ix, iy = min(int(fx * m), m - 1), min(int(fy * m), m - 1)
            for cx in (0, 1):
                for cy in (0, 1):
                    vk = f * G * G + (iy + cy) * step * G + (ix + cx) * step
                    out.append((vk * N_SLOTS + s, uu, vv))
    return out


def test_cameras_merged_one_by_one_equal_one_set(sphere, monkeypatch):
    """Two cameras' region, reduced per camera and chunk and merged, against a plain per-ray
    reference over both at once: the same keys, each rectangle the rays' (u, v) hull (no
    margin: not widened)."""
    cams = [sphere.scene.camera("close"), sphere.scene.camera("zoom")]
    monkeypatch.setattr(region_mod, "KEY_CHUNK", 100)         # several chunks a camera
    reg = region_for_cameras(sphere, PARAMS, cams, 24, 24, margin=0)
    for level in (PARAMS.viewpoint_depth, PARAMS.viewpoint_depth + 1):
        hull = {}
        for k, u, v in ray_keys(sphere, cams, 24, 24, level):
            r = hull.setdefault(int(k), [u, u, v, v])
            r[:] = [min(r[0], u), max(r[1], u), min(r[2], v), max(r[3], v)]
        keys, rects = reg.rects_at(level)
        assert sorted(hull) == list(keys)
        np.testing.assert_array_equal(rects, [hull[int(k)] for k in keys])


def test_the_bake_keeps_a_bounded_share_of_rays_yet_covers_every_ray(sphere, monkeypatch):
    """With the cap at 500 rays, the region keeps 500 of a 96 x 96 image's rays for the bake,
    yet every ray of the image finds its cell's corner trees and its direction inside their
    rectangles."""
    monkeypatch.setattr(region_mod, "MAX_CAMERA_RAYS", 500)
    cam = sphere.scene.camera("close")
    reg = region_for_cameras(sphere, PARAMS, [cam], 96, 96)
    level = PARAMS.viewpoint_depth
    keys, rects = reg.rects_at(level)
    full = ray_keys(sphere, [cam], 96, 96, level)
    assert len(reg.rays[0]) == 500 and len(full) > 4 * 4 * 500   # 4 corner keys a ray
    k = np.array([x[0] for x in full])
    pos = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
    assert np.array_equal(keys[pos], k)
    r = rects[pos]
    u, v = np.array([x[1] for x in full]), np.array([x[2] for x in full])
    assert np.all((r[:, 0] <= u) & (u <= r[:, 1]) & (r[:, 2] <= v) & (v <= r[:, 3]))
