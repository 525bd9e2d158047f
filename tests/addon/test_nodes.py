"""Shader node graphs of environment surfaces and the world, rendered by Cycles and by the
RI-Tree Preview engine: they agree per pixel.

Every case builds one small node graph: the colour of an emission room (a rotated, scaled cube
seen from inside, so object and generated coordinates differ from world ones, with a second
box sharing the material), or the world's background. A flat NURBS mirror shows the room or sky
from other directions. Cycles renders at 1 sample per pixel with a 0.01 px box filter, with
light sampling off (emission-only surfaces, a sharp mirror: Cycles' path is then exactly a
Whitted tracer's); the RI-Tree Preview engine traces exactly. They must agree to AGREE at every
pixel away from edges (pixels whose colour jumps near the pixel centre, found by rendering the
exported scene with the camera moved by +-PROBE_PX), up to what Cycles' sample offset from
the pixel centre (measured once, ``cycles_offset``) changes a colour of the slope found there.
"""

import dataclasses
import math

import numpy as np
import pytest

from riray.render.exact import render_exact
from riray.scene.camera import Shot
from riray.trace.scene_tracer import SceneTracer

W, H = 32, 24
AGREE = 1e-3        # per pixel: |Cycles - riray| <= AGREE * max(1, |riray|) (Cycles is float32)
# Cycles' box filter of width 0.01 px keeps every sample within FILTER_PX of the pixel centre
# (per axis); the offset actually used is measured (cycles_offset) and, times OFFSET_MARGIN,
# sets how much a colour's slope may move it.
FILTER_PX = 0.005
OFFSET_MARGIN = 2.0
# The exported scene is also rendered with the camera moved by +-PROBE_PX along x and y: a
# pixel is an edge (not compared) where that shows a discontinuity (second difference above
# AGREE / 2). PROBE_PX is 3x the filter's half width: every jump a sample can cross shows.
PROBE_PX = 0.015
MIN_CHECKED = 0.5   # at least half of the pixels must be compared (not edges)
ROOM_SCALE = (3.0, 4.0, 1.6)


# --------------------------------------------------------------------------- graph building
class G:
    """A node tree with helpers: ``node(idname, inputs, **attrs)`` sets inputs by identifier
    (sockets are linked, values set), ``out(node, identifier)``."""

    def __init__(self, bl, nt, tmp_path=None):
        self.bl, self.nt, self.tmp_path = bl, nt, tmp_path
        self._pos = None

    def node(self, idname, inputs=None, **attrs):
        n = self.nt.nodes.new(idname)
        for k, v in attrs.items():
            setattr(n, k, v)
        for ident, v in (inputs or {}).items():
            sock = next(s for s in n.inputs if s.identifier == ident)
            if hasattr(v, "is_output"):
                self.nt.links.new(v, sock)
            else:
                sock.default_value = v
        return n

    @staticmethod
    def out(node, ident=None):
        return node.outputs[0] if ident is None else next(s for s in node.outputs
                                                          if s.identifier == ident)

    def pos(self):
        if self._pos is None:
            self._pos = self.out(self.node("ShaderNodeNewGeometry"), "Position")
        return self._pos

    def vec(self, scale=(0.35, 0.3, 0.25), offset=(0.1, -0.05, 0.02), src=None):
        """src (default: the position) * scale + offset."""
        return self.out(self.node("ShaderNodeVectorMath", {
            "Vector": src or self.pos(), "Vector_001": scale, "Vector_002": offset},
            operation="MULTIPLY_ADD"), "Vector")

    def abc(self):
        """Three float sockets varying over the room: 0.35 x + 0.1, 0.3 y - 0.05, 0.25 z + 0.02."""
        sep = self.node("ShaderNodeSeparateXYZ", {"Vector": self.vec()})
        return self.out(sep, "X"), self.out(sep, "Y"), self.out(sep, "Z")

    def rgb(self, r, g, b):
        return self.out(self.node("ShaderNodeCombineXYZ", {"X": r, "Y": g, "Z": b}))

    def image(self, name, w, h, seed, png_dir=None):
        """A w x h image of random colours: float pixels (linear), or an 8-bit sRGB PNG file
        saved in ``png_dir`` and loaded back (how users' images arrive)."""
        bpy = self.bl.bpy
        img = bpy.data.images.new(name, w, h, float_buffer=png_dir is None)
        px = np.random.default_rng(seed).uniform(0.05, 1.0, w * h * 4)
        px[3::4] = 1.0
        img.pixels.foreach_set(px.astype(np.float32))
        if png_dir is None:
            return img
        img.filepath_raw = str(png_dir / f"{name}.png")
        img.file_format = "PNG"
        img.save()
        bpy.data.images.remove(img)
        return bpy.data.images.load(str(png_dir / f"{name}.png"))


def emission_material(bl, name, build, tmp_path):
    """A material emitting ``build(G)`` (a colour socket) with strength 1, or the shader
    ``build`` returns when it returns a shader socket."""
    mat = bl.compat.new_material(name)
    nt = mat.node_tree
    for n in list(nt.nodes):
        if n.type != "OUTPUT_MATERIAL":
            nt.nodes.remove(n)
    g = G(bl, nt, tmp_path)
    sock = build(g)
    if sock.type != "SHADER":
        sock = g.out(g.node("ShaderNodeEmission", {"Color": sock, "Strength": 1.0}))
    nt.links.new(sock, nt.nodes["Material Output"].inputs["Surface"])
    mat.cycles.emission_sampling = "NONE"
    return mat


