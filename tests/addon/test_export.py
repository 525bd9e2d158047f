"""Export: exact NURBS (knots from Blender's flags) against Blender's own evaluated mesh, mesh
and curve objects, classes, materials, environment, cameras, and clear errors."""

import math

import numpy as np
import pytest

from riray.geometry.nurbs import evaluate
from riray.scene.camera import pixel_rays

TOL = 1e-5          # m: Blender's evaluated mesh is float32


def _add(bpy, prim, **kw):
    getattr(bpy.ops.surface, f"primitive_nurbs_surface_{prim}_add")(**kw)
    return bpy.context.active_object


def _evaluated_world_vertices(bpy, obj):
    dg = bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(dg)
    me = ev.to_mesh()
    co = np.empty(len(me.vertices) * 3)
    me.vertices.foreach_get("co", co)
    ev.to_mesh_clear()
    m = np.array(obj.matrix_world)
    return co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3]


def _exported_samples(bl, obj, so):
    """Core evaluation of the exported (world-space) patches at Blender's sample parameters,
    spline after spline, in the evaluated mesh's vertex order."""
    ex = bl.export
    out = []
    patches = iter(so.patches)
    for sp in obj.data.splines:
        if not ex.spline_is_surface(sp):
            continue
        patch = next(patches)
        u, v = ex.blender_sample_params(sp, patch.surface)
        uu, vv = np.meshgrid(u, v, indexing="ij")
        out.append(evaluate(patch.surface, uu.ravel(), vv.ravel(), derivatives=0)[0])
    return np.concatenate(out)


def _check_against_mesh(bl, obj):
    so = bl.export.export_object(obj, bl.bpy.context.evaluated_depsgraph_get())
    got = _exported_samples(bl, obj, so)
    ref = _evaluated_world_vertices(bl.bpy, obj)
    assert got.shape == ref.shape
    err = np.abs(got - ref).max()
    assert err <= TOL, err
    return so, err


@pytest.mark.parametrize("prim", ["sphere", "torus", "cylinder", "surface"])
def test_primitive_matches_evaluated_mesh(bl, prim):
    obj = _add(bl.bpy, prim, location=(0.5, -1.0, 2.0), rotation=(0.3, -0.2, 0.7),
               scale=(1.5, 0.7, 1.2))
    bl.bpy.context.view_layer.update()
    so, _ = _check_against_mesh(bl, obj)
    assert len(so.patches) == 1 and so.patches[0].class_id == 0


def test_flags_and_orders_match_evaluated_mesh(bl):
    """Every combination of cyclic / endpoint / bezier flags and orders Blender evaluates."""
    bpy = bl.bpy
    obj = _add(bpy, "surface")
    sp = obj.data.splines[0]
    checked = 0
    for order in (2, 3, 4):
        for cyc in (False, True):
            for end in (False, True):
                for bez in (False, True):
                    sp.order_u = sp.order_v = order
                    sp.use_cyclic_u, sp.use_endpoint_u, sp.use_bezier_u = cyc, end, bez
                    sp.use_cyclic_v, sp.use_endpoint_v, sp.use_bezier_v = False, end, bez
                    sp.resolution_u = sp.resolution_v = 3
                    obj.data.update_tag()
                    bpy.context.view_layer.update()
                    ref = _evaluated_world_vertices(bpy, obj)
                    try:
                        so = bl.export.export_object(obj, bpy.context.evaluated_depsgraph_get())
                    except bl.report.ExportError:
                        assert len(ref) == 0, (order, cyc, end, bez)   # Blender refuses too
                        continue
                    got = _exported_samples(bl, obj, so)
                    assert got.shape == ref.shape, (order, cyc, end, bez)
                    assert np.abs(got - ref).max() <= TOL, (order, cyc, end, bez)
                    checked += 1
    assert checked == 21


