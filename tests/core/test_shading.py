"""Environment shading and local illumination against closed-form irradiance."""

import numpy as np
import pytest

from riray.scene.model import (Light, Material, Mesh, ObjectMaterial, Scene, SpecularObject,
                               Texture, World)
from riray.trace.meshes import MeshSet
from riray.trace.shading import MAX_RADIANCE, Environment, local_illumination
from riray.trace.textures import eval_texture, eval_world

ALBEDO = np.array([0.8, 0.6, 0.4])


def quad(z, half, name, mat, uvs=False):
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    return Mesh(name, v, np.array([[0, 1, 2], [0, 2, 3]]), mat,
                uvs=(v[:, :2] / (2 * half) + 0.5) if uvs else None)


def scene(lights, meshes=None, world=None, materials=None):
    mats = {"floor": Material("floor", "diffuse", Texture(color=tuple(ALBEDO))),
            "lamp": Material("lamp", "emission", Texture(color=(1.0, 0.5, 0.25)), strength=4.0)}
    mats.update(materials or {})
    return Scene(objects=[SpecularObject("obj", [])],
                 meshes=meshes if meshes is not None else [quad(0.0, 50.0, "floor", "floor")],
                 materials=mats, lights=lights, world=world or World(color=(0.1, 0.2, 0.3)))


def down_rays(xy, z=3.0):
    xy = np.atleast_2d(np.asarray(xy, float))
    return np.column_stack([xy, np.full(len(xy), z)]), np.tile([0.0, 0.0, -1.0], (len(xy), 1))


@pytest.mark.parametrize("shadows", [False, True])
def test_point_light_irradiance(shadows):
    h, power = 2.0, 500.0
    env = Environment(scene([Light("p", "point", color=(1.0, 1.0, 0.5), position=(1.0, 2.0, h),
                                   power=power, shadows=shadows)]))
    o, d = down_rays([[1.0, 2.0], [2.5, 2.0]])
    col = env.shade_rays(o, d)
    r2 = np.array([h * h, h * h + 1.5 ** 2])
    cos = h / np.sqrt(r2)
    e = power / (4 * np.pi * r2) * cos
    np.testing.assert_allclose(col, ALBEDO / np.pi * e[:, None] * [1.0, 1.0, 0.5], rtol=1e-12)
    assert env.stats == {"env_rays": 2, "shadow_rays": 2 if shadows else 0}


def test_sun_cosine_and_ambient_and_backface():
    theta = np.radians(35.0)
    world = World(color=(0.0, 0.0, 0.0), ambient=0.25)
    sun = Light("sun", "sun", direction=(np.sin(theta), 0.0, -np.cos(theta)), strength=3.0)
    env = Environment(scene([sun], world=world))
    o, d = down_rays([[0.3, -0.4]])
    col = env.shade_rays(o, d)
    np.testing.assert_allclose(col[0], ALBEDO / np.pi * (0.25 + 3.0 * np.cos(theta)), rtol=1e-12)
    # seen from below, the floor faces away from the sun: ambient only
    below = env.shade_rays(o * [1, 1, -1], -d)
    np.testing.assert_allclose(below[0], ALBEDO / np.pi * 0.25, rtol=1e-12)


def test_shadows_from_env_mesh_and_occluder():
    light = Light("p", "point", position=(0.0, 0.0, 4.0), power=800.0)
    blocker = quad(2.0, 0.5, "blocker", "floor")
    o, d = down_rays([[0.0, 0.0], [3.0, 3.0]], z=1.0)     # below the blocker's height
    lit = Environment(scene([light])).shade_rays(o, d)
    assert np.all(lit > 0)
    env = Environment(scene([light], meshes=[quad(0.0, 50.0, "floor", "floor"), blocker]))
    col = env.shade_rays(o, d)
    np.testing.assert_allclose(col[0], 0.0)
    np.testing.assert_allclose(col[1], lit[1], rtol=1e-12)
    occ = Environment(scene([light]), occluder=MeshSet([blocker]))
    np.testing.assert_allclose(occ.shade_rays(o, d), col, rtol=1e-12)
    light.shadows = False
    np.testing.assert_allclose(Environment(scene([light]), occluder=MeshSet([blocker]))
                               .shade_rays(o, d), lit, rtol=1e-12)


def test_emission_ignores_lights_and_miss_sees_world():
    world = World(kind="gradient", color=(0.2, 0.2, 0.2), zenith=(0.1, 0.3, 0.9), strength=2.0)
    env = Environment(scene([Light("p", "point", position=(0, 0, 1.0), power=1e4)],
                            meshes=[quad(0.0, 1.0, "lamp", "lamp")], world=world))
    o, d = down_rays([[0.2, 0.1]])
    np.testing.assert_allclose(env.shade_rays(o, d), [[4.0, 2.0, 1.0]])
    up = np.array([[0.6, 0.0, 0.8], [0.0, -1.0, 0.0]])
    np.testing.assert_allclose(env.shade_rays(np.full((2, 3), 0.5), up), eval_world(world, up))
    assert env.stats["shadow_rays"] == 0


