"""The "RI-Tree Preview" render engine: stills and a 3-frame animation through
bpy.ops.render.render, checked pixel by pixel against core's own render of the exported scene;
passes; errors are reported, never a silent frame."""

import math

import numpy as np
import pytest

from riray.render.exact import render_exact
from riray.trace.scene_tracer import SceneTracer

W, H = 48, 36          # small frames keep the test quick


def build_scene(bl, tmp_path):
    """A glossy NURBS sphere over a checker floor, a point light, a coloured world."""
    bpy = bl.bpy
    scene = bpy.context.scene
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=0.8, location=(0, 0, 0.2))
    obj = bpy.context.active_object
    mat = bl.compat.new_material("chrome")
    p = mat.node_tree.nodes["Principled BSDF"]
    p.inputs["Metallic"].default_value = 1.0
    p.inputs["Roughness"].default_value = 0.0
    p.inputs["Base Color"].default_value = (0.9, 0.85, 0.8, 1.0)
    obj.data.materials.append(mat)
    bpy.ops.mesh.primitive_plane_add(size=8, location=(0, 0, -0.7))
    floor = bpy.context.active_object
    fm = bl.compat.new_material("floor")
    nt = fm.node_tree
    chk = nt.nodes.new("ShaderNodeTexChecker")
    chk.inputs["Scale"].default_value = 2.0
    uv = nt.nodes.new("ShaderNodeTexCoord")
    nt.links.new(uv.outputs["UV"], chk.inputs["Vector"])
    nt.links.new(chk.outputs["Color"], nt.nodes["Principled BSDF"].inputs["Base Color"])
    floor.data.materials.append(fm)
    # a back wall with an image texture (float pixels, linear)
    bpy.ops.mesh.primitive_plane_add(size=6, location=(0, 3, 1), rotation=(math.radians(90), 0, 0))
    wall = bpy.context.active_object
    img = bpy.data.images.new("wallpaper", 4, 4, float_buffer=True)
    img.pixels.foreach_set(np.random.default_rng(3).uniform(0, 1, 64).astype(np.float32))
    wm = bl.compat.new_material("wall")
    tex = wm.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image = img
    wm.node_tree.links.new(tex.outputs["Color"],
                           wm.node_tree.nodes["Principled BSDF"].inputs["Base Color"])
    wall.data.materials.append(wm)
    bpy.ops.object.light_add(type="POINT", location=(2, -2, 3))
    bpy.context.active_object.data.energy = 900.0
    bpy.ops.object.camera_add(location=(0, -5, 1.2), rotation=(math.radians(80), 0, 0))
    scene.camera = bpy.context.active_object
    world = bl.compat.new_world("w")
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.2, 0.3, 0.5, 1)
    world.riray.ambient = 0.5
    scene.world = world
    scene.riray.target = obj
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = 2 * W, 2 * H, 50
    r.image_settings.file_format = "OPEN_EXR"
    r.image_settings.color_depth = "32"
    r.filepath = str(tmp_path / "still.exr")
    bpy.context.view_layer.update()
    return obj


def baked_scene(bl, tmp_path, blend_name, depths=(3, 4)):
    """build_scene, saved as ``blend_name``, its object's tree baked for the camera at
    viewpoint / direction ``depths`` through the operator."""
    obj = build_scene(bl, tmp_path)
    bl.bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / blend_name))
    assert bl.bpy.ops.riray.bake(object=obj.name, viewpoint_depth=depths[0],
                                 direction_depth=depths[1], bake_for_cameras=True) == {"FINISHED"}
    return obj


def load_exr(bpy, path):
    img = bpy.data.images.load(str(path))
    w, h = img.size
    px = np.empty(w * h * 4, np.float32)
    img.pixels.foreach_get(px)
    bpy.data.images.remove(img)
    return px.reshape(h, w, 4)[::-1, :, :3].astype(np.float64)


def core_reference(bl, obj):
    bpy = bl.bpy
    s = bl.export.export_scene(bpy.context.evaluated_depsgraph_get(), obj, bl.report.Report(),
                               cameras="ACTIVE")
    return render_exact(SceneTracer(s), workers=1).image