def test_joined_splines_and_classes(bl):
    bpy = bl.bpy
    a = _add(bpy, "sphere", location=(0, 0, 0))
    b = _add(bpy, "torus", location=(3, 0, 0))
    c = _add(bpy, "cylinder", location=(0, 3, 0))
    for o in (a, b, c):
        o.select_set(True)
    bpy.context.view_layer.objects.active = a
    bpy.ops.object.join()
    obj = bpy.context.active_object
    assert len(obj.data.splines) == 3
    so, _ = _check_against_mesh(bl, obj)
    assert [p.class_id for p in so.patches] == [0, 1, 2]       # each spline its own class
    bpy.ops.riray.spline_groups_sync()
    obj.riray.spline_groups[0].group = 4
    obj.riray.spline_groups[2].group = 4
    so = bl.export.export_object(obj, bpy.context.evaluated_depsgraph_get())
    assert [p.class_id for p in so.patches] == [4, 0, 4]
    # per-material join
    obj.riray.spline_groups.clear()
    m = bpy.data.materials.new("joined")
    m.riray.join_class = True
    obj.data.materials.append(m)
    so = bl.export.export_object(obj, bpy.context.evaluated_depsgraph_get())
    assert len({p.class_id for p in so.patches}) == 1


def test_mesh_classes_split_at_sharp_edges(bl):
    bpy = bl.bpy
    bpy.ops.mesh.primitive_cube_add(size=2.0, location=(1, 2, 3))
    cube = bpy.context.active_object
    so = bl.export.export_object(cube, bpy.context.evaluated_depsgraph_get())
    assert len(so.patches) == 6                     # flat faces: one class each
    assert all(p.is_mesh and len(p.triangles) == 2 for p in so.patches)
    pts = np.concatenate([p.vertices for p in so.patches])
    assert np.allclose(pts.min(0), (0, 1, 2)) and np.allclose(pts.max(0), (2, 3, 4))
    bpy.ops.object.shade_smooth()
    so = bl.export.export_object(cube, bpy.context.evaluated_depsgraph_get())
    assert len(so.patches) == 1                     # smooth and no sharp edges: one class
    me = cube.data
    me.edges.foreach_set("use_edge_sharp", [True] * len(me.edges))
    me.update()
    so = bl.export.export_object(cube, bpy.context.evaluated_depsgraph_get())
    assert len(so.patches) == 6
    for p in so.patches:                            # split at every edge: each face's normal
        if p.normals is None:                       # (Blender: every face shades flat)
            continue
        v = p.vertices[p.triangles]
        face = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        face /= np.linalg.norm(face, axis=1)[:, None]
        assert np.allclose(p.normals, face[:, None, :], atol=1e-6)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_smooth_mesh_exports_world_corner_normals(bl):
    """A smooth UV sphere scaled (1, 1, 3) and rotated: its corner normals are the ellipsoid's
    normals at the corners (the gradient of its implicit form, a truth independent of Blender's
    normals) to the tessellation's error; a flat one has none."""
    bpy = bl.bpy
    bpy.ops.mesh.primitive_uv_sphere_add(segments=64, ring_count=32, location=(1, 2, 3),
                                         rotation=(0.3, 0.0, 0.5))
    ball = bpy.context.active_object
    ball.scale = (1.0, 1.0, 3.0)
    bpy.context.view_layer.update()
    dg = bpy.context.evaluated_depsgraph_get()
    assert bl.export.export_object(ball, dg).patches[0].normals is None
    bpy.ops.object.shade_smooth()
    (p,) = bl.export.export_object(ball, bpy.context.evaluated_depsgraph_get()).patches
    assert p.normals.shape == (len(p.triangles), 3, 3)
    assert np.allclose(np.linalg.norm(p.normals, axis=2), 1.0, atol=1e-9)
    m = np.array(ball.matrix_world)
    local = (p.vertices[p.triangles] - m[:3, 3]) @ np.linalg.inv(m[:3, :3]).T
    grad = local @ np.linalg.inv(m[:3, :3])          # n_world ~ grad(|x_local|^2) M^-1
    cos = np.einsum("ijk,ijk->ij", p.normals, _unit(grad))
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 2.0
    # the corner normals face the way the winding does (outward)
    v = p.vertices[p.triangles]
    face = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    assert (np.einsum("ijk,ik->ij", p.normals, face) > 0).all()