def build_scene(bl, tmp_path, room=None, world=None):
    """Camera, a flat NURBS mirror, the room (``room(G)``: its colour or shader) and the world
    (``world(G)``: the background's colour or shader; black when None). Returns the mirror."""
    bpy = bl.bpy
    scene = bpy.context.scene
    if room is not None:
        mat = emission_material(bl, "room", room, tmp_path)
        bpy.ops.mesh.primitive_cube_add(size=2, location=(0.3, 0.2, 1.4), rotation=(0, 0, 0.3))
        cube = bpy.context.active_object
        cube.name = "Room"
        cube.scale = ROOM_SCALE
        cube.color = (0.2, 0.5, 0.7, 0.6)
        cube.pass_index = 3
        mat.pass_index = 5
        cube.data.materials.append(mat)
        bpy.ops.mesh.primitive_cube_add(size=0.5, location=(-1.2, 1.8, 0.6),
                                        rotation=(0.2, 0.4, -0.5))
        box = bpy.context.active_object
        box.name = "Box"
        box.data.materials.append(mat)
        for o in (cube, box):       # diffuse closures see nothing, as in riray without lights
            o.visible_diffuse = False
    bpy.ops.surface.primitive_nurbs_surface_surface_add(
        radius=0.8, location=(0.4, 0.6, 1.0), rotation=(math.radians(65), 0.0, math.radians(25)))
    mirror = bpy.context.active_object
    mirror.name = "Mirror"
    for sp in mirror.data.splines:          # flat: Cycles' tessellation is then exact
        co = np.empty(len(sp.points) * 4)
        sp.points.foreach_get("co", co)
        co = co.reshape(-1, 4)
        co[:, 2], co[:, 3] = 0.0, 1.0
        sp.points.foreach_set("co", co.ravel())
    mm = bl.compat.new_material("mirror")
    nt = mm.node_tree
    glossy = nt.nodes.new("ShaderNodeBsdfGlossy")
    glossy.inputs["Roughness"].default_value = 0.0
    glossy.inputs["Color"].default_value = (1, 1, 1, 1)
    nt.links.new(glossy.outputs[0], nt.nodes["Material Output"].inputs["Surface"])
    mirror.data.materials.append(mm)
    cam_rot = (math.radians(85), 0, 0) if room is not None else (math.radians(70), 0, 0.3)
    bpy.ops.object.camera_add(location=(0.0, -2.5, 1.3), rotation=cam_rot)
    scene.camera = bpy.context.active_object
    scene.camera.data.lens = 24 if room is not None else 16
    w = bl.compat.new_world("world")
    wt = w.node_tree
    bg = wt.nodes["Background"]
    bg.inputs["Color"].default_value = (0, 0, 0, 1)
    if world is not None:
        g = G(bl, wt, tmp_path)
        sock = world(g)
        if sock.type == "SHADER":
            wt.links.new(sock, wt.nodes["World Output"].inputs["Surface"])
        else:
            wt.links.new(sock, bg.inputs["Color"])
    w.cycles.sampling_method = "NONE"
    scene.world = w
    scene.riray.target = mirror
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = W, H, 100
    r.image_settings.file_format = "OPEN_EXR"
    r.image_settings.color_depth = "32"
    r.threads_mode, r.threads = "FIXED", 1
    c = scene.cycles
    c.device, c.samples, c.seed = "CPU", 1, 1
    c.use_adaptive_sampling = c.use_denoising = False
    c.pixel_filter_type, c.filter_width = "BOX", 0.01
    c.max_bounces = c.glossy_bounces = c.transmission_bounces = 8
    c.diffuse_bounces = c.volume_bounces = 0
    c.sample_clamp_direct = c.sample_clamp_indirect = 0.0
    bpy.context.view_layer.update()
    return mirror


def render(bl, engine, path):
    bpy = bl.bpy
    scene = bpy.context.scene
    scene.render.engine = engine
    scene.render.filepath = str(path)
    assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    img = bpy.data.images.load(str(path))
    px = np.empty(W * H * 4, np.float32)
    img.pixels.foreach_get(px)
    bpy.data.images.remove(img)
    return px.reshape(H, W, 4)[::-1, :, :3].astype(np.float64)


def edges_and_slack(scene, base, offset_px):
    """((H, W) bool edge pixels, (H, W) colour change a sample ``offset_px`` pixels from the
    centre can cause there) from renders with the camera moved by +-PROBE_PX (its shift is in
    units of the larger frame side); both relative to max(1, |colour|)."""
    cam = scene.cameras[0]
    step = PROBE_PX / max(W, H)
    scale = np.maximum(1.0, np.abs(base))
    edge, slack = np.zeros((H, W), bool), np.zeros((H, W))
    for dx, dy in ((step, 0), (0, step)):
        pair = []
        for sign in (1, -1):
            scene.cameras[0] = dataclasses.replace(cam, shift_x=cam.shift_x + sign * dx,
                                                   shift_y=cam.shift_y + sign * dy)
            pair.append(render_exact(SceneTracer(scene), Shot(width=W, height=H), workers=1).image)
        edge |= (np.abs(pair[0] + pair[1] - 2 * base) / scale).max(axis=2) > AGREE / 2
        slope = np.maximum(np.abs(pair[0] - base), np.abs(pair[1] - base)) / PROBE_PX / scale
        slack += slope.max(axis=2) * offset_px
    scene.cameras[0] = cam
    return edge, slack


@pytest.fixture(scope="session")
def cycles_offset(blender, tmp_path_factory):
    """How far (pixels, per axis) Cycles' sample lies from the pixel centre in these renders,
    measured on a background showing the incoming direction (which gives the sample's position
    in the image plane), times OFFSET_MARGIN; within the box filter's half width."""
    from riray.scene.camera import camera_rays
    bl = blender
    bl.reset()
    tmp = tmp_path_factory.mktemp("offset")
    mirror = build_scene(bl, tmp, world=lambda g: g.out(g.node("ShaderNodeNewGeometry"),
                                                        "Incoming"))
    mirror.hide_render = True
    cyc = render(bl, "CYCLES", tmp / "offset.exr")
    scene = bl.export.export_scene(bl.bpy.context.evaluated_depsgraph_get(), mirror,
                                   bl.report.Report(), cameras="ACTIVE")
    cam = scene.cameras[0]
    rot = np.asarray(cam.matrix_world)[:3, :3]
    plane = lambda d: (d @ rot)[:, :2] / -(d @ rot)[:, 2:]     # noqa: E731  (image plane)
    centre = plane(camera_rays(cam, W, H)[1])
    pixel = np.abs(centre[1, 0] - centre[0, 0])
    off = np.abs(plane(-cyc.reshape(-1, 3)) - centre).max() / pixel
    assert off <= FILTER_PX
    bl.reset()
    return OFFSET_MARGIN * off


