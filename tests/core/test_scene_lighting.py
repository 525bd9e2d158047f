"""The world's light (sky term), area lights (closed-form irradiance, soft shadows, seen in
reflections) and glossy environment layers, against closed forms; their scene fields."""

import math

import numpy as np
import pytest

from riray.scene.format import scene_to_dict
from riray.scene.model import Light, Material, Mesh, Scene, SpecularObject, Texture, World
from riray.scene.parse import scene_from_dict
from riray.scene.samples import build
from riray.scene.validate import SceneError
from riray.trace.shading import AREA_SIDE, Environment

ALBEDO = np.array([0.8, 0.6, 0.4])
SKY = np.array([0.4, 0.5, 0.7])
FACES = np.array([[0, 1, 2], [0, 2, 3]])


def quad(z, half, name, mat):
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    return Mesh(name, v, FACES.copy(), mat)


def scene(lights, meshes=None, world=None, materials=None):
    mats = {"floor": Material("floor", "diffuse", Texture(color=tuple(ALBEDO)))}
    mats.update(materials or {})
    return Scene(objects=[SpecularObject("obj", [])],
                 meshes=meshes if meshes is not None else [quad(0.0, 50.0, "floor", "floor")],
                 materials=mats, lights=lights, world=world or World(color=(0.1, 0.2, 0.3)))


def down_rays(xy, z=3.0):
    xy = np.atleast_2d(np.asarray(xy, float))
    return np.column_stack([xy, np.full(len(xy), z)]), np.tile([0.0, 0.0, -1.0], (len(xy), 1))


def corner_form_factor(x, y):
    """Form factor from a point to a parallel rectangle of sides x, y (in units of the height)
    with one corner straight above it (the standard closed form)."""
    a, b = x / math.sqrt(1 + x * x), y / math.sqrt(1 + y * y)
    return (a * math.atan(y / math.sqrt(1 + x * x)) + b * math.atan(x / math.sqrt(1 + y * y))) \
        / (2 * math.pi)


def area(size=(1.0, 1.0), h=2.0, power=300.0, shape="rectangle", shadows=True, at=(0.0, 0.0)):
    return Light("a", "area", position=(at[0], at[1], h), direction=(0.0, 0.0, -1.0),
                 axis=(1.0, 0.0, 0.0), size=size, shape=shape, power=power, shadows=shadows)


def test_unoccluded_plane_under_a_uniform_sky_gets_albedo_times_sky():
    env = Environment(scene([], world=World(color=tuple(SKY), sky=True)))
    o, d = down_rays([[0.0, 0.0], [3.3, -7.1], [10.0, 20.0]])
    assert np.allclose(env.shade_rays(o, d), ALBEDO * SKY, rtol=1e-12)


def test_sky_is_off_unless_the_world_lights_the_scene():
    env = Environment(scene([], world=World(color=tuple(SKY))))
    o, d = down_rays([[0.0, 0.0]])
    assert np.allclose(env.shade_rays(o, d), 0.0)


def box_room(half, height, ceiling=True):
    """A room's floor, four walls and (optionally) ceiling: quads, 2 half wide, ``height``."""
    h, z = half, height
    walls = {"floor": [[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]],
             "north": [[-h, h, 0], [h, h, 0], [h, h, z], [-h, h, z]],
             "south": [[-h, -h, 0], [h, -h, 0], [h, -h, z], [-h, -h, z]],
             "east": [[h, -h, 0], [h, h, 0], [h, h, z], [h, -h, z]],
             "west": [[-h, -h, 0], [-h, h, 0], [-h, h, z], [-h, -h, z]],
             "ceiling": [[-h, -h, z], [h, -h, z], [h, h, z], [-h, h, z]]}
    if not ceiling:
        del walls["ceiling"]
    return [Mesh(k, np.array(v, float), FACES.copy(), "floor") for k, v in walls.items()]