def test_custom_split_normals_are_exported(bl):
    bpy = bl.bpy
    bpy.ops.mesh.primitive_plane_add(size=2.0, rotation=(0.0, 0.5, 0.0))
    plane = bpy.context.active_object
    bpy.ops.object.shade_smooth()
    me = plane.data
    tilt = _unit(np.array([0.3, 0.0, 1.0]))
    me.normals_split_custom_set([tuple(tilt)] * len(me.loops))
    me.update()
    (p,) = bl.export.export_object(plane, bpy.context.evaluated_depsgraph_get()).patches
    want = np.array(plane.matrix_world)[:3, :3] @ tilt      # a rotation: normals turn with it
    assert np.allclose(p.normals, want, atol=1e-4)         # Blender stores them encoded


def test_curve_with_bevel_exports_through_mesh(bl):
    bpy = bl.bpy
    bpy.ops.curve.primitive_bezier_circle_add(radius=1.0)
    curve = bpy.context.active_object
    rep = bl.report.Report()
    with pytest.raises(bl.report.ExportError, match="Extrude, Bevel or Fill"):
        bl.export.export_object(curve, bpy.context.evaluated_depsgraph_get(), rep)
    curve.data.bevel_depth = 0.2
    bpy.context.view_layer.update()
    so = bl.export.export_object(curve, bpy.context.evaluated_depsgraph_get(), rep)
    assert so.patches and all(p.is_mesh for p in so.patches)


def test_bad_objects_give_reports(bl):
    bpy = bl.bpy
    dg = lambda: bpy.context.evaluated_depsgraph_get()   # noqa: E731
    err = bl.report.ExportError
    bpy.ops.object.text_add()
    with pytest.raises(err, match="text objects"):
        bl.export.export_object(bpy.context.active_object, dg())
    bpy.ops.object.empty_add()
    with pytest.raises(err, match="Empty: an empty object has no surface to export"):
        bl.export.export_object(bpy.context.active_object, dg())
    bpy.ops.object.light_add(type="POINT")
    with pytest.raises(err, match="Point: a light object has no surface"):
        bl.export.export_object(bpy.context.active_object, dg())
    me = bpy.data.meshes.new("nofaces")
    me.from_pydata([(0, 0, 0), (1, 0, 0)], [(0, 1)], [])
    o = bpy.data.objects.new("nofaces", me)
    bpy.context.scene.collection.objects.link(o)
    with pytest.raises(err, match="no faces"):
        bl.export.export_object(o, dg())
    # a surface object whose only spline is a curve (one row of points)
    curve_surf = _add(bpy, "curve")
    with pytest.raises(err, match="no NURBS surface splines"):
        bl.export.export_object(curve_surf, dg())
    with pytest.raises(err, match="no object"):
        bl.export.export_object(None, dg())
    # the operator reports instead of raising
    bpy.context.view_layer.objects.active = o
    with pytest.raises(RuntimeError, match="no faces"):
        bpy.ops.riray.bake(object="nofaces")


def test_zero_weight_control_point_is_named(bl):
    """Blender lets a CV's weight be 0; the export names the spline and control point instead
    of reporting that the surface has no surface splines."""
    bpy = bl.bpy
    obj = _add(bpy, "surface")
    obj.name = "Sheet"
    obj.data.splines[0].points[5].co[3] = 0.0
    with pytest.raises(bl.report.ExportError,
                       match=r"Sheet: nothing to export: in spline 0, control point 5 \(u 1, "
                             r"v 1\) has weight 0; NURBS weights must be > 0"):
        bl.export.export_object(obj, bpy.context.evaluated_depsgraph_get())
    # with a valid second spline the bad one is skipped and reported the same way
    joined = _add(bpy, "surface", location=(3, 0, 0))
    obj.select_set(True)
    bpy.context.view_layer.objects.active = joined
    bpy.ops.object.join()
    rep = bl.report.Report()
    so = bl.export.export_object(joined, bpy.context.evaluated_depsgraph_get(), rep)
    assert len(so.patches) == 1
    assert any("control point 5 (u 1, v 1) has weight 0" in m for m in rep.messages("WARNING"))