def compare(bl, tmp_path, offset_px, room=None, world=None, min_std=0.02):
    """Render with Cycles and the RI-Tree Preview engine; check they agree away from edges.
    Returns (exported core scene, riray image, report)."""
    bpy = bl.bpy
    mirror = build_scene(bl, tmp_path, room, world)
    cyc = render(bl, "CYCLES", tmp_path / "cycles.exr")
    got = render(bl, "RIRAY", tmp_path / "riray.exr")
    rep = bl.report.Report()
    scene = bl.export.export_scene(bpy.context.evaluated_depsgraph_get(), mirror, rep,
                                   cameras="ACTIVE")
    base = render_exact(SceneTracer(scene), Shot(width=W, height=H), workers=1).image
    # the engine renders the exported scene (EXR float32)
    assert (np.abs(base - got) / np.maximum(1.0, np.abs(base))).max() < 1e-6
    edge, slack = edges_and_slack(scene, base, offset_px)
    ok = ~edge
    assert ok.mean() >= MIN_CHECKED, f"only {ok.mean():.0%} of the pixels are not edges"
    assert got[ok].std() > min_std, "the case shows (almost) nothing"
    err = (np.abs(cyc - got) / np.maximum(1.0, np.abs(got))).max(axis=2) - slack
    worst = np.unravel_index(np.argmax(np.where(ok, err, -np.inf)), err.shape)
    assert err[ok].max() <= AGREE, (f"{err[ok].max():.3g} beyond the slack "
                                    f"{slack[worst]:.3g} at {worst}: cycles {cyc[worst]}, "
                                    f"riray {got[worst]}")
    return scene, got, rep


# --------------------------------------------------------------------------- cases
def _tex_coord(output, **attrs):
    return lambda g: g.out(g.node("ShaderNodeTexCoord", **attrs), output)


def _tex_coord_other_object(output):
    """Object coordinates of another object (the node's Object field): an empty."""
    def build(g):
        bpy = g.bl.bpy
        empty = bpy.data.objects.new("Frame", None)
        bpy.context.scene.collection.objects.link(empty)
        empty.location, empty.rotation_euler, empty.scale = (0.5, -1, 2), (0.3, 0.2, 1.0), \
            (1.5, 0.8, 2.0)
        return g.out(g.node("ShaderNodeTexCoord", object=empty), output)
    return build


def _geometry(output):
    return lambda g: g.out(g.node("ShaderNodeNewGeometry"), output)


def _object_info(g):
    info = g.node("ShaderNodeObjectInfo")
    o = lambda k: g.out(info, k)    # noqa: E731
    loc = g.out(g.node("ShaderNodeVectorMath", {"Vector": o("Location"), "Scale": 0.3},
                       operation="SCALE"), "Vector")
    idx = g.out(g.node("ShaderNodeMath", {"Value": o("Object Index"), "Value_001": 0.1},
                       operation="MULTIPLY"))
    mi = g.out(g.node("ShaderNodeMath", {"Value": o("Material Index"), "Value_001": 0.1},
                      operation="MULTIPLY"))
    mix = g.node("ShaderNodeMix", {"Factor_Float": o("Random"), "A_Color": o("Color"),
                                   "B_Color": g.rgb(o("Alpha"), idx, mi)}, data_type="RGBA")
    return g.out(g.node("ShaderNodeVectorMath", {"Vector": g.out(mix, "Result_Color"),
                                                 "Vector_001": loc}, operation="ADD"), "Vector")


def _mapping(kind):
    return lambda g: g.out(g.node("ShaderNodeMapping", {
        "Vector": g.vec(), "Location": (0.3, -0.2, 0.5), "Rotation": (0.4, -0.7, 1.1),
        "Scale": (1.3, 0.6, -0.8)}, vector_type=kind))


def _xyz(g):
    sep = g.node("ShaderNodeSeparateXYZ", {"Vector": g.vec()})
    return g.rgb(g.out(sep, "Z"), g.out(sep, "X"), g.out(sep, "Y"))


def _color_sep_comb(g):
    sep = g.node("ShaderNodeSeparateColor", {"Color": g.vec()})
    return g.out(g.node("ShaderNodeCombineColor", {"Red": g.out(sep, "Blue"),
                                                   "Green": g.out(sep, "Red"),
                                                   "Blue": g.out(sep, "Green")}))


MATH_INPUTS = {"logarithm": "ac", "arctan2": "ab", "compare": "abc"}
MATH_OPS = ["ADD", "SUBTRACT", "MULTIPLY", "DIVIDE", "MULTIPLY_ADD", "POWER", "LOGARITHM",
            "SQRT", "INVERSE_SQRT", "ABSOLUTE", "EXPONENT", "MINIMUM", "MAXIMUM", "LESS_THAN",
            "GREATER_THAN", "SIGN", "COMPARE", "SMOOTH_MIN", "SMOOTH_MAX", "ROUND", "FLOOR",
            "CEIL", "TRUNC", "FRACT", "MODULO", "FLOORED_MODULO", "WRAP", "SNAP", "PINGPONG",
            "SINE", "COSINE", "TANGENT", "ARCSINE", "ARCCOSINE", "ARCTANGENT", "ARCTAN2", "SINH",
            "COSH", "TANH", "RADIANS", "DEGREES"]


