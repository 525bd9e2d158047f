"""Several specular objects in Blender: every object with a sharp glass or mirror material (or
marked RI-Tree Object) renders with its own tree, or exactly with a warning naming it; F12's
pixels equal core's render of the exported scene of all of them; baking one object never
changes how the others render; an older file's scene.riray.target still renders."""

import math
import os

import numpy as np
import pytest

from riray.render.exact import render_exact
from riray.render.interpolated import render_tree
from riray.ritree import tree as ritree
from riray.ritree.query import QueryOptions
from riray.trace.scene_tracer import object_tracers

W, H = 48, 36


def _material(bl, name, shader, **inputs):
    mat = bl.compat.new_material(name)
    nt = mat.node_tree
    for node in [n for n in nt.nodes if n.type != "OUTPUT_MATERIAL"]:
        nt.nodes.remove(node)
    node = nt.nodes.new(shader)
    for key, value in inputs.items():
        node.inputs[key].default_value = value
    out = next(n for n in nt.nodes if n.type == "OUTPUT_MATERIAL")
    nt.links.new(node.outputs[0], out.inputs["Surface"])
    return mat


def build_scene(bl, tmp_path):
    """A glass NURBS sphere and a mirror NURBS torus over a plain floor, a point light, a
    camera; saved as a .blend (the caches go beside it). Returns (sphere, torus)."""
    bpy = bl.bpy
    scene = bpy.context.scene
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=0.7, location=(-0.9, 0, 0.2))
    sphere = bpy.context.active_object
    sphere.data.materials.append(_material(bl, "glass", "ShaderNodeBsdfGlass", IOR=1.45,
                                           Roughness=0.0))
    bpy.ops.surface.primitive_nurbs_surface_torus_add(location=(1.0, 0.3, 0.1))
    torus = bpy.context.active_object
    torus.scale = (0.6, 0.6, 0.6)
    torus.data.materials.append(_material(bl, "mirror", "ShaderNodeBsdfGlossy", Roughness=0.0,
                                          Color=(0.9, 0.8, 0.7, 1.0)))
    bpy.ops.mesh.primitive_plane_add(size=8, location=(0, 0, -0.6))
    bpy.ops.object.light_add(type="POINT", location=(2, -2, 3))
    bpy.context.active_object.data.energy = 900.0
    bpy.ops.object.camera_add(location=(0, -5, 1.4), rotation=(math.radians(78), 0, 0))
    scene.camera = bpy.context.active_object
    world = bl.compat.new_world("w")
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.2, 0.3, 0.5, 1)
    world.riray.ambient = 0.5
    scene.world = world
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = 2 * W, 2 * H, 50
    bpy.context.view_layer.update()
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "two.blend"))
    return sphere, torus


def _exported(bl, objs):
    return bl.export.export_scene(bl.bpy.context.evaluated_depsgraph_get(), objs,
                                  bl.report.Report(), cameras="ACTIVE")


def _bake(bl, obj):
    assert bl.bpy.ops.riray.bake(object=obj.name, viewpoint_depth=2, direction_depth=3,
                                 bake_for_cameras=True) == {"FINISHED"}


def test_specular_objects_by_material_mark_and_older_target(bl, tmp_path):
    """Sharp glass and mirror materials make an object specular, a rough metal or a plain
    surface does not unless marked; an older file's scene.riray.target is one too."""
    bpy = bl.bpy
    sphere, torus = build_scene(bl, tmp_path)

    def names():
        return [o.name for o in bl.export.specular_objects(bpy.context.evaluated_depsgraph_get())]
    assert names() == ["SurfSphere", "SurfTorus"]
    torus.data.materials[0] = _material(bl, "brushed", "ShaderNodeBsdfPrincipled",
                                        Metallic=1.0, Roughness=0.4)
    assert names() == ["SurfSphere"]
    torus.riray.specular = True
    assert names() == ["SurfSphere", "SurfTorus"]
    torus.riray.specular = False
    bpy.context.scene.riray.target = torus
    assert names() == ["SurfSphere", "SurfTorus"]
    sphere.hide_render = True
    assert names() == ["SurfTorus"]


def test_every_object_renders_exactly_with_a_warning_each(bl, tmp_path, capfd):
    """Without trees F12 traces both objects, warns about each by name, and its pixels are
    core's exact render of the scene of both."""
    bpy = bl.bpy
    sphere, torus = build_scene(bl, tmp_path)
    capfd.readouterr()
    assert bpy.ops.render.render() == {"FINISHED"}
    out = "".join(capfd.readouterr())
    for obj in (sphere, torus):
        assert f"Warning: {obj.name}: " in out and "traced exactly" in out, out
    last = bl.engine.LAST_RENDER
    st = last["stats"]
    assert st["mode"] == "exact" and set(st["objects"]) == {sphere.name, torus.name}
    assert all(o["object_pixels"] > 30 for o in st["objects"].values())
    assert st["object_pixels"] == sum(o["object_pixels"] for o in st["objects"].values())
    sts = object_tracers(_exported(bl, [sphere, torus]))
    ref = render_exact(sts[0], workers=1, others=sts[1:]).image
    assert np.abs(last["image"] - ref).max() < 1e-5


def test_baking_one_object_leaves_the_others(bl, tmp_path, capfd, monkeypatch):
    """Baking the sphere renders it through its tree and the torus still exactly (pixels equal
    core's render_tree of both with the sphere's tree); baking the torus then renders both
    through their trees, the sphere's tree untouched."""
    bpy = bl.bpy
    sphere, torus = build_scene(bl, tmp_path)
    _bake(bl, sphere)
    assert sphere.riray.specular and not torus.riray.specular
    # the frame as one share, as core's render_tree below cuts it: a tree query's answers may
    # depend on which rays share its batch
    bpy.context.scene.riray.render_processes = 1
    monkeypatch.setattr(bl.engine, "SHARES_PER_WORKER", 1)
    capfd.readouterr()
    assert bpy.ops.render.render() == {"FINISHED"}
    out = "".join(capfd.readouterr())
    assert f"Warning: {torus.name}: " in out and f"Warning: {sphere.name}: " not in out, out
    st = bl.engine.LAST_RENDER["stats"]
    assert st["objects"][sphere.name]["mode"] == "tree"
    assert st["objects"][torus.name]["mode"] == "exact" and st["mode"] == "mixed"
    path = bl.cache.cache_path(sphere)
    sts = object_tracers(_exported(bl, [sphere, torus]))
    opts = QueryOptions(**bl.properties.query_options(sphere))
    ref = render_tree(sts[0], ritree.load(path), options=opts, reference=False, workers=1,
                      others=[(sts[1], None)])
    assert np.abs(bl.engine.LAST_RENDER["image"] - ref.image).max() < 1e-5
    before = os.stat(path)
    _bake(bl, torus)
    assert bpy.ops.render.render() == {"FINISHED"}
    st = bl.engine.LAST_RENDER["stats"]
    assert {n: o["mode"] for n, o in st["objects"].items()} == {sphere.name: "tree",
                                                               torus.name: "tree"}
    after = os.stat(path)
    assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns)
    assert bl.cache.cache_path(torus) != path


@pytest.mark.parametrize("allow", [False])
def test_no_tree_and_tracing_off_names_the_object(bl, tmp_path, allow):
    bpy = bl.bpy
    sphere, torus = build_scene(bl, tmp_path)
    _bake(bl, sphere)
    bpy.context.scene.riray.allow_tracing = allow
    with pytest.raises(RuntimeError, match=f"{torus.name}: .*tracing without a tree is "
                                           "switched off"):
        bpy.ops.render.render()
