"""Build the sample scenes as .blend files with bpy - the same scenes as core's
``riray.scene.samples.build(name)`` (teapot, vase_mirror, vase_glass, glass_sphere, bowl).

    python sample_scenes/build_blend.py [NAME ...] [--out DIR]          (the bpy module)
    blender -b --python sample_scenes/build_blend.py -- [NAME ...] [--out DIR]   (Blender 4.2+)

Default output: build/sample_scenes/<name>.blend. Each file holds:
- the specular object: one SURFACE object (named after the sample), one NURBS spline per core
  patch, with the order / endpoint / bezier flags whose Blender knot vector equals the patch's
  (up to the parameter scale) - so riray's exporter gives back exactly the core patches - and
  the patch class ids as spline class groups (object.riray.spline_groups);
- its material as nodes: mirror -> Glossy BSDF, glass -> Refraction BSDF, dielectric -> Glass
  BSDF (tint, IOR; highlight settings in material.riray);
- the room: one mesh object per core mesh with UVs, materials as node trees the exporter reads
  back exactly (Diffuse BSDF with constant / Checker / stripes (Checker + Mapping) / gradient
  (Color Ramp <- Map Range <- Separate XYZ <- UV) colours);
- the lamp (point light, zero radius), the sky (Color Ramp on the view direction's Z) with the
  ambient term in world.riray.ambient, the cameras far / close / zoom (scene camera: far), the
  300 x 300 render size, engine RI-Tree Preview when the add-on is enabled, view transform
  Standard, and scene.riray.target = the object.
riray settings are written as ID properties when the add-on is not enabled; Blender adopts them
when it is. Needs numpy and the repository's core (the installed ``riray`` package or, with a
real Blender, core/ loaded from this checkout).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DEFAULT_OUT = ROOT / "build" / "sample_scenes"
SPLINE_RESOLUTION = 4          # evaluated-mesh samples per control point (viewport only)


def import_riray():
    """The installed ``riray`` package, else this checkout's core/ loaded under that name."""
    try:
        import riray  # noqa: F401
    except ImportError:
        core = ROOT / "core"
        spec = importlib.util.spec_from_file_location(
            "riray", core / "__init__.py", submodule_search_locations=[str(core)])
        module = importlib.util.module_from_spec(spec)
        sys.modules["riray"] = module
        spec.loader.exec_module(module)
    return sys.modules["riray"]


import bpy  # noqa: E402  (after the docstring on purpose: the script needs Blender)
import numpy as np  # noqa: E402

import_riray()
from riray.geometry.knots import blender_knots  # noqa: E402
from riray.scene import samples  # noqa: E402