def _math(ops, clamp=False):
    """Three Math operations on (a, b, c) as the red, green and blue of the colour."""
    def build(g):
        a, b, c = g.abc()
        args = {"a": a, "b": b, "c": c}
        chans = []
        for op in ops:
            names = MATH_INPUTS.get(op.lower(), "abc")
            ins = dict(zip(("Value", "Value_001", "Value_002"), (args[k] for k in names)))
            chans.append(g.out(g.node("ShaderNodeMath", ins, operation=op, use_clamp=clamp)))
        chans += [chans[-1]] * (3 - len(chans))
        return g.rgb(*chans)
    return build


VECTOR_OPS = ["ADD", "SUBTRACT", "MULTIPLY", "DIVIDE", "MULTIPLY_ADD", "CROSS_PRODUCT",
              "PROJECT", "REFLECT", "REFRACT", "FACEFORWARD", "SCALE", "NORMALIZE", "ABSOLUTE",
              "POWER", "SIGN", "MINIMUM", "MAXIMUM", "FLOOR", "CEIL", "FRACTION", "MODULO",
              "WRAP", "SNAP", "SINE", "COSINE", "TANGENT"]
VALUE_OPS = ["DOT_PRODUCT", "DISTANCE", "LENGTH"]


def _vector_math(op):
    def build(g):
        a = g.vec()
        b = g.vec(scale=(-0.1, 0.12, 0.1), offset=(0.6, 0.7, -0.5))   # |b| >= 0.17
        c = g.vec(scale=(0.25, 0.1, -0.3), offset=(-0.1, 0.35, 0.2))
        s = g.abc()[2]
        n = g.node("ShaderNodeVectorMath", {"Vector": a, "Vector_001": b, "Vector_002": c,
                                            "Scale": s}, operation=op)
        if op in VALUE_OPS:
            return g.rgb(g.out(n, "Value"), g.out(n, "Value"), g.out(n, "Value"))
        return g.out(n, "Vector")
    return build


def _map_range(interps, clamp, vector=False):
    def build(g):
        a, b, c = g.abc()
        if vector:
            return g.out(g.node("ShaderNodeMapRange", {
                "Vector": g.vec(), "From_Min_FLOAT3": (-0.5, 0.6, 0.1),
                "From_Max_FLOAT3": (0.9, -0.4, 0.6), "To_Min_FLOAT3": (0.1, 0.0, 0.9),
                "To_Max_FLOAT3": (0.8, 1.2, 0.2), "Steps_FLOAT3": (3.0, 4.0, 2.0)},
                data_type="FLOAT_VECTOR", interpolation_type=interps[0], clamp=clamp), "Vector")
        chans = []
        for k, (interp, src) in enumerate(zip(interps, (a, b, c))):
            lo, hi = (0.8, -0.6) if k == 1 else (-0.6, 0.8)     # one reversed range
            chans.append(g.out(g.node("ShaderNodeMapRange", {
                "Value": src, "From Min": lo, "From Max": hi, "To Min": 0.1, "To Max": 0.9,
                "Steps": 3.0}, interpolation_type=interp, clamp=clamp), "Result"))
        return g.rgb(*chans)
    return build


def _clamp(g):
    a, b, c = g.abc()
    mm = g.node("ShaderNodeClamp", {"Value": a, "Min": -0.2, "Max": 0.5}, clamp_type="MINMAX")
    rg = g.node("ShaderNodeClamp", {"Value": b, "Min": 0.6, "Max": -0.1}, clamp_type="RANGE")
    mm2 = g.node("ShaderNodeClamp", {"Value": c, "Min": 0.6, "Max": 0.2}, clamp_type="MINMAX")
    return g.rgb(g.out(mm), g.out(rg), g.out(mm2))


def _mix_float(clamp):
    def build(g):
        a, b, c = g.abc()
        f = g.out(g.node("ShaderNodeMath", {"Value": a, "Value_001": 2.0}, operation="MULTIPLY"))
        m = g.node("ShaderNodeMix", {"Factor_Float": f, "A_Float": b, "B_Float": c},
                   data_type="FLOAT", clamp_factor=clamp)
        return g.rgb(g.out(m, "Result_Float"), f, c)
    return build


def _mix_vector(mode):
    def build(g):
        a, b, c = g.abc()
        ins = {"Factor_Float": a, "Factor_Vector": g.vec(scale=(1.1, -0.9, 1.4)),
               "A_Vector": g.vec(), "B_Vector": (0.9, 0.1, 0.5)}
        return g.out(g.node("ShaderNodeMix", ins, data_type="VECTOR", factor_mode=mode,
                            clamp_factor=False), "Result_Vector")
    return build


BLENDS = ["MIX", "DARKEN", "MULTIPLY", "BURN", "LIGHTEN", "SCREEN", "DODGE", "ADD", "OVERLAY",
          "SOFT_LIGHT", "LINEAR_LIGHT", "DIFFERENCE", "EXCLUSION", "SUBTRACT", "DIVIDE"]


def _fract_colour(g, scale):
    return g.out(g.node("ShaderNodeVectorMath", {"Vector": g.vec(scale=scale)},
                        operation="FRACTION"), "Vector")


def _mix_color(blend, legacy=False, clamp_result=False):
    def build(g):
        a, b, c = g.abc()
        ca = _fract_colour(g, (0.7, 0.5, 0.9))
        cb = _fract_colour(g, (-0.4, 0.8, 0.3))
        fac = g.out(g.node("ShaderNodeMath", {"Value": b, "Value_001": 0.5}, operation="ADD"))
        if legacy:
            return g.out(g.node("ShaderNodeMixRGB", {"Fac": fac, "Color1": ca, "Color2": cb},
                                blend_type=blend, use_clamp=clamp_result))
        return g.out(g.node("ShaderNodeMix", {"Factor_Float": fac, "A_Color": ca, "B_Color": cb},
                            data_type="RGBA", blend_type=blend, clamp_factor=False,
                            clamp_result=clamp_result), "Result_Color")
    return build