def _principled(bl, name, **inputs):
    m = bl.compat.new_material(name)
    p = m.node_tree.nodes["Principled BSDF"]
    for k, v in inputs.items():
        p.inputs[k].default_value = v
    return m


def _shader(bl, name, idname, **inputs):
    m = bl.compat.new_material(name)
    nt = m.node_tree
    for n in list(nt.nodes):
        if n.type != "OUTPUT_MATERIAL":
            nt.nodes.remove(n)
    node = nt.nodes.new(idname)
    for k, v in inputs.items():
        node.inputs[k].default_value = v
    nt.links.new(node.outputs[0], nt.nodes["Material Output"].inputs["Surface"])
    return m


def test_object_material_mapping(bl):
    bpy = bl.bpy
    om = bl.materials.object_material
    rep = bl.report.Report()
    m = om(_principled(bl, "metal", **{"Metallic": 1.0, "Roughness": 0.0,
                                         "Base Color": (0.9, 0.8, 0.7, 1)}), rep, "o")
    assert m.kind == "mirror" and np.allclose(m.tint, (0.9, 0.8, 0.7))
    m = om(_principled(bl, "glassy", **{"Transmission Weight": 1.0, "IOR": 1.33,
                                          "Roughness": 0.0}), rep, "o")
    assert m.kind == "dielectric" and m.ior == pytest.approx(1.33)
    assert not rep.messages("WARNING")
    m = om(_shader(bl, "gl", "ShaderNodeBsdfGlossy", Color=(0.5, 0.6, 0.7, 1), Roughness=0.0),
           rep, "o")
    assert m.kind == "mirror" and np.allclose(m.tint, (0.5, 0.6, 0.7))
    m = om(_shader(bl, "rf", "ShaderNodeBsdfRefraction", IOR=1.6, Roughness=0.0), rep, "o")
    assert m.kind == "glass" and m.ior == pytest.approx(1.6)
    m = om(_shader(bl, "gs", "ShaderNodeBsdfGlass", IOR=1.45, Roughness=0.0), rep, "o")
    assert m.kind == "dielectric" and m.ior == pytest.approx(1.45)
    assert not rep.messages("WARNING")
    # approximations are reported by name with what was used instead
    m = om(_principled(bl, "rough plastic", **{"Roughness": 0.4}), rep, "o")
    msgs = " ".join(rep.messages("WARNING"))
    assert m.kind == "mirror" and 0 < m.diffuse < 1
    assert "rough plastic" in msgs and "roughness 0.4 ignored" in msgs
    assert "mirror coat" in msgs
    m = om(_shader(bl, "emit", "ShaderNodeEmission"), rep, "o")
    assert m.kind == "mirror" and "cannot be simulated" in " ".join(rep.messages("WARNING"))
    m = om(None, rep, "obj")
    assert m.kind == "mirror" and "no material" in " ".join(rep.messages())


def test_material_with_nodes_switched_off(bl):
    """Before 5.0 a material or world with Use Nodes off renders with its plain colour."""
    bpy = bl.bpy
    if bpy.app.version >= (5, 0, 0):
        pytest.skip("from 5.0 Blender always uses the node tree")
    m = _principled(bl, "off", **{"Metallic": 1.0, "Base Color": (0.2, 0.4, 0.6, 1)})
    m.diffuse_color = (0.9, 0.1, 0.1, 1)
    m.use_nodes = False
    got = bl.materials.object_material(m, bl.report.Report(), "o")
    assert got.kind == "mirror" and np.allclose(got.tint, (0.9, 0.1, 0.1))
    w = bl.compat.new_world("plain")
    w.node_tree.nodes["Background"].inputs["Color"].default_value = (0.1, 0.2, 0.3, 1)
    w.color = (0.5, 0.5, 0.25)
    w.use_nodes = False
    got = bl.materials.export_world(w, bl.report.Report())
    assert got.kind == "color" and np.allclose(got.color, (0.5, 0.5, 0.25))