def _load_compat():
    """riray_addon/compat.py (Blender API differences; needs only bpy), loaded from this
    checkout whether or not the add-on is installed."""
    spec = importlib.util.spec_from_file_location("riray_addon_compat",
                                                  ROOT / "riray_addon" / "compat.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


compat = _load_compat()


# --------------------------------------------------------------------------- riray settings
def set_riray(idblock, **values) -> None:
    """Write riray settings: through the registered property group when the add-on is enabled,
    else as the ID properties Blender adopts when it gets enabled."""
    if hasattr(type(idblock), "riray"):
        group = idblock.riray
        for k, v in values.items():
            if k == "spline_groups":
                group.spline_groups.clear()
                for g in v:
                    group.spline_groups.add().group = int(g)
            else:
                setattr(group, k, v)
        return
    group = dict(idblock.get("riray", {}) or {})
    for k, v in values.items():
        group[k] = [{"group": int(g)} for g in v] if k == "spline_groups" else v
    idblock["riray"] = group


# --------------------------------------------------------------------------- NURBS
def blender_flags(knots: np.ndarray, degree: int, count: int) -> tuple[bool, bool]:
    """(endpoint, bezier) flags whose Blender knot vector equals ``knots`` up to an affine
    reparametrization; ValueError if no flags reproduce it."""
    k = np.asarray(knots, dtype=np.float64)
    norm = (k - k[0]) / (k[-1] - k[0])
    for endpoint in (True, False):
        for bezier in (False, True):
            try:
                bk = blender_knots(degree + 1, count, False, endpoint, bezier)
            except ValueError:
                continue
            if len(bk) == len(k) and np.allclose((bk - bk[0]) / (bk[-1] - bk[0]), norm,
                                                 atol=1e-12):
                return endpoint, bezier
    raise ValueError(f"knot vector {k.tolist()} (degree {degree}) has no Blender equivalent")


def add_surface_splines(obj, shapes: list[tuple[int, int]]) -> None:
    """Append one NURBS surface spline of count_u x count_v points per shape. The Python API
    only adds points along u, so each spline starts as a row and is extruded in edit mode, one
    row at a time (only that spline's last row selected)."""
    cu = obj.data
    view_layer = bpy.context.view_layer
    view_layer.objects.active = obj
    obj.select_set(True)
    for nu, nv in shapes:
        sp = cu.splines.new("NURBS")
        sp.points.add(nu - 1)
        idx = len(cu.splines) - 1
        for _ in range(nv - 1):
            for j, other in enumerate(cu.splines):
                n = len(other.points)
                for i, p in enumerate(other.points):
                    p.select = j == idx and i >= n - nu
            bpy.ops.object.mode_set(mode="EDIT")
            bpy.ops.curve.extrude(mode="TRANSLATION")
            bpy.ops.object.mode_set(mode="OBJECT")
        sp = cu.splines[idx]
        if (sp.point_count_u, sp.point_count_v) != (nu, nv):
            raise RuntimeError(f"spline {idx}: built {sp.point_count_u} x {sp.point_count_v} "
                               f"points, wanted {nu} x {nv}")


def surface_object(name: str, patches) -> "bpy.types.Object":
    """A SURFACE object holding every core patch exactly, in world space (identity transform)."""
    cu = bpy.data.curves.new(name, "SURFACE")
    cu.dimensions = "3D"
    obj = bpy.data.objects.new(name, cu)
    bpy.context.scene.collection.objects.link(obj)
    add_surface_splines(obj, [p.surface.points.shape[:2] for p in patches])
    write_splines(obj, patches, reverse_u=False)
    set_riray(obj, spline_groups=[p.class_id for p in patches])
    return obj


def write_splines(obj, patches, reverse_u: bool) -> None:
    """Set each spline's order, knot flags and weighted points from its core patch; with
    ``reverse_u`` the u direction is reversed (the same surface, its normals turned over)."""
    for sp, patch in zip(obj.data.splines, patches):
        s = patch.surface
        nu, nv = s.points.shape[:2]
        ku = s.knots_u[0] + s.knots_u[-1] - s.knots_u[::-1] if reverse_u else s.knots_u
        eu, bu = blender_flags(ku, s.degree_u, nu)
        ev, bv = blender_flags(s.knots_v, s.degree_v, nv)
        sp.order_u, sp.order_v = s.degree_u + 1, s.degree_v + 1
        sp.use_endpoint_u, sp.use_bezier_u, sp.use_cyclic_u = eu, bu, False
        sp.use_endpoint_v, sp.use_bezier_v, sp.use_cyclic_v = ev, bv, False
        sp.resolution_u = sp.resolution_v = SPLINE_RESOLUTION
        sp.use_smooth = True
        co = np.concatenate([s.points, s.weights[..., None]], axis=2)     # [iu, iv, 4]
        co = co[::-1] if reverse_u else co
        sp.points.foreach_set("co", co.transpose(1, 0, 2).ravel())        # u fastest
    obj.data.update_tag()


def signed_volume(obj) -> float:
    """Volume (m^3) enclosed by the object's evaluated (tessellated) surface, signed by its
    normals: negative when they point inwards."""
    dg = bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(dg)
    me = ev.to_mesh()
    me.calc_loop_triangles()
    v = np.empty(len(me.vertices) * 3)
    me.vertices.foreach_get("co", v)
    t = np.empty(len(me.loop_triangles) * 3, np.int64)
    me.loop_triangles.foreach_get("vertices", t)
    ev.to_mesh_clear()
    v, t = v.reshape(-1, 3), t.reshape(-1, 3)
    return float(np.einsum("ij,ij->i", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]])).sum() / 6)