def _ramp(interp, alpha=False):
    def build(g):
        a, b, c = g.abc()
        node = g.node("ShaderNodeValToRGB", {"Fac": g.out(g.node(
            "ShaderNodeMath", {"Value": a, "Value_001": 0.4}, operation="ADD"))})
        ramp = node.color_ramp
        ramp.interpolation = interp
        els = ramp.elements
        els[0].position, els[0].color = 0.1, (1.0, 0.2, 0.0, 0.3)
        els[1].position, els[1].color = 0.9, (0.1, 0.3, 1.0, 1.0)
        for pos, col in ((0.35, (0.0, 1.0, 0.4, 0.8)), (0.6, (0.9, 0.9, 0.1, 0.5))):
            e = els.new(pos)
            e.color = col
        if alpha:
            return g.rgb(g.out(node, "Alpha"), g.out(node, "Alpha"), b)
        return g.out(node, "Color")
    return build


def _color_ops(g):
    a, b, c = g.abc()
    col = _fract_colour(g, (0.7, 0.5, 0.9))
    inv = g.node("ShaderNodeInvert", {"Fac": a, "Color": col})
    gam = g.node("ShaderNodeGamma", {"Color": g.out(inv), "Gamma": 1.7})
    bc = g.node("ShaderNodeBrightContrast", {"Color": g.out(gam), "Bright": 0.1,
                                             "Contrast": 0.4})
    bw = g.node("ShaderNodeRGBToBW", {"Color": col})
    return g.out(g.node("ShaderNodeMix", {"Factor_Float": 0.3, "A_Color": g.out(bc),
                                          "B_Color": g.rgb(g.out(bw), c, a)},
                        data_type="RGBA"), "Result_Color")


def _checker(linked):
    def build(g):
        ins = {"Color1": (0.9, 0.3, 0.1, 1), "Color2": (0.1, 0.4, 0.8, 1), "Scale": 3.0}
        if linked:
            ins["Vector"] = g.vec()
        n = g.node("ShaderNodeTexChecker", ins)
        return g.rgb(g.out(n, "Fac"), g.out(g.node("ShaderNodeSeparateColor", {
            "Color": g.out(n, "Color")}), "Red"), g.out(g.node("ShaderNodeSeparateColor", {
                "Color": g.out(n, "Color")}), "Blue"))
    return build


GRADIENTS = ["LINEAR", "QUADRATIC", "EASING", "DIAGONAL", "SPHERICAL", "QUADRATIC_SPHERE",
             "RADIAL"]


def _gradient(kind):
    def build(g):
        n = g.node("ShaderNodeTexGradient", {"Vector": g.vec(scale=(0.4, 0.3, 0.35),
                                                             offset=(0.0, -0.3, -0.2))},
                   gradient_type=kind)
        return g.rgb(g.out(n, "Fac"), g.abc()[2], g.out(n, "Fac"))
    return build


def _image(interp="Linear", ext="REPEAT", projection="FLAT", srgb=False, linked=True):
    def build(g):
        img = g.image("px", 5, 3, seed=4, png_dir=g.tmp_path if srgb else None)
        ins = {"Vector": g.vec(scale=(0.4, 0.3, 0.5), offset=(0.2, 0.1, 0.3))} if linked else {}
        n = g.node("ShaderNodeTexImage", ins, interpolation=interp, extension=ext,
                   projection=projection)
        n.image = img
        if projection == "BOX":
            n.projection_blend = 0.3
        return g.out(n, "Color")
    return build


def _noise(kind, detail=2.0, normalize=True, distortion=0.0, output="Fac", scale=1.7):
    """A Noise Texture; ``scale`` low enough for its finest octave to be smooth at 32 x 24."""
    def build(g):
        n = g.node("ShaderNodeTexNoise", {"Vector": g.vec(scale=(0.5, 0.4, 0.6)),
                                          "Scale": scale, "Detail": detail, "Roughness": 0.6,
                                          "Lacunarity": 2.3, "Offset": 0.4, "Gain": 1.3,
                                          "Distortion": distortion},
                   noise_type=kind, normalize=normalize)
        if output == "Fac":
            return g.rgb(g.out(n, "Fac"), g.abc()[2], g.out(n, "Fac"))
        return g.out(n, "Color")
    return build


def _shader_mix(g):
    a, b, c = g.abc()
    emit = g.node("ShaderNodeEmission", {"Color": _fract_colour(g, (0.7, 0.5, 0.9)),
                                         "Strength": g.out(g.node("ShaderNodeMath", {
                                             "Value": c, "Value_001": 1.0},
                                             operation="ADD"))})
    # no specular layer: Cycles would sample glossy reflections of the room (only the
    # specular object reflects in riray)
    prin = g.node("ShaderNodeBsdfPrincipled", {
        "Base Color": (0.8, 0.2, 0.2, 1), "Specular IOR Level": 0.0,
        "Emission Color": _fract_colour(g, (-0.4, 0.8, 0.3)), "Emission Strength": 1.5})
    diff = g.node("ShaderNodeBsdfDiffuse", {"Color": (0.3, 0.9, 0.1, 1)})
    add = g.node("ShaderNodeAddShader", {"Shader": g.out(prin), "Shader_001": g.out(diff)})
    return g.out(g.node("ShaderNodeMixShader", {"Fac": a, "Shader": g.out(emit),
                                                "Shader_001": g.out(add)}))