def test_still_matches_core(bl, tmp_path):
    bpy = bl.bpy
    obj = build_scene(bl, tmp_path)
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    got = load_exr(bpy, tmp_path / "still.exr")
    assert got.shape == (H, W, 3)
    ref = core_reference(bl, obj)
    assert np.abs(got - ref).max() < 1e-5
    last = bl.engine.LAST_RENDER
    st = last["stats"]
    assert st["object_pixels"] > 50 and st["traced_fraction"] == 1.0 and st["mode"] == "exact"
    assert np.all(last["traced"][last["traced"] > 0] == 1.0)
    assert last["traced"].sum() == st["object_pixels"]
    # the checker floor and the sphere's reflection are there (not a flat frame)
    assert got.std() > 0.05
    # the same scene through the JSON scene file (riray.export_scene -> riray's load_scene)
    path = tmp_path / "scene" / "exported.json"
    assert bpy.ops.riray.export_scene(filepath=str(path), object=obj.name) == {"FINISHED"}
    from riray.scene.io import load_scene
    again = render_exact(SceneTracer(load_scene(path)), workers=1).image
    assert np.abs(again - ref).max() < 1e-12


def test_worker_processes_render_the_same_pixels(bl, tmp_path, monkeypatch):
    """Chunks on two forked worker processes give the in-process frame exactly; the setting's
    automatic value follows the platform."""
    bpy = bl.bpy
    build_scene(bl, tmp_path)
    scene = bpy.context.scene
    monkeypatch.setattr(bl.engine, "share_size", lambda n, procs, per_worker: 300)  # many shares
    calls = []
    real_map = bl.engine.map_chunks

    def recording_map(fn, n, chunk, workers, progress):
        calls.append((n, chunk, workers))
        return real_map(fn, n, chunk, workers, progress)

    monkeypatch.setattr(bl.engine, "map_chunks", recording_map)
    frames = []
    for procs in (1, 2):
        scene.riray.render_processes = procs
        assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
        assert bl.engine.LAST_RENDER["stats"]["processes"] == procs
        n, chunk, workers = calls[-1]
        assert workers == procs and n > 2 * chunk             # the pool really gets chunks
        frames.append(bl.engine.LAST_RENDER["image"].copy())
    assert np.array_equal(frames[0], frames[1]) and frames[0].std() > 0.05
    assert bl.engine.render_processes(3) == 3
    import os
    import sys
    auto = bl.engine.render_processes(0)
    assert auto == (os.cpu_count() if sys.platform.startswith("linux") else 1)


def test_passes_written_to_multilayer_exr(bl, tmp_path):
    bpy = bl.bpy
    build_scene(bl, tmp_path)
    scene = bpy.context.scene
    bpy.context.view_layer.riray.use_pass_angle_error = True
    bl.compat.set_multilayer_exr(scene.render.image_settings)
    scene.render.filepath = str(tmp_path / "layers.exr")
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    head = (tmp_path / "layers.exr").read_bytes()[:20000]
    assert b"Traced" in head and b"Angle Error" in head
    assert np.all(bl.engine.LAST_RENDER["angle"] == 0.0)        # traced exactly


def test_animation_three_frames(bl, tmp_path):
    bpy = bl.bpy
    obj = build_scene(bl, tmp_path)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 3
    for f, x in ((1, -0.6), (3, 0.6)):
        obj.location.x = x
        obj.keyframe_insert("location", frame=f)
    scene.render.filepath = str(tmp_path / "anim_####")
    assert bpy.ops.render.render(animation=True) == {"FINISHED"}
    frames = []
    for f in (1, 2, 3):
        got = load_exr(bpy, tmp_path / f"anim_{f:04d}.exr")
        scene.frame_set(f)
        ref = core_reference(bl, obj)
        assert np.abs(got - ref).max() < 1e-5, f
        frames.append(got)
    assert np.abs(frames[0] - frames[2]).max() > 0.1           # the sphere moved


def test_render_errors_are_reported(bl, tmp_path):
    bpy = bl.bpy
    obj = build_scene(bl, tmp_path)
    scene = bpy.context.scene
    scene.riray.allow_tracing = False
    with pytest.raises(RuntimeError, match="tracing without a tree is switched off"):
        bpy.ops.render.render(write_still=True)
    scene.riray.allow_tracing = True
    scene.riray.target = None
    obj.hide_render = True          # no object with a glass or mirror material is left
    bpy.ops.surface.primitive_nurbs_surface_torus_add(location=(3, 3, 0))
    with pytest.raises(RuntimeError, match="no specular object to render"):
        bpy.ops.render.render(write_still=True)
    bpy.ops.object.text_add()
    txt = bpy.context.active_object
    # a text object cannot be a specular object (poll), an empty mesh marked one gives a report
    me = bpy.data.meshes.new("empty")
    empty = bpy.data.objects.new("empty", me)
    scene.collection.objects.link(empty)
    empty.riray.specular = True
    with pytest.raises(RuntimeError, match="no faces"):
        bpy.ops.render.render(write_still=True)
    empty.riray.specular = False
    obj.hide_render = False
    scene.camera = None
    with pytest.raises(RuntimeError, match="no camera"):
        bpy.ops.render.render(write_still=True)
    assert txt.type == "FONT"