def orient_outwards(obj, patches) -> None:
    """Turn a closed object's normals outwards (Cycles and EEVEE decide entering versus leaving
    glass from them; riray follows the solid and does not care)."""
    bpy.context.view_layer.update()
    if signed_volume(obj) < 0:
        write_splines(obj, patches, reverse_u=True)
        bpy.context.view_layer.update()


# --------------------------------------------------------------------------- materials
def _clear(nt, keep_type: str):
    for n in list(nt.nodes):
        if n.type != keep_type:
            nt.nodes.remove(n)
    return [n for n in nt.nodes if n.type == keep_type][0]


def object_material(om) -> "bpy.types.Material":
    m = compat.new_material(f"riray_{om.kind}")
    nt = m.node_tree
    out = _clear(nt, "OUTPUT_MATERIAL")
    idname = {"mirror": "ShaderNodeBsdfGlossy", "glass": "ShaderNodeBsdfRefraction",
              "dielectric": "ShaderNodeBsdfGlass"}[om.kind]
    node = nt.nodes.new(idname)
    node.inputs["Color"].default_value = (*om.tint, 1.0)
    node.inputs["Roughness"].default_value = 0.0
    if "IOR" in node.inputs:
        node.inputs["IOR"].default_value = om.ior
    nt.links.new(node.outputs[0], out.inputs["Surface"])
    if om.diffuse:
        print(f"warning: object material diffuse={om.diffuse} has no node equivalent here")
    set_riray(m, custom_highlight=True, specular=float(om.specular),
              shininess=float(om.shininess))
    m.diffuse_color = (*om.tint, 1.0)
    return m


def _coords_node(nt, tex):
    tc = nt.nodes.new("ShaderNodeTexCoord")
    return tc.outputs["UV" if tex.coords == "uv" else "Object"]


def _texture_socket(nt, tex):
    """Output socket (or constant RGBA) reproducing a core Texture."""
    if tex.kind == "constant":
        return (*tex.color, 1.0)
    if tex.kind in ("checker", "stripes"):
        chk = nt.nodes.new("ShaderNodeTexChecker")
        chk.inputs["Color1"].default_value = (*tex.color2, 1.0)    # core's parity convention
        chk.inputs["Color2"].default_value = (*tex.color, 1.0)
        chk.inputs["Scale"].default_value = tex.scale
        src = _coords_node(nt, tex)
        if tex.kind == "stripes":
            mp = nt.nodes.new("ShaderNodeMapping")
            sc = [0.0, 0.0, 0.0]
            sc[tex.axis] = 1.0
            mp.inputs["Scale"].default_value = sc
            nt.links.new(src, mp.inputs["Vector"])
            src = mp.outputs["Vector"]
        nt.links.new(src, chk.inputs["Vector"])
        return chk.outputs["Color"]
    if tex.kind == "gradient":
        sep = nt.nodes.new("ShaderNodeSeparateXYZ")
        nt.links.new(_coords_node(nt, tex), sep.inputs[0])
        mr = nt.nodes.new("ShaderNodeMapRange")
        mr.clamp = True
        mr.inputs["From Min"].default_value = tex.start
        mr.inputs["From Max"].default_value = tex.end
        nt.links.new(sep.outputs["XYZ"[tex.axis]], mr.inputs["Value"])
        ramp = nt.nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].color = (*tex.color, 1.0)
        ramp.color_ramp.elements[1].color = (*tex.color2, 1.0)
        nt.links.new(mr.outputs["Result"], ramp.inputs[0])
        return ramp.outputs["Color"]
    if tex.kind == "image":
        node = nt.nodes.new("ShaderNodeTexImage")
        node.image = bpy.data.images.load(tex.path) if tex.path else None
        if tex.scale != 1.0:
            mp = nt.nodes.new("ShaderNodeMapping")
            mp.inputs["Scale"].default_value = (tex.scale,) * 3
            nt.links.new(_coords_node(nt, tex), mp.inputs["Vector"])
            nt.links.new(mp.outputs["Vector"], node.inputs["Vector"])
        return node.outputs["Color"]
    raise ValueError(f"texture kind {tex.kind!r}")