def _tex_material(bl, name, build):
    m = bl.compat.new_material(name)
    nt = m.node_tree
    p = nt.nodes["Principled BSDF"]
    build(nt, p.inputs["Base Color"])
    return m


def test_environment_textures(bl):
    bpy = bl.bpy
    em = bl.materials.environment_material
    rep = bl.report.Report()

    def checker(nt, sock):
        t = nt.nodes.new("ShaderNodeTexChecker")
        t.inputs["Scale"].default_value = 4.0
        t.inputs["Color1"].default_value = (1, 0, 0, 1)
        t.inputs["Color2"].default_value = (0, 0, 1, 1)
        uv = nt.nodes.new("ShaderNodeTexCoord")
        nt.links.new(uv.outputs["UV"], t.inputs["Vector"])
        nt.links.new(t.outputs["Color"], sock)

    mat = em(_tex_material(bl, "chk", checker), rep, None)
    assert mat.kind == "diffuse" and mat.color.kind == "checker" and mat.color.coords == "uv"
    assert mat.color.scale == 4.0
    assert mat.color.color == (0, 0, 1) and mat.color.color2 == (1, 0, 0)    # parity swap

    def stripes(nt, sock):
        checker(nt, sock)
        t = [n for n in nt.nodes if n.type == "TEX_CHECKER"][0]
        mp = nt.nodes.new("ShaderNodeMapping")
        mp.inputs["Scale"].default_value = (0.5, 0.0, 0.0)
        uv = [n for n in nt.nodes if n.type == "TEX_COORD"][0]
        nt.links.new(uv.outputs["UV"], mp.inputs["Vector"])
        nt.links.new(mp.outputs["Vector"], t.inputs["Vector"])

    mat = em(_tex_material(bl, "str", stripes), rep, None)
    assert mat.color.kind == "stripes" and mat.color.axis == 0 and mat.color.scale == 2.0

    def gradient(nt, sock):
        ramp = nt.nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].color = (1, 1, 0, 1)
        ramp.color_ramp.elements[1].color = (0, 1, 1, 1)
        mr = nt.nodes.new("ShaderNodeMapRange")
        mr.inputs["From Min"].default_value = 0.0
        mr.inputs["From Max"].default_value = 4.0
        sep = nt.nodes.new("ShaderNodeSeparateXYZ")
        uv = nt.nodes.new("ShaderNodeTexCoord")
        nt.links.new(uv.outputs["UV"], sep.inputs[0])
        nt.links.new(sep.outputs["Y"], mr.inputs["Value"])
        nt.links.new(mr.outputs["Result"], ramp.inputs[0])
        nt.links.new(ramp.outputs["Color"], sock)

    mat = em(_tex_material(bl, "grad", gradient), rep, None)
    t = mat.color
    assert (t.kind, t.axis, t.start, t.end, t.coords) == ("gradient", 1, 0.0, 4.0, "uv")
    assert t.color == (1, 1, 0) and t.color2 == (0, 1, 1)
    assert not rep.messages("WARNING"), rep

    def image(nt, sock):
        img = bpy.data.images.new("px", 4, 2, float_buffer=True)
        img.colorspace_settings.name = "Non-Color"
        img.pixels.foreach_set(np.linspace(0, 1, 32).astype(np.float32))
        t = nt.nodes.new("ShaderNodeTexImage")
        t.image = img
        nt.links.new(t.outputs["Color"], sock)

    mat = em(_tex_material(bl, "img", image), rep, None)
    assert mat.color.kind == "image" and mat.color.image.shape == (2, 4, 3)
    px = np.linspace(0, 1, 32).reshape(2, 4, 4)[::-1, :, :3]          # top row first
    assert np.allclose(mat.color.image, px, atol=1e-6)

    def wave(nt, sock):
        w = nt.nodes.new("ShaderNodeTexWave")
        nt.links.new(w.outputs["Color"], sock)

    mat = em(_tex_material(bl, "wavy", wave), rep, None)
    assert mat.color.kind == "constant"
    assert "'wavy'" in " ".join(rep.messages("WARNING"))
    emis = _shader(bl, "lamp", "ShaderNodeEmission", Strength=3.0)
    mat = em(emis, rep, None)
    assert mat.kind == "emission" and mat.strength == 3.0