def _value_rgb_reroute_mute(g):
    val = g.node("ShaderNodeValue")
    val.outputs[0].default_value = 0.7
    rgb = g.node("ShaderNodeRGB")
    rgb.outputs[0].default_value = (0.2, 0.6, 0.9, 1)
    rr = g.node("NodeReroute")
    g.nt.links.new(g.out(rgb), rr.inputs[0])
    muted = g.node("ShaderNodeInvert", {"Color": g.out(rr)})
    muted.mute = True                         # passes its colour through
    luma = g.node("ShaderNodeMath", {"Value": g.out(rgb), "Value_001": g.abc()[1]},
                  operation="ADD")                      # a colour into a float: luminance
    return g.out(g.node("ShaderNodeMix", {"Factor_Float": g.abc()[0],
                                          "A_Color": g.out(muted),
                                          "B_Color": g.rgb(g.out(val), g.out(luma), 0.1)},
                        data_type="RGBA"), "Result_Color")


def _issue_example(g):
    """The issue's room: Geometry -> Position -> Separate XYZ -> Math -> Checker."""
    sep = g.node("ShaderNodeSeparateXYZ", {"Vector": g.pos()})
    sine = g.node("ShaderNodeMath", {"Value": g.out(sep, "Z"), "Value_001": 2.0},
                  operation="MULTIPLY")
    wave = g.node("ShaderNodeMath", {"Value": g.out(sine)}, operation="SINE")
    vec = g.node("ShaderNodeCombineXYZ", {"X": g.out(sep, "X"), "Y": g.out(sep, "Y"),
                                          "Z": g.out(wave)})
    chk = g.node("ShaderNodeTexChecker", {"Vector": g.out(vec), "Scale": 1.5,
                                          "Color1": (0.9, 0.8, 0.2, 1),
                                          "Color2": (0.1, 0.2, 0.6, 1)})
    return g.out(chk, "Color")


def _combined_tiles(g):
    """Tiles: snapped object coordinates through a 4-stop ramp, multiplied with a gradient,
    a mix shader driven by backfacing."""
    tc = g.node("ShaderNodeTexCoord")
    snap = g.node("ShaderNodeVectorMath", {"Vector": g.out(tc, "Object"),
                                           "Vector_001": (0.4, 0.4, 0.4)}, operation="SNAP")
    length = g.node("ShaderNodeVectorMath", {"Vector": g.out(snap, "Vector")},
                    operation="LENGTH")
    ramp = g.node("ShaderNodeValToRGB", {"Fac": g.out(length, "Value")})
    els = ramp.color_ramp.elements
    els[0].color, els[1].color = (0.1, 0.1, 0.5, 1), (1.0, 0.9, 0.3, 1)
    els.new(0.4).color = (0.8, 0.1, 0.1, 1)
    grad = g.node("ShaderNodeTexGradient", {"Vector": g.out(tc, "Generated")},
                  gradient_type="SPHERICAL")
    mix = g.node("ShaderNodeMix", {"Factor_Float": 0.6, "A_Color": g.out(ramp, "Color"),
                                   "B_Color": g.out(grad, "Color")},
                 data_type="RGBA", blend_type="MULTIPLY")
    e1 = g.node("ShaderNodeEmission", {"Color": g.out(mix, "Result_Color"), "Strength": 2.0})
    e2 = g.node("ShaderNodeEmission", {"Color": g.out(tc, "UV"), "Strength": 1.0})
    back = g.out(g.node("ShaderNodeNewGeometry"), "Backfacing")
    return g.out(g.node("ShaderNodeMixShader", {"Fac": back, "Shader": g.out(e2),
                                                "Shader_001": g.out(e1)}))


ROOM_CASES = {
    **{f"tex_coord_{o.lower()}": _tex_coord(o) for o in
       ("Generated", "Normal", "UV", "Object", "Camera", "Reflection")},
    "tex_coord_object_of_an_empty": _tex_coord_other_object("Object"),
    **{f"geometry_{o.lower().replace(' ', '_')}": _geometry(o) for o in
       ("Position", "Normal", "True Normal", "Incoming", "Backfacing")},
    "object_info": _object_info,
    **{f"mapping_{k.lower()}": _mapping(k) for k in ("POINT", "TEXTURE", "VECTOR", "NORMAL")},
    "separate_combine_xyz": _xyz,
    "separate_combine_color": _color_sep_comb,
    **{"math_" + "_".join(o.lower() for o in MATH_OPS[i:i + 3]): _math(MATH_OPS[i:i + 3])
       for i in range(0, len(MATH_OPS), 3)},
    "math_clamped": _math(["MULTIPLY", "SUBTRACT", "SINE"], clamp=True),
    **{f"vector_math_{o.lower()}": _vector_math(o) for o in VECTOR_OPS + VALUE_OPS},
    "map_range_linear_stepped_smooth": _map_range(["LINEAR", "STEPPED", "SMOOTHSTEP"], True),
    "map_range_unclamped": _map_range(["LINEAR", "STEPPED", "SMOOTHERSTEP"], False),
    **{f"map_range_vector_{k.lower()}": _map_range([k], True, vector=True)
       for k in ("LINEAR", "STEPPED", "SMOOTHSTEP", "SMOOTHERSTEP")},
    "map_range_vector_unclamped": _map_range(["LINEAR"], False, vector=True),
    "clamp": _clamp,
    "mix_float": _mix_float(True),
    "mix_float_unclamped": _mix_float(False),
    "mix_vector_uniform": _mix_vector("UNIFORM"),
    "mix_vector_non_uniform": _mix_vector("NON_UNIFORM"),
    **{f"mix_color_{b.lower()}": _mix_color(b) for b in BLENDS},
    "mix_color_clamped": _mix_color("ADD", clamp_result=True),
    "mix_rgb_legacy_overlay": _mix_color("OVERLAY", legacy=True),
    "mix_rgb_legacy_clamped": _mix_color("LINEAR_LIGHT", legacy=True, clamp_result=True),
    **{f"color_ramp_{k.lower()}": _ramp(k) for k in ("LINEAR", "EASE", "CONSTANT")},
    "color_ramp_alpha": _ramp("LINEAR", alpha=True),
    "invert_gamma_bright_contrast_bw": _color_ops,
    "checker": _checker(True),
    "checker_generated": _checker(False),
    **{f"gradient_{k.lower()}": _gradient(k) for k in GRADIENTS},
    **{f"image_{i.lower()}_{e.lower()}": _image(i, e) for i in ("Closest", "Linear")
       for e in ("REPEAT", "EXTEND", "CLIP", "MIRROR")},
    "image_box": _image(projection="BOX"),
    "image_srgb": _image(srgb=True),
    "image_uv": _image(linked=False),
    "shaders_mix_add_principled_diffuse": _shader_mix,
    "noise_fbm": _noise("FBM"),
    "noise_fbm_fractional_unnormalized": _noise("FBM", detail=3.4, normalize=False, scale=0.5),
    "noise_multifractal": _noise("MULTIFRACTAL", detail=1.5),
    "noise_hybrid_multifractal": _noise("HYBRID_MULTIFRACTAL", detail=2.5),
    "noise_ridged_multifractal": _noise("RIDGED_MULTIFRACTAL"),
    "noise_hetero_terrain": _noise("HETERO_TERRAIN", detail=2.7, scale=0.8),
    "noise_distorted_color": _noise("FBM", distortion=0.8, output="Color"),
    "value_rgb_reroute_mute": _value_rgb_reroute_mute,
    "combined_issue_example": _issue_example,
    "combined_tiles": _combined_tiles,
}


