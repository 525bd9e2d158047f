"""The engine keeps the object's tracer, the loaded tree and the environment between frames
(riray_addon/reuse.py): a camera move reuses all of them, an edited control point rebuilds the
tracer (the tree is then stale), a moved light the environment; every frame equals the same
frame rendered with nothing kept."""

import math

import numpy as np

W, H = 40, 30
FRAMES = (1, 2, 3)
PARTS = {"object", "environment", "tree", "proxy"}


def animated_scene(bl, tmp_path):
    """A mirror NURBS sphere over a floor, a point light, a camera moving over FRAMES; the
    tree baked for the camera's positions over the frame range."""
    bpy = bl.bpy
    scene = bpy.context.scene
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=0.8, location=(0, 0, 0.2))
    obj = bpy.context.active_object
    bpy.ops.mesh.primitive_plane_add(size=8, location=(0, 0, -0.7))
    bpy.ops.object.light_add(type="POINT", location=(2, -2, 3))
    bpy.context.active_object.data.energy = 900.0
    bpy.ops.object.camera_add(rotation=(math.radians(80), 0, 0))
    cam = scene.camera = bpy.context.active_object
    scene.frame_start, scene.frame_end = FRAMES[0], FRAMES[-1]
    for f, x in zip(FRAMES, (-0.3, 0.0, 0.3)):
        cam.location = (x, -5.0, 1.2)
        cam.keyframe_insert("location", frame=f)
    scene.frame_set(FRAMES[0])
    scene.riray.target = obj
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = W, H, 100
    r.filepath = str(tmp_path / "frame_")
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "reuse.blend"))
    assert bpy.ops.riray.bake(object=obj.name, viewpoint_depth=2, direction_depth=3,
                              bake_for_cameras=True) == {"FINISHED"}
    return obj


def render(bl, frame, keep=True):
    """(image, stats) of ``frame`` rendered as a still (``keep``: with the parts kept from
    earlier renders, else with none)."""
    bl.bpy.context.scene.frame_set(frame)
    if not keep:
        bl.engine.reuse.MEMO.clear()
    assert bl.bpy.ops.render.render() == {"FINISHED"}
    last = bl.engine.LAST_RENDER
    return last["image"].copy(), last["stats"]


def test_animation_reuses_tracer_tree_and_environment(bl, tmp_path):
    bpy = bl.bpy
    obj = animated_scene(bl, tmp_path)
    seen = []

    def record(*_args):
        seen.append((bl.engine.LAST_RENDER["image"].copy(), bl.engine.LAST_RENDER["stats"]))

    bpy.app.handlers.render_post.append(record)
    try:
        assert bpy.ops.render.render(animation=True) == {"FINISHED"}
    finally:
        bpy.app.handlers.render_post.remove(record)
    assert [s["frame"] for _, s in seen] == list(FRAMES)
    for image, stats in seen:
        assert stats["mode"] == "tree" and stats["object_pixels"] > 50
        assert set(stats["build_parts_s"]) >= PARTS and stats["export_s"] > 0.0
        assert "solved_along_path" in stats and 0.0 <= stats["solved_fraction"] <= 1.0
    assert not PARTS & set(seen[0][1]["reused"])            # the first frame builds them
    for _, stats in seen[1:]:
        assert set(stats["reused"]) >= PARTS, stats["reused"]
    assert np.abs(seen[0][0] - seen[2][0]).max() > 0.05       # the camera moved
    for f, (image, _) in zip(FRAMES, seen):
        fresh, stats = render(bl, f, keep=False)
        assert stats["reused"] == []
        assert np.allclose(image, fresh, rtol=0.0, atol=1e-9), f

    # a control point moved: the tracer is rebuilt (with the shadow caster), the tree is stale
    points = obj.data.splines[0].points
    front = min(range(len(points)), key=lambda i: points[i].co.y)      # facing the camera
    points[front].co.y -= 0.3
    bpy.context.view_layer.update()
    image, stats = render(bl, 3)
    assert stats["tree"] == "stale" and stats["mode"] == "exact"
    assert "object" not in stats["reused"] and "environment" not in stats["reused"]
    fresh, _ = render(bl, 3, keep=False)
    assert np.allclose(image, fresh, rtol=0.0, atol=1e-9)
    assert np.abs(image - seen[2][0]).max() > 0.05             # the edit shows
    points[front].co.y += 0.3
    bpy.context.view_layer.update()

    # the light moved: only the environment is rebuilt
    render(bl, 3)
    bpy.data.objects["Point"].location.x += 1.0
    bpy.context.view_layer.update()
    image, stats = render(bl, 3)
    assert stats["tree"] == "fresh"
    assert set(stats["reused"]) >= {"object", "tree", "proxy"}
    assert "environment" not in stats["reused"]
    fresh, _ = render(bl, 3, keep=False)
    assert np.allclose(image, fresh, rtol=0.0, atol=1e-9)
    assert np.abs(image - seen[2][0]).max() > 1e-3            # the lighting changed