def test_environment_lights_world_cameras(bl):
    bpy = bl.bpy
    scene = bpy.context.scene
    obj = _add(bpy, "sphere")
    bpy.ops.mesh.primitive_plane_add(size=4, location=(0, 0, -1.5))
    bpy.ops.object.light_add(type="POINT", location=(1, 2, 3))
    bpy.context.active_object.data.energy = 250.0
    bpy.ops.object.light_add(type="SUN", rotation=(0.0, 0.0, 0.0))
    bpy.ops.object.light_add(type="SPOT", location=(0, 0, 4))
    bpy.ops.mesh.primitive_cube_add(location=(5, 5, 5))
    bpy.context.active_object.hide_render = True
    bpy.ops.object.camera_add(location=(0, -6, 1), rotation=(math.radians(85), 0, 0))
    cam = bpy.context.active_object
    cam.data.shift_x = 0.1
    cam.data.sensor_fit = "VERTICAL"
    scene.camera = cam
    scene.render.resolution_x, scene.render.resolution_y = 64, 48
    scene.render.resolution_percentage = 50
    world = bl.compat.new_world("sky")
    scene.world = world
    nt = world.node_tree
    bg = nt.nodes["Background"]
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    sep = nt.nodes.new("ShaderNodeSeparateXYZ")
    tc = nt.nodes.new("ShaderNodeTexCoord")
    nt.links.new(tc.outputs["Generated"], sep.inputs[0])
    nt.links.new(sep.outputs["Z"], ramp.inputs[0])
    nt.links.new(ramp.outputs["Color"], bg.inputs["Color"])
    ramp.color_ramp.elements[0].color = (0.6, 0.65, 0.7, 1)
    ramp.color_ramp.elements[1].color = (0.25, 0.4, 0.8, 1)
    world.riray.ambient = 0.6
    bpy.context.view_layer.update()
    rep = bl.report.Report()
    s = bl.export.export_scene(bpy.context.evaluated_depsgraph_get(), obj, rep)
    assert [m.name for m in s.meshes] == ["Plane"]              # hidden cube, sphere excluded
    assert s.meshes[0].uvs is not None and len(s.meshes[0].triangles) == 2
    kinds = sorted((li.kind, li.name) for li in s.lights)
    assert [k for k, _ in kinds] == ["point", "point", "sun"]
    point = [li for li in s.lights if li.name == "Point"][0]
    assert point.power == 250.0 and np.allclose(point.position, (1, 2, 3))
    sun = [li for li in s.lights if li.kind == "sun"][0]
    assert np.allclose(sun.direction, (0, 0, -1))
    assert any("spot lights are rendered as point lights" in m for m in rep.messages())
    w = s.world
    assert (w.kind, w.color, w.zenith, w.ambient) == ("gradient", pytest.approx((0.6, 0.65, 0.7)),
                                                      pytest.approx((0.25, 0.4, 0.8)),
                                                      pytest.approx(0.6))
    assert (s.render.width, s.render.height) == (32, 24)
    c = s.cameras[0]
    assert c.name == cam.name and c.sensor_fit == "VERTICAL" and c.shift_x == pytest.approx(0.1)
    # core's camera rays through the frame corners = Blender's view_frame corners
    frame = [np.array(cam.matrix_world @ v) for v in cam.data.view_frame(scene=scene)]
    w_, h_ = s.render.width, s.render.height
    o, d = pixel_rays(c, w_, h_, np.array([w_, w_, 0, 0]), np.array([0, h_, h_, 0]))
    for k in range(4):
        to = frame[k] - o[k]
        assert np.allclose(to / np.linalg.norm(to), d[k], atol=1e-6)