def environment_material(mat) -> "bpy.types.Material":
    m = compat.new_material(mat.name)
    nt = m.node_tree
    out = _clear(nt, "OUTPUT_MATERIAL")
    if mat.kind == "emission":
        node = nt.nodes.new("ShaderNodeEmission")
        node.inputs["Strength"].default_value = mat.strength
    else:
        node = nt.nodes.new("ShaderNodeBsdfDiffuse")
    col = _texture_socket(nt, mat.color)
    if isinstance(col, tuple):
        node.inputs["Color"].default_value = col
        m.diffuse_color = col
    else:
        nt.links.new(col, node.inputs["Color"])
    nt.links.new(node.outputs[0], out.inputs["Surface"])
    return m


# --------------------------------------------------------------------------- environment
def mesh_object(mesh, material) -> "bpy.types.Object":
    me = bpy.data.meshes.new(mesh.name)
    me.from_pydata(mesh.vertices.tolist(), [], mesh.triangles.tolist())
    if mesh.uvs is not None:
        layer = me.uv_layers.new(name="UVMap")
        corner_vertex = np.empty(len(me.loops), dtype=np.int64)
        me.loops.foreach_get("vertex_index", corner_vertex)
        layer.data.foreach_set("uv", mesh.uvs[corner_vertex].ravel())
    me.polygons.foreach_set("use_smooth", [bool(mesh.smooth)] * len(me.polygons))
    me.materials.append(material)
    me.update()
    obj = bpy.data.objects.new(mesh.name, me)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def light_object(light):
    if light.kind == "sun":
        data = bpy.data.lights.new(light.name, "SUN")
        data.energy = light.strength
    else:
        data = bpy.data.lights.new(light.name, "POINT")
        data.energy = light.power
        data.shadow_soft_size = 0.0
    data.color = light.color
    data.use_shadow = bool(light.shadows)
    obj = bpy.data.objects.new(light.name, data)
    bpy.context.scene.collection.objects.link(obj)
    if light.kind == "sun":
        d = -np.asarray(light.direction, dtype=np.float64)          # local +Z = towards the sun
        z = d / np.linalg.norm(d)
        x = np.cross((0.0, 1.0, 0.0) if abs(z[1]) < 0.9 else (1.0, 0.0, 0.0), z)
        x /= np.linalg.norm(x)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2] = x, np.cross(z, x), z
        obj.matrix_world = _matrix(m)
    else:
        obj.location = light.position
    return obj


def _matrix(m):
    from mathutils import Matrix
    return Matrix([list(map(float, row)) for row in m])


def world_block(world):
    w = compat.new_world("riray_world")
    nt = w.node_tree
    bg = [n for n in nt.nodes if n.type == "BACKGROUND"][0]
    bg.inputs["Strength"].default_value = world.strength
    if world.kind == "gradient":
        tc = nt.nodes.new("ShaderNodeTexCoord")
        sep = nt.nodes.new("ShaderNodeSeparateXYZ")
        ramp = nt.nodes.new("ShaderNodeValToRGB")
        nt.links.new(tc.outputs["Generated"], sep.inputs[0])
        nt.links.new(sep.outputs["Z"], ramp.inputs[0])
        ramp.color_ramp.elements[0].color = (*world.color, 1.0)
        ramp.color_ramp.elements[1].color = (*world.zenith, 1.0)
        nt.links.new(ramp.outputs["Color"], bg.inputs["Color"])
    elif world.kind == "image":
        env = nt.nodes.new("ShaderNodeTexEnvironment")
        env.image = bpy.data.images.load(world.path) if world.path else None
        nt.links.new(env.outputs["Color"], bg.inputs["Color"])
    else:
        bg.inputs["Color"].default_value = (*world.color, 1.0)
    w.color = world.color
    set_riray(w, ambient=float(world.ambient))
    return w