def test_a_closed_room_casts_no_sky_rays_an_open_one_does():
    """In a closed room no sky ray can leave, so the term is off (no occlusion rays cast) and
    the floor is as dark as with the term on; without its ceiling the floor's centre sees the
    open square overhead: pi L times the form factor of a square of side 2 at height 1."""
    world = World(color=tuple(SKY), sky=True)
    closed = Environment(scene([], meshes=box_room(1.0, 1.0), world=world))
    assert not closed.sky
    o, d = np.array([[0.0, 0.0, 0.5]]), np.array([[0.0, 0.0, -1.0]])
    assert np.allclose(closed.shade_rays(o, d), 0.0)
    p, n = np.zeros((3, 1)), np.array([[0.0], [0.0], [1.0]])
    assert np.allclose(closed.sky_irradiance(p, n, n, None), 0.0)
    open_top = Environment(scene([], meshes=box_room(1.0, 1.0, ceiling=False), world=world))
    assert open_top.sky
    ring = np.array([[0.0, 0.0], [0.01, 0.0], [0.0, 0.01], [-0.01, 0.0], [0.0, -0.01]])
    pts = np.column_stack([ring, np.zeros(len(ring))]).T.copy()
    nrm = np.tile([[0.0], [0.0], [1.0]], (1, len(ring)))
    e = open_top.sky_irradiance(pts, nrm, nrm, None).mean(axis=1)
    assert np.allclose(e, np.pi * SKY * 4 * corner_form_factor(1.0, 1.0), rtol=0.1)


def test_sky_under_a_roof_is_the_open_share_of_the_cosine():
    """A point under an infinite-ish roof at height h with a hole of radius r straight above
    sees the sky through the hole only: irradiance pi L sin^2 = pi L r^2 / (r^2 + h^2) in the
    mean over the point's sample sets (a ring of points near the axis averages the noise)."""
    r, h = 1.0, 1.0
    n = 64
    a = 2 * np.pi * np.arange(n) / n
    ring = np.stack([np.cos(a), np.sin(a)], 1) * r * 1.2
    roof = []
    for k in range(n):                               # the roof: a fan of quads outside the hole
        c0, c1 = np.cos(a[k]), np.sin(a[k])
        c2, c3 = np.cos(a[(k + 1) % n]), np.sin(a[(k + 1) % n])
        v = np.array([[r * c0, r * c1, h], [50 * c0, 50 * c1, h], [50 * c2, 50 * c3, h],
                      [r * c2, r * c3, h]])
        roof.append(Mesh(f"roof{k}", v, FACES.copy(), "floor"))
    env = Environment(scene([], meshes=[quad(0.0, 50.0, "floor", "floor")] + roof,
                            world=World(color=tuple(SKY), sky=True)))
    pts = np.column_stack([np.zeros(1), np.zeros(1), np.zeros(1)])
    pts = np.vstack([pts, np.column_stack([0.01 * ring, np.zeros(n)])])
    nrm = np.tile([0.0, 0.0, 1.0], (len(pts), 1)).T
    e = env.sky_irradiance(pts.T.copy(), nrm, nrm, None)
    want = np.pi * SKY * r * r / (r * r + h * h)
    assert np.allclose(e.mean(axis=1), want, rtol=0.03)


@pytest.mark.parametrize("size,h", [((1.0, 1.0), 2.0), ((2.0, 0.5), 1.0), ((3.0, 3.0), 0.5)])
def test_rectangle_irradiance_on_its_axis_is_the_closed_form(size, h):
    light = area(size, h, shadows=False)
    env = Environment(scene([light]))
    e, _ = env.light_irradiance(light, [[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]], [[0.0, 0.0, 1.0]])
    radiance = light.power / (np.pi * size[0] * size[1])             # Cycles: P / (pi A)
    ff = 4 * corner_form_factor(size[0] / 2 / h, size[1] / 2 / h)
    assert np.allclose(e, radiance * np.pi * ff, rtol=1e-10)