def test_environment_instances_and_excluded_collections(bl):
    bpy = bl.bpy
    scene = bpy.context.scene
    obj = _add(bpy, "sphere")
    coll = bpy.data.collections.new("props")
    scene.collection.children.link(coll)
    me = bpy.data.meshes.new("tri")
    me.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [(0, 1, 2)])
    tri = bpy.data.objects.new("tri", me)
    coll.objects.link(tri)
    inst = bpy.data.objects.new("props_instance", None)
    inst.instance_type = "COLLECTION"
    inst.instance_collection = coll
    inst.location = (10, 0, 0)
    scene.collection.objects.link(inst)
    bpy.context.view_layer.update()
    dg = bpy.context.evaluated_depsgraph_get()
    s = bl.export.export_scene(dg, obj, bl.report.Report(), cameras="NONE")
    got = {m.name: m for m in s.meshes}
    assert set(got) == {"tri", "tri.inst1"}
    xs = sorted(float(m.vertices[:, 0].min()) for m in got.values())
    assert xs == [0.0, 10.0]                       # the instance carries its own matrix
    # an excluded collection is not rendered, so not exported (the instance still is)
    bpy.context.view_layer.layer_collection.children["props"].exclude = True
    bpy.context.view_layer.update()
    s = bl.export.export_scene(bpy.context.evaluated_depsgraph_get(), obj, bl.report.Report(),
                               cameras="NONE")
    assert [float(m.vertices[:, 0].min()) for m in s.meshes] == [10.0]


def test_what_changes_the_image_is_a_warning(bl):
    """Every approximation that changes the image is reported as a warning (Blender shows
    those): a light's radius, a named UV map, image interpolation,
    objects left out of the environment. Light exposure and temperature are rendered."""
    bpy = bl.bpy
    obj = _add(bpy, "sphere")
    bpy.ops.mesh.primitive_uv_sphere_add(location=(3, 0, 0))
    bpy.ops.object.shade_smooth()
    ball = bpy.context.active_object

    def image(nt, sock):
        uv = nt.nodes.new("ShaderNodeUVMap")
        uv.uv_map = "UVMap"
        t = nt.nodes.new("ShaderNodeTexImage")
        t.image = bpy.data.images.new("px", 2, 2)
        t.interpolation = "Closest"
        nt.links.new(uv.outputs["UV"], t.inputs["Vector"])
        nt.links.new(t.outputs["Color"], sock)

    ball.data.materials.append(_tex_material(bl, "tiles", image))
    vol = bpy.data.objects.new("Fog", bpy.data.volumes.new("fog"))
    bpy.context.scene.collection.objects.link(vol)
    bpy.ops.object.light_add(type="POINT", location=(0, 0, 3))
    lamp = bpy.context.active_object.data
    lamp.shadow_soft_size, lamp.energy, lamp.color = 0.2, 100.0, (1.0, 0.5, 0.25)
    has_exposure = hasattr(lamp, "exposure")             # Blender 4.5 and later
    if has_exposure:
        lamp.exposure, lamp.use_temperature, lamp.temperature = 1.0, True, 3000.0
    bpy.context.scene.world = bl.compat.new_world("sky")
    bpy.context.view_layer.update()
    rep = bl.report.Report()
    dg = bpy.context.evaluated_depsgraph_get()
    s = bl.export.export_scene(dg, obj, rep)
    bl.export.export_object(ball, dg, rep)
    # the texture kinds' reading of the material (the node graph reads it exactly)
    bl.materials._fixed_environment_material(ball.data.materials[0], rep, ball, True)
    warnings = " | ".join(rep.messages("WARNING"))
    for text in ("light Point: radius 0.2 m ignored",
                 "UV map 'UVMap': the mesh's active UV map is used",
                 "image interpolation Closest -> linear",
                 "Fog: volume objects are not part of the environment"):
        assert text in warnings, text
    assert not rep.messages("INFO"), rep       # (without a world, Blender renders black too)
    assert "smooth shading" not in warnings   # rendered as Blender shades it
    light = s.lights[0]
    if has_exposure:
        assert light.power == pytest.approx(200.0)
        tint = np.array(lamp.temperature_color[:3])
        assert np.allclose(light.color, np.array([1.0, 0.5, 0.25]) * tint, atol=1e-6)
        assert tint[0] > tint[2]                         # 3000 K is warm
    else:
        assert light.power == pytest.approx(100.0)