FIXED_PATTERN_CASES = {"image_uv", "environment_linear"}


@pytest.mark.parametrize("case", sorted(ROOM_CASES))
def test_room_graph_matches_cycles(bl, tmp_path, cycles_offset, case):
    if case.startswith("vector_math_"):
        ops = bl.bpy.types.ShaderNodeVectorMath.bl_rna.properties["operation"].enum_items
        if case[len("vector_math_"):].upper() not in ops:
            pytest.skip(f"this Blender has no Vector Math {case[12:]}")
    scene, _, rep = compare(bl, tmp_path, cycles_offset, room=ROOM_CASES[case])
    # a tree one of the fixed patterns describes exactly keeps its texture kind
    want = {"emission"} if case in FIXED_PATTERN_CASES else {"nodes"}
    assert {m.kind for m in scene.materials.values()} == want
    # the object-dependent graph is exported once per object that uses it
    assert sorted(scene.materials) in (["room"], ["room [Box]", "room [Room]"])
    assert not rep.messages("WARNING"), rep




def _world_ramp(g):
    sep = g.node("ShaderNodeSeparateXYZ", {"Vector": g.out(g.node("ShaderNodeTexCoord"),
                                                              "Generated")})
    node = g.node("ShaderNodeValToRGB", {"Fac": g.out(sep, "Z")})
    els = node.color_ramp.elements
    els[0].color, els[1].color = (0.8, 0.7, 0.6, 1), (0.1, 0.3, 0.9, 1)
    els.new(0.3).color = (0.9, 0.9, 1.0, 1)
    return g.out(node, "Color")


def _world_environment(interp, mapped):
    def build(g):
        img = g.image("sky", 16, 8, seed=9)
        ins = {}
        if mapped:
            ins["Vector"] = g.out(g.node("ShaderNodeMapping", {
                "Vector": g.out(g.node("ShaderNodeTexCoord"), "Generated"),
                "Rotation": (0.2, -0.3, 0.8)}, vector_type="VECTOR"))
        n = g.node("ShaderNodeTexEnvironment", ins, interpolation=interp)
        n.image = img
        return g.out(n, "Color")
    return build


def _world_shaders(g):
    """Mix Shader of two backgrounds (factor: the direction's z) plus an emission."""
    z = g.out(g.node("ShaderNodeSeparateXYZ", {"Vector": g.pos()}), "Z")
    b1 = g.node("ShaderNodeBackground", {"Color": (0.9, 0.5, 0.2, 1), "Strength": 1.5})
    b2 = g.node("ShaderNodeBackground", {"Color": g.out(g.node("ShaderNodeTexCoord"),
                                                         "Reflection"), "Strength": 0.7})
    mix = g.node("ShaderNodeMixShader", {"Fac": z, "Shader": g.out(b1), "Shader_001": g.out(b2)})
    em = g.node("ShaderNodeEmission", {"Color": (0.1, 0.2, 0.1, 1), "Strength": 2.0})
    return g.out(g.node("ShaderNodeAddShader", {"Shader": g.out(mix), "Shader_001": g.out(em)}))


def _world_checker_sky(g):
    """Checks on the sky from rotated generated coordinates and a gradient."""
    tc = g.node("ShaderNodeTexCoord")
    mp = g.node("ShaderNodeMapping", {"Vector": g.out(tc, "Generated"),
                                      "Rotation": (0.0, 0.4, 0.3), "Scale": (3, 3, 3)})
    chk = g.node("ShaderNodeTexChecker", {"Vector": g.out(mp), "Scale": 1.0,
                                          "Color1": (0.9, 0.9, 0.8, 1),
                                          "Color2": (0.2, 0.3, 0.5, 1)})
    grad = g.node("ShaderNodeTexGradient", {"Vector": g.out(tc, "Object")},
                  gradient_type="RADIAL")
    return g.out(g.node("ShaderNodeMix", {"Factor_Float": g.out(grad, "Fac"),
                                          "A_Color": g.out(chk, "Color"),
                                          "B_Color": (0.8, 0.2, 0.1, 1)},
                        data_type="RGBA", blend_type="SOFT_LIGHT"), "Result_Color")