def test_textured_material_and_bad_references():
    tex = Texture(kind="checker", color=(1, 1, 1), color2=(0, 0, 0), scale=2.0, coords="uv")
    mats = {"chk": Material("chk", "diffuse", tex)}
    floor = quad(0.0, 2.0, "floor", "chk", uvs=True)
    env = Environment(scene([Light("s", "sun", direction=(0, 0, -1.0), strength=1.0)],
                            meshes=[floor], materials=mats))
    xy = np.array([[0.1, 0.1], [0.6, 0.1], [-1.3, 0.7]])
    o, d = down_rays(xy)
    uv = xy / 4.0 + 0.5
    np.testing.assert_allclose(env.shade_rays(o, d),
                               eval_texture(tex, np.column_stack([xy, 0 * xy[:, 0]]), uv) / np.pi)
    with pytest.raises(ValueError, match="'floor'.*no uvs"):
        Environment(scene([], meshes=[quad(0.0, 2.0, "floor", "chk")], materials=mats))
    with pytest.raises(ValueError, match="'floor'.*'nope'"):
        Environment(scene([], meshes=[quad(0.0, 2.0, "floor", "nope")]))


def test_local_illumination():
    h, power = 3.0, 900.0
    light = Light("p", "point", position=(0.0, 0.0, h), power=power)
    env = Environment(scene([light], world=World(ambient=0.5)))
    mat = ObjectMaterial(base_color=(0.5, 1.0, 0.25), diffuse=0.4, specular=0.3, shininess=20.0)
    p = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    n = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])      # the first is flipped to the viewer
    view = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])   # looking straight down: n.h = 1
    col = local_illumination(p, n, view, mat, env)
    e = power / (4 * np.pi * (h - 1.0) ** 2)
    diff = 0.4 * np.array(mat.base_color) / np.pi * (0.5 + e)
    spec = 0.3 * (20.0 + 8.0) / (8 * np.pi) * e
    np.testing.assert_allclose(col, [diff + spec] * 2, rtol=1e-12)
    # a blocker between the point and the light leaves the ambient term only
    env2 = Environment(scene([light], world=World(ambient=0.5),
                             meshes=[quad(2.0, 0.5, "floor", "floor")]))
    np.testing.assert_allclose(local_illumination(p, n, view, mat, env2),
                               [0.4 * np.array(mat.base_color) / np.pi * 0.5] * 2, rtol=1e-12)
    assert np.all(local_illumination(p, n, view, ObjectMaterial(specular=0.0), env) == 0)


def test_radiance_is_finite_for_extreme_valid_values():
    """A point light 1e-160 m above the floor (1/r^2 beyond float range) with the largest power
    and colour a scene file allows, one colour component 0: finite radiance, no NaN (inf * 0),
    clamped at MAX_RADIANCE, and the light's own spot the brightest."""
    light = Light("p", "point", color=(1e12, 0.0, 1e12), position=(0.0, 0.0, 1e-160), power=1e12)
    env = Environment(scene([light]))
    o, d = down_rays([[0.0, 0.0], [1e-3, 0.0], [2.0, 0.0]])
    col = env.shade_rays(o, d)
    assert np.isfinite(col).all() and np.isfinite(col.astype(np.float32)).all()
    assert col.max() <= MAX_RADIANCE and np.all(col[:, 1] == 0)
    assert col[0, 0] >= col[1, 0] > col[2, 0] > 0
    mat = ObjectMaterial(diffuse=1.0, base_color=(1e12, 1e12, 0.0), specular=1e12,
                         shininess=1e12)
    n = np.tile([0.0, 0.0, 1.0], (3, 1))
    loc = local_illumination(o + 3 * d, n, d, mat, env)
    assert np.isfinite(loc).all() and loc.max() <= MAX_RADIANCE


def test_render_of_extreme_valid_scene_is_finite_in_float32():
    """Every colour, power and strength of the glass sphere scene at the format's maximum
    (1e12): the float32 image is finite (radiance x tint would overflow it unclamped)."""
    from riray.render.exact import render_exact
    from riray.scene.camera import Shot
    from riray.trace.scene_tracer import SceneTracer
    from riray.scene import samples
    s = samples.build("glass_sphere")
    for li in s.lights:
        li.color, li.power, li.strength = (1e12,) * 3, 1e12, 1e12
    for m in s.materials.values():
        m.color.color = m.color.color2 = (1e12,) * 3
        m.strength = 1e12
    s.object.material.tint = (1e12,) * 3
    s.world.strength = s.world.ambient = 1e12
    res = render_exact(SceneTracer(s), Shot(camera="close", width=6, height=6), workers=1)
    assert np.isfinite(res.image.astype(np.float32)).all()
    assert res.image.max() > 1e20                      # really that bright (tint x clamped)