def test_area_lights_world_light_and_glossy_layers(bl):
    """An area light is exported as an area (Cycles' frame: the object's X / Y columns times
    Size / Size Y, facing -Z), the world lights the scene, a Principled's metallic, roughness
    and specular layer reach the environment material, and the specular object's highlight
    follows its roughness unless Custom Highlight is on."""
    bpy = bl.bpy
    obj = _add(bpy, "sphere")
    bpy.ops.mesh.primitive_plane_add(size=4, location=(0, 0, -1.5))
    plane = bpy.context.active_object
    plane.data.materials.append(_principled(bl, "metal", **{
        "Metallic": 0.75, "Roughness": 0.3, "IOR": 1.5, "Base Color": (0.9, 0.7, 0.4, 1)}))
    bpy.ops.object.light_add(type="AREA", location=(1, 2, 3), rotation=(math.radians(90), 0, 0))
    lamp = bpy.context.active_object
    lamp.scale = (2.0, 1.0, 1.0)
    lamp.data.energy, lamp.data.shape = 120.0, "RECTANGLE"
    lamp.data.size, lamp.data.size_y = 0.5, 0.25
    bpy.ops.object.light_add(type="AREA", location=(0, 0, 4))
    bpy.context.active_object.data.shape = "DISK"
    bpy.context.scene.world = bl.compat.new_world("w")
    bpy.context.view_layer.update()
    rep = bl.report.Report()
    s = bl.export.export_scene(bpy.context.evaluated_depsgraph_get(), obj, rep)
    rect, disk = sorted((li for li in s.lights), key=lambda li: li.position[2])
    assert (rect.kind, rect.shape, rect.power) == ("area", "rectangle", 120.0)
    assert np.allclose(rect.position, (1, 2, 3)) and np.allclose(rect.size, (1.0, 0.25))
    assert np.allclose(rect.direction, (0, 1, 0), atol=1e-6)       # -Z turned 90 deg about X
    assert np.allclose(rect.axis, (1, 0, 0), atol=1e-6)
    assert (disk.kind, disk.shape) == ("area", "ellipse")
    assert not any("area lights" in m for m in rep.messages())
    assert s.world.sky is True
    m = s.materials["metal"]
    assert (m.metallic, m.roughness) == (pytest.approx(0.75), pytest.approx(0.3))
    assert m.specular == pytest.approx(0.04)
    om = bl.materials.object_material
    sharp = om(_principled(bl, "glass", **{"Transmission Weight": 1.0, "Roughness": 0.0}),
               rep, "o")
    assert sharp.specular == 0.0
    rough = _principled(bl, "rough", **{"Metallic": 1.0, "Roughness": 0.5})
    assert (om(rough, rep, "o").specular, om(rough, rep, "o").shininess) == (1.0, 30.0)
    rough.riray.custom_highlight = True
    rough.riray.specular, rough.riray.shininess = 0.5, 40.0
    assert (om(rough, rep, "o").specular, om(rough, rep, "o").shininess) == (0.5, 40.0)