def test_still_through_baked_tree_matches_core(bl, tmp_path):
    """Bake the object's RI-Tree through the operator, render F12 through it: the pixels equal
    core's own interpolated render (render_tree) of the exported scene with the same tree and
    rules, most object pixels are interpolated, and the Traced pass marks exactly the rest."""
    from riray.render.interpolated import render_tree
    from riray.ritree import tree as ritree
    from riray.ritree.query import QueryOptions

    bpy = bl.bpy
    obj = baked_scene(bl, tmp_path, "tree_still.blend")
    path = bl.cache.cache_path(obj)
    # a coarse tree on a strongly curved mirror: the 20 deg pairwise angle rule would trace
    # nearly everything; rays past the tolerance are traced rather than solved, so that the
    # Traced pass has pixels to mark; the rules are render-time options (no re-bake)
    obj.riray.use_angle_threshold = False
    obj.riray.use_solve_paths = False
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    got = load_exr(bpy, tmp_path / "still.exr")
    last = bl.engine.LAST_RENDER
    st = last["stats"]
    s = bl.export.export_scene(bpy.context.evaluated_depsgraph_get(), obj, bl.report.Report(),
                               cameras="ACTIVE")
    opts = QueryOptions(**bl.properties.query_options(obj))
    ref = render_tree(SceneTracer(s), ritree.load(path), options=opts, reference=False, workers=1)
    assert st["mode"] != "exact" and st["object_pixels"] > 50
    assert 0.0 < st["traced_fraction"] < 0.9
    assert np.abs(got - ref.image).max() < 1e-5
    assert np.array_equal(last["traced"].reshape(H, W) > 0, ref.masks["traced"])


def test_camera_outside_the_baked_region_warns(bl, tmp_path, capfd):
    """A frame whose camera left the region the tree was baked for: its object rays enter the
    tree's box in directions the bake never saw (a camera looking along -x, the tree baked for
    one looking along +y), so every one is traced, and the user is warned - a WARNING report,
    which Blender shows (and prints as "Warning:"), naming the camera, the frame and what to
    bake; the status line says it too. At the baked camera nothing is outside, no warning."""
    bpy = bl.bpy
    baked_scene(bl, tmp_path, "outside.blend", depths=(2, 3))
    capfd.readouterr()
    assert bpy.ops.render.render() == {"FINISHED"}
    assert bl.engine.LAST_RENDER["stats"]["outside_fraction"] == 0.0
    assert "outside the region" not in "".join(capfd.readouterr())
    cam = bpy.context.scene.camera
    cam.location, cam.rotation_euler = (5.0, 0.0, 1.2), (math.radians(80), 0.0, math.radians(90))
    assert bpy.ops.render.render() == {"FINISHED"}
    st = bl.engine.LAST_RENDER["stats"]
    assert st["mode"] == "tree" and st["object_pixels"] > 50
    assert st["outside_fraction"] == st["traced_fraction"] == 1.0
    out = "".join(capfd.readouterr())
    assert ("Warning: SurfSphere: 100% of its pixels lie outside the region its RI-Tree was "
            "baked for (camera Camera, frame 1) and were traced exactly: bake again with this "
            "camera in place, or with Bake for scene cameras > Frame range on") in out, out
    assert "| outside the baked region 100.0%" in bl.engine.status_line(st)


def test_damaged_cache_falls_back_to_tracing(bl, tmp_path):
    """A cache whose header reads (so it looks fresh) but whose last array fails its check:
    the render traces the object exactly instead of failing; with tracing without a tree
    switched off it stops, saying why the cache cannot be used."""
    bpy = bl.bpy
    obj = baked_scene(bl, tmp_path, "damaged.blend", depths=(2, 3))
    path = bl.cache.cache_path(obj)
    data = bytearray(open(path, "rb").read())
    data[-200] ^= 0xFF                        # inside the last array, after the header
    open(path, "wb").write(bytes(data))
    assert bl.cache.tree_status(obj, bpy.context.evaluated_depsgraph_get(),
                                memo=False)["state"] == "fresh"
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    assert bl.engine.LAST_RENDER["stats"]["mode"] == "exact"
    bpy.context.scene.riray.allow_tracing = False
    try:
        with pytest.raises(RuntimeError, match="RI-Tree cache cannot be used .*corrupt.*re-bake"):
            bpy.ops.render.render(write_still=True)
    finally:
        bpy.context.scene.riray.allow_tracing = True