def camera_object(cam):
    data = bpy.data.cameras.new(cam.name)
    data.type = "ORTHO" if cam.kind == "orthographic" else "PERSP"
    data.lens = cam.lens
    data.sensor_width, data.sensor_height = cam.sensor_width, cam.sensor_height
    data.sensor_fit = cam.sensor_fit
    data.shift_x, data.shift_y = cam.shift_x, cam.shift_y
    data.ortho_scale = cam.ortho_scale
    data.clip_start, data.clip_end = cam.clip_start, cam.clip_end
    obj = bpy.data.objects.new(cam.name, data)
    bpy.context.scene.collection.objects.link(obj)
    obj.matrix_world = _matrix(cam.matrix_world)
    return obj


# --------------------------------------------------------------------------- scenes
def build_scene(name: str, core_scene=None):
    """Replace the current file's content with sample ``name``; returns the surface object."""
    core_scene = core_scene or samples.build(name)
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.name = name
    obj = surface_object(core_scene.object.name, core_scene.object.patches)
    obj.data.materials.append(object_material(core_scene.object.material))
    if core_scene.object.material.kind != "mirror":
        orient_outwards(obj, core_scene.object.patches)
    mats = {k: environment_material(m) for k, m in core_scene.materials.items()}
    for mesh in core_scene.meshes:
        mesh_object(mesh, mats[mesh.material])
    for light in core_scene.lights:
        light_object(light)
    scene.world = world_block(core_scene.world)
    cams = [camera_object(c) for c in core_scene.cameras]
    scene.camera = cams[0] if cams else None
    r = scene.render
    r.resolution_x, r.resolution_y = core_scene.render.width, core_scene.render.height
    r.resolution_percentage = 100
    if "RIRAY" in {getattr(e, "bl_idname", "") for e in bpy.types.RenderEngine.__subclasses__()}:
        r.engine = "RIRAY"
    scene.view_settings.view_transform = "Standard"
    set_riray(scene, target=obj, max_events=int(core_scene.render.max_events))
    bpy.context.view_layer.objects.active = obj
    bpy.context.view_layer.update()
    return obj


def build_blend(name: str, out_dir: Path) -> Path:
    build_scene(name)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{name}.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), compress=True)
    return path


def script_args(argv: list[str]) -> list[str]:
    """The script's own arguments: those after ``--`` (Blender's convention), else everything
    after the script path when run by plain Python with the bpy module."""
    if "--" in argv:
        return argv[argv.index("--") + 1:]
    binary = bpy.app.binary_path
    if binary and argv and os.path.realpath(argv[0]) == os.path.realpath(binary):
        return []                     # blender -b --python script.py (no "--")
    return argv[1:]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Build the sample scenes as .blend files.")
    ap.add_argument("names", nargs="*", help=f"samples (default: {', '.join(samples.SAMPLES)})")
    ap.add_argument("--out", default=str(DEFAULT_OUT), help=f"output folder ({DEFAULT_OUT})")
    args = ap.parse_args(script_args(sys.argv) if argv is None else argv)
    names = args.names or list(samples.SAMPLES)
    bad = [n for n in names if n not in samples.SAMPLES]
    if bad:
        ap.error(f"unknown sample(s) {bad}; choose from {', '.join(samples.SAMPLES)}")
    for n in names:
        path = build_blend(n, Path(args.out))
        print(f"{n:13s} -> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