def test_disk_irradiance_on_its_axis_is_the_closed_form():
    r, h = 0.75, 1.5
    light = area((2 * r, 2 * r), h, shape="ellipse", shadows=False)
    env = Environment(scene([light]))
    e, _ = env.light_irradiance(light, [[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]], [[0.0, 0.0, 1.0]])
    radiance = light.power / (np.pi * np.pi * r * r)
    assert np.allclose(e, radiance * np.pi * r * r / (r * r + h * h), rtol=2e-3)


def test_area_light_lights_nothing_behind_it():
    light = area(h=2.0)
    env = Environment(scene([light]))
    e, _ = env.light_irradiance(light, [[0.0, 0.0, 3.0]], [[0.0, 0.0, 1.0]], [[0.0, 0.0, 1.0]])
    assert np.all(e == 0)


def test_soft_shadow_penumbra_is_monotone_and_soft():
    """A wall edge under a 1 m square light: along a line across its shadow the lit share of
    the irradiance rises from 0 (umbra) to 1 (the unoccluded closed form), within one
    sample's share of noise."""
    light = area((1.0, 1.0), 2.0)
    blocker = quad(1.0, 5.0, "wall", "floor")
    blocker.vertices[:, 0] -= 5.0                    # the half-plane x < 0 at z = 1
    env = Environment(scene([light], meshes=[quad(0.0, 50.0, "floor", "floor"), blocker]))
    x = np.linspace(-1.5, 1.5, 121)
    pts = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    up = np.tile([0.0, 0.0, 1.0], (len(x), 1))
    e = env.light_irradiance(light, pts, up, up)[0][:, 0]
    free = Environment(scene([area((1.0, 1.0), 2.0, shadows=False)]))
    e_free = free.light_irradiance(free.lights[0], pts, up, up)[0][:, 0]
    assert np.all(e[x < -0.6] == 0) and np.allclose(e[x > 0.6], e_free[x > 0.6], rtol=1e-12)
    share = e / e_free
    assert np.all(np.diff(share) >= -1.0 / AREA_SIDE ** 2)
    assert ((share > 0.05) & (share < 0.95)).sum() >= 20    # a penumbra, not a hard edge