def test_max_error_and_path_identity_trace_through_baked_tree(bl, tmp_path):
    """The render-time tolerance (Max error), Path identity and the mirror rules reach core's
    query: with a tolerance far below any error the bake measured and mirror rays from the
    interpolated normal and no path solving, nearly every object pixel is traced (the Traced
    pass and LAST_RENDER agree); with exact mirror hits (the default) most of those are answered
    by Newton instead, and path solving (the default) traces no more; with the tolerance off
    far fewer are traced; path identity only adds traced rays; none of it needs a re-bake."""
    bpy = bl.bpy
    obj = baked_scene(bl, tmp_path, "tree_tolerance.blend")
    p = obj.riray
    p.use_angle_threshold = False
    p.use_solve_paths = False

    def render():
        assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
        last = bl.engine.LAST_RENDER
        st = last["stats"]
        assert st["mode"] == "tree" and st["object_pixels"] > 50
        assert last["traced"].sum() == st["traced_pixels"]
        return st["traced_fraction"]

    # the default is the tolerance (core's DEFAULT_MAX_ERROR_DEG), the angle threshold off
    assert bl.properties.query_options(obj)["max_error_deg"] == pytest.approx(2.0)
    assert bpy.types.Object.bl_rna.properties["riray"].fixed_type.properties[
        "use_angle_threshold"].default is False
    p.use_max_error = False
    assert bl.properties.query_options(obj)["max_error_deg"] is None
    off = render()
    p.use_path_identity = True
    assert bl.properties.query_options(obj)["path_identity"] is True
    path = render()
    p.use_path_identity = False
    assert bl.properties.query_options(obj)["mirror_rays"] == "newton"    # core's default
    p.use_mirror_newton = False
    assert bl.properties.query_options(obj)["mirror_rays"] == "reflect"
    p.use_mirror_normal = False
    assert bl.properties.query_options(obj)["mirror_rays"] == "interpolate"   # the paper's rule
    p.use_mirror_newton = True
    assert bl.properties.query_options(obj)["mirror_rays"] == "interpolate"   # needs the normal
    p.use_mirror_normal = True
    p.use_max_error, p.max_error_deg = True, 1e-4
    assert bl.properties.query_options(obj)["max_error_deg"] == pytest.approx(1e-4)
    tight_newton = render()
    p.use_mirror_newton = False
    tight = render()
    p.use_mirror_newton = True
    assert bl.cache.tree_status(obj, bpy.context.evaluated_depsgraph_get(),
                                memo=False)["state"] == "fresh"       # no re-bake needed
    p.use_solve_paths = True
    tight_solved = render()
    assert off < 0.5 and off <= path            # here 0.11 / 0.11 / 1.0
    assert tight >= 0.98
    assert tight_newton < 0.5                   # here 0.18
    assert tight_solved <= tight_newton         # paths this short are left to the tracer


def exr_attributes(path) -> dict:
    """An OpenEXR file's header attributes, name -> (type, raw bytes): after the magic number
    and version, each is name NUL, type NUL, int32 size, value; an empty name ends the list."""
    import struct
    data = open(path, "rb").read()
    assert data[:4] == b"\x76\x2f\x31\x01"
    pos, out = 8, {}
    while data[pos] != 0:
        fields = []
        for _ in range(2):
            end = data.index(b"\0", pos)
            fields.append(data[pos:end].decode())
            pos = end + 1
        (size,) = struct.unpack_from("<i", data, pos)
        out[fields[0]] = (fields[1], data[pos + 4:pos + 4 + size])
        pos += 4 + size
    return out


def png_text(path) -> dict:
    """The tEXt chunks of a PNG file (keyword -> text), read from its bytes."""
    import struct
    data = open(path, "rb").read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, out = 8, {}
    while pos < len(data):
        (size,) = struct.unpack_from(">I", data, pos)
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + size]
        if kind == b"tEXt":
            key, _, text = body.partition(b"\0")
            out[key.decode("latin-1")] = text
        pos += 12 + size
    return out