WORLD_CASES = {
    **{f"tex_coord_{o.lower()}": _tex_coord(o) for o in
       ("Generated", "Normal", "Object", "Camera", "Reflection")},
    "tex_coord_object_of_an_empty": _tex_coord_other_object("Object"),
    **{f"geometry_{o.lower()}": _geometry(o) for o in ("Position", "Normal", "Incoming")},
    **{f"gradient_{k.lower()}": (lambda k: lambda g: g.out(g.node(
        "ShaderNodeTexGradient", {"Vector": g.vec(scale=(0.8, 0.7, 0.9),
                                                  offset=(0.1, 0.0, -0.1))},
        gradient_type=k), "Color"))(k) for k in ("LINEAR", "SPHERICAL", "RADIAL", "EASING")},
    "color_ramp_3_stops": _world_ramp,
    "environment_linear": _world_environment("Linear", False),
    "environment_closest_mapped": _world_environment("Closest", True),
    "shaders_mix_add": _world_shaders,
    "noise_sky": (lambda g: g.out(g.node("ShaderNodeTexNoise", {"Scale": 2.0, "Detail": 3.0},
                                         noise_type="FBM"), "Color")),
    "combined_checker_sky": _world_checker_sky,
}


@pytest.mark.parametrize("case", sorted(WORLD_CASES))
def test_world_graph_matches_cycles(bl, tmp_path, cycles_offset, case):
    scene, _, rep = compare(bl, tmp_path, cycles_offset, world=WORLD_CASES[case])
    assert scene.world.kind == ("image" if case in FIXED_PATTERN_CASES else "nodes")
    assert not rep.messages("WARNING"), rep


# --------------------------------------------------------------------------- what is not evaluated
def _graph_of(scene, name="room"):
    return next(m for m in scene.materials.values() if m.name.startswith(name)).graph


def _export(bl, mirror):
    rep = bl.report.Report()
    scene = bl.export.export_scene(bl.bpy.context.evaluated_depsgraph_get(), mirror, rep,
                                   cameras="ACTIVE")
    return scene, " | ".join(rep.messages("WARNING"))


def test_unsupported_nodes_give_the_socket_value_and_one_warning(bl, tmp_path):
    """A node core does not evaluate is replaced by the value of the socket it feeds, with one
    warning naming the node and the material; the rest of the graph is kept."""
    def room(g):
        wave = g.node("ShaderNodeTexWave", {"Vector": g.pos()})
        math = g.node("ShaderNodeMath", {"Value": g.out(wave, "Fac"), "Value_001": 0.25},
                      operation="ADD")
        math.inputs[0].default_value = 0.5               # what replaces the noise
        path = g.node("ShaderNodeLightPath")
        mix = g.node("ShaderNodeMix", {"Factor_Float": g.out(path, "Is Camera Ray"),
                                       "A_Color": g.rgb(g.out(math), 0.2, 0.1),
                                       "B_Color": (0.3, 0.3, 0.3, 1)}, data_type="RGBA")
        next(s for s in mix.inputs if s.identifier == "Factor_Float").default_value = 0.0
        return g.out(mix, "Result_Color")

    mirror = build_scene(bl, tmp_path, room=room)
    scene, warn = _export(bl, mirror)
    assert warn.count("'Wave Texture'") == 1 and warn.count("'Light Path'") == 1
    assert "material 'room'" in warn and "(TEX_WAVE) is not supported" in warn
    img = render_exact(SceneTracer(scene), Shot(width=W, height=H), workers=1).image
    assert np.allclose(img[~np.isclose(img, 0).all(axis=2)], [0.75, 0.2, 0.1], atol=1e-6)
    math = next(n for n in _graph_of(scene).nodes if n.type == "math")
    assert "a" not in math.links and math.inputs["a"] == 0.5


def test_unsupported_outputs_shaders_and_settings_are_reported(bl, tmp_path):
    def room(g):
        tc = g.node("ShaderNodeTexCoord")
        glossy = g.node("ShaderNodeBsdfGlossy", {"Color": g.out(tc, "Window")})
        glossy.inputs["Color"].default_value = (0.1, 0.6, 0.2, 1)
        ramp = g.node("ShaderNodeValToRGB")
        ramp.color_ramp.interpolation = "B_SPLINE"
        em = g.node("ShaderNodeEmission", {"Color": g.out(ramp, "Color")})
        em.inputs["Color"].default_value = (0.4, 0.0, 0.0, 1)
        return g.out(g.node("ShaderNodeAddShader", {"Shader": g.out(glossy),
                                                    "Shader_001": g.out(em)}))

    mirror = build_scene(bl, tmp_path, room=room)
    scene, warn = _export(bl, mirror)
    assert "output 'Window' of node 'Texture Coordinate'" in warn
    assert "shader 'Glossy BSDF' (BSDF_GLOSSY) is shaded as diffuse" in warn
    assert "'Color Ramp' (VALTORGB): interpolation B_SPLINE is not supported" in warn
    g = _graph_of(scene)
    diffuse = next(n for n in g.nodes if n.type == "diffuse")
    emission = next(n for n in g.nodes if n.type == "emission")
    assert np.allclose(diffuse.inputs["color"], (0.1, 0.6, 0.2))
    assert np.allclose(emission.inputs["color"], (0.4, 0.0, 0.0))


def test_graph_scene_survives_the_json_file(bl, tmp_path):
    """riray.export_scene writes graph materials, the world graph and their images (as .npy)
    into a scene file that riray's loader renders to the same pixels."""
    from riray.scene.io import load_scene
    mirror = build_scene(bl, tmp_path, room=_image(projection="BOX"),
                         world=_world_environment("Closest", True))
    scene, _ = _export(bl, mirror)
    path = tmp_path / "scene" / "graph.json"
    assert bl.bpy.ops.riray.export_scene(filepath=str(path), object=mirror.name) == {"FINISHED"}
    again = load_scene(path)
    assert again.world.kind == "nodes" and {m.kind for m in again.materials.values()} == {"nodes"}
    a = render_exact(SceneTracer(scene), Shot(width=W, height=H), workers=1).image
    b = render_exact(SceneTracer(again), Shot(width=W, height=H), workers=1).image
    assert a.std() > 0.05 and np.abs(a - b).max() < 1e-12