def test_rays_see_the_lit_face_of_an_area_light_only():
    light = area((1.0, 1.0), 2.0, power=100.0)
    env = Environment(scene([light], meshes=[quad(-5.0, 1.0, "floor", "floor")]))
    up = env.shade_rays([[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])       # below: the lit face
    down = env.shade_rays([[0.0, 0.0, 4.0]], [[0.0, 0.0, 1.0]])     # above: its back
    aside = env.shade_rays([[2.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    assert np.allclose(up - aside, 100.0 / np.pi, rtol=1e-12)
    assert np.allclose(down, aside)


def test_sharp_metal_reflects_the_sky():
    mats = {"metal": Material("metal", "diffuse", Texture(color=(0.9, 0.7, 0.4)), metallic=1.0,
                              roughness=0.0)}
    env = Environment(scene([], meshes=[quad(0.0, 50.0, "floor", "metal")], materials=mats,
                            world=World(color=tuple(SKY), sky=True)))
    o = np.array([[0.0, 0.0, 1.0]])
    d = np.array([[0.6, 0.0, -0.8]])
    assert np.allclose(env.shade_rays(o, d), np.array([0.9, 0.7, 0.4]) * SKY, rtol=1e-12)


def test_dielectric_layer_reflects_more_at_grazing_angles():
    mats = {"coat": Material("coat", "diffuse", Texture(color=(0.2, 0.2, 0.2)), specular=0.04,
                             roughness=0.0)}
    env = Environment(scene([], meshes=[quad(0.0, 50.0, "floor", "coat")], materials=mats,
                            world=World(color=(1.0, 1.0, 1.0), sky=True)))
    c = np.linspace(1.0, 0.05, 8)
    d = np.column_stack([np.sqrt(1 - c * c), np.zeros_like(c), -c])
    rad = env.shade_rays(d * -1.0, d)[:, 0]
    fresnel = 0.04 + 0.96 * (1 - c) ** 5                 # Schlick, sharp layer
    assert np.allclose(rad, 0.2 * (1 - fresnel) + fresnel, rtol=1e-12)


def test_scene_fields_round_trip_and_old_files_load_unchanged():
    s = build("glass_sphere")
    d = scene_to_dict(s)
    old = scene_from_dict(d)
    assert old.world.sky is False and all(m.metallic == 0 and m.specular == 0
                                          for m in old.materials.values())
    d["lights"].append({"name": "a", "kind": "area", "position": [0, 0, 3],
                        "direction": [0, 0, -2], "axis": [1, 0, 1e-7], "size": [1, 2],
                        "shape": "ellipse", "power": 100})
    d["world"]["sky"] = True
    d["materials"][0].update(metallic=0.5, roughness=0.2, specular=0.04)
    back = scene_from_dict(scene_to_dict(scene_from_dict(d)))
    li = back.lights[-1]
    assert li.kind == "area" and li.direction == (0.0, 0.0, -1.0) and li.axis == (1.0, 0.0, 0.0)
    assert li.size == (1.0, 2.0) and li.area == pytest.approx(np.pi / 2)
    assert back.world.sky is True
    m = back.materials[d["materials"][0]["name"]]
    assert (m.metallic, m.roughness, m.specular) == (0.5, 0.2, 0.04)


@pytest.mark.parametrize("patch,msg", [
    ({"axis": [0, 0.1, 1]}, "lights[0].axis: must be perpendicular to direction"),
    ({"size": [1, 0]}, "lights[0].size[1]: a side must be > 0"),
    ({"shape": "disc"}, "lights[0].shape: unknown shape 'disc'"),
    ({"strength": 3}, "lights[0]: unknown key 'strength'"),
])
def test_bad_area_lights_are_refused_by_field(patch, msg):
    d = scene_to_dict(build("glass_sphere"))
    d["lights"] = [{"name": "a", "kind": "area", **patch}]
    with pytest.raises(SceneError, match=msg.replace("[", r"\[").replace("]", r"\]")):
        scene_from_dict(d)


def test_emission_materials_have_no_glossy_layer():
    d = scene_to_dict(build("glass_sphere"))
    d["materials"].append({"name": "lamp", "kind": "emission", "metallic": 1})
    with pytest.raises(SceneError, match="an 'emission' material has no metallic"):
        scene_from_dict(d)


def test_sampled_terms_ignore_the_last_bits_of_a_point():
    """The same hit found in another batch of rays can differ in its last bits; its sampled
    terms (sky, area light, lobe rays) must not: a pixel changed with the number of render
    processes when the samples' offsets were hashed from a point's raw bits. Points a few ulps
    apart get the same offsets; points a thousandth of a unit apart different ones."""
    from riray.trace.lights import point_offsets
    rng = np.random.default_rng(7)
    p = rng.uniform(-20, 20, (3, 2000))
    # random cell-interior points (the grid step is 2^-24: a few ulps never cross a cell edge
    # but at ~1e-8 of the points, none of these)
    nudged = p + np.abs(p) * rng.choice([-4, -1, 1, 4], p.shape) * np.finfo(float).eps
    assert np.array_equal(point_offsets(p, 3), point_offsets(nudged, 3))
    other = point_offsets(p + 1e-3, 3)
    assert np.mean(np.any(other != point_offsets(p, 3), axis=0)) > 0.99
    # a sky-lit floor under an area light, shaded along the same rays twice, once moved a
    # few ulps: the same colour but for rounding (the sampled terms' noise is ~1e-2)
    blocker = quad(1.0, 0.5, "roof", "floor")          # penumbrae of the sky and the light
    env = Environment(scene([area()], meshes=[quad(0.0, 50.0, "floor", "floor"), blocker],
                            world=World(color=tuple(SKY), sky=True)))
    o, d = down_rays(rng.uniform(-1.5, 1.5, (500, 2)))
    o[:, 2] = 0.5                                        # below the blocker, above the floor
    a = env.shade_rays(o, d)
    b = env.shade_rays(o * (1 + 2 * np.finfo(float).eps), d)
    assert np.abs(a - b).max() < 1e-9