def test_saved_images_carry_riray_metadata(bl, tmp_path):
    """The frame's traced fraction and render time ride in the saved file: string attributes
    of an EXR header, text chunks of a PNG (what docs/blender.md promises)."""
    bpy = bl.bpy
    build_scene(bl, tmp_path)
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    attrs = exr_attributes(tmp_path / "still.exr")
    st = bl.engine.LAST_RENDER["stats"]
    assert attrs["riray traced fraction"] == ("string", f"{st['traced_fraction']:.4f}".encode())
    assert attrs["riray render s"] == ("string", f"{st['render_time_s']:.3f}".encode())
    render = bpy.context.scene.render
    render.image_settings.file_format = "PNG"
    render.filepath = str(tmp_path / "still.png")
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    text = png_text(tmp_path / "still.png")
    st = bl.engine.LAST_RENDER["stats"]
    assert text["riray traced fraction"] == f"{st['traced_fraction']:.4f}".encode()
    assert text["riray render s"] == f"{st['render_time_s']:.3f}".encode()


def test_render_region(bl, tmp_path):
    """With a render region only its pixels are rendered: cropped to the region, or in place
    in the full frame (the rest empty); they equal the full frame's pixels there."""
    bpy = bl.bpy
    obj = build_scene(bl, tmp_path)
    ref = core_reference(bl, obj)
    r = bpy.context.scene.render
    r.use_border = True
    r.border_min_x, r.border_max_x, r.border_min_y, r.border_max_y = 0.25, 0.8, 0.1, 0.6
    x0, x1, y0, y1 = int(0.25 * W), int(0.8 * W), int(0.1 * H), int(0.6 * H)
    rows = slice(H - y1, H - y0)                       # top row first
    r.use_crop_to_border = True
    r.filepath = str(tmp_path / "crop.exr")
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    got = load_exr(bpy, tmp_path / "crop.exr")
    assert got.shape == (y1 - y0, x1 - x0, 3)
    assert np.abs(got - ref[rows, x0:x1]).max() < 1e-5
    assert bl.engine.LAST_RENDER["image"].shape == (y1 - y0, x1 - x0, 3)
    r.use_crop_to_border = False
    r.filepath = str(tmp_path / "inplace.exr")
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    got = load_exr(bpy, tmp_path / "inplace.exr")
    assert got.shape == (H, W, 3)
    assert np.abs(got[rows, x0:x1] - ref[rows, x0:x1]).max() < 1e-5
    outside = np.ones((H, W), bool)
    outside[rows, x0:x1] = False
    assert np.all(got[outside] == 0.0)


def test_depth_of_field_is_reported(bl, tmp_path):
    bpy = bl.bpy
    build_scene(bl, tmp_path)
    bpy.context.scene.camera.data.dof.use_dof = True
    reports = []
    engine = type("Engine", (), {"camera_override": None, "update_stats": lambda *a: None,
                                 "report": lambda _, lv, msg: reports.append((set(lv), msg))})()
    bl.engine.RirayRenderEngine._export(engine, bpy.context.evaluated_depsgraph_get())
    assert ({"WARNING"}, "camera Camera: depth of field is not rendered (everything is in "
                         "focus)") in reports


def test_samples_per_pixel_match_core(bl, tmp_path):
    """scene.riray.samples = 4: the engine's frame is core's 4-sample exact render of the
    exported scene (the same stratified rays, the same filter), the Traced pass holds the
    fraction of each pixel's samples traced, and the counts are rays."""
    from riray.scene.camera import Shot
    bpy = bl.bpy
    obj = build_scene(bl, tmp_path)
    bpy.context.scene.riray.samples = 4
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    got = load_exr(bpy, tmp_path / "still.exr")
    s = bl.export.export_scene(bpy.context.evaluated_depsgraph_get(), obj, bl.report.Report(),
                               cameras="ACTIVE")
    ref = render_exact(SceneTracer(s), Shot(samples=4), workers=1)
    assert np.abs(got - ref.image).max() < 1e-5
    assert np.abs(got - core_reference(bl, obj)).max() > 0.05      # not one ray per pixel
    last = bl.engine.LAST_RENDER
    st = last["stats"]
    assert st["samples"] == 4 and st["mode"] == "exact" and st["traced_fraction"] == 1.0
    assert np.isclose(last["traced"].sum() * 4, st["object_pixels"])
    assert np.allclose(last["traced"], ref.masks["object"])
    assert 0 < np.sum((last["traced"] > 0) & (last["traced"] < 1))      # partly covered pixels
