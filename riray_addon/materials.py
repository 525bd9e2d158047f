"""Blender materials / worlds -> core materials, with a report of every approximation.

Specular object (``object_material``), from the shader at the active Material Output:
  Glossy BSDF (also Anisotropic)          -> "mirror", tint = Color
  Refraction BSDF                         -> "glass" (pure refraction), ior, tint = Color
  Glass BSDF                              -> "dielectric" (Fresnel split at the first hit)
  Principled BSDF  transmission >= 0.5    -> "dielectric", ior, tint = Base Color
                   metallic >= 0.5        -> "mirror", tint = Base Color
                   otherwise              -> "mirror" coat over a diffuse base: diffuse =
                                             1 - F0(ior), base colour = Base Color
Roughness, textured inputs, mixes and other shaders are reported with what was used instead.
Highlights (specular / shininess) follow the shader's roughness (none for a sharp surface: it
reflects the area lights themselves), or material.riray's when its Custom Highlight is on.

Environment (``environment_material``): the fixed patterns core has texture kinds for, when
they describe the tree exactly: Principled / Diffuse BSDF -> "diffuse" with the base colour
(a Principled's metallic and roughness too);
Emission (or a Principled with emission) -> "emission"; colour sources: constant; Image Texture
(UV, optional uniform Mapping scale); Checker Texture (colours swapped to core's parity
convention; a Mapping with one zero axis scale gives stripes); a linear gradient = Color Ramp
(2 stops, linear) or Mix (A/B) driven by [Map Range ->] Separate XYZ of UV / Object
coordinates. Any other tree becomes a "nodes" material: its shader node graph
(riray_addon/nodegraph.py), which core evaluates node by node; nodes it cannot evaluate give
the socket's own value, reported.

World (``export_world``): likewise Background colour (constant), a Color Ramp on Separate
XYZ.Z of the Generated/Normal/Object coordinate (core's horizon -> zenith gradient), or an
equirectangular Environment Texture, else the world's node graph; strength; ambient from
world.riray.ambient; the world lights the scene (sky), as in Cycles.
"""

from __future__ import annotations

import numpy as np

from ..core.scene.model import Material, ObjectMaterial, Texture, World
from ..core.trace.shading import ROUGH_SHARP, roughness_shininess
from . import compat
from .node_helpers import image_pixels, output_node, source
from .nodegraph import SurfaceContext, surface_graph, world_graph
from .report import Report

# Below this the roughness of a specular shader is treated as zero without a report.
ROUGH_OK = 0.02
# Principled weights are snapped to 0/1 at this threshold (reports the approximation).
SNAP = 0.5
DEFAULT_COLOR = (0.8, 0.8, 0.8)


def _rgb(c) -> tuple[float, float, float]:
    return (float(c[0]), float(c[1]), float(c[2]))


# --------------------------------------------------------------------------- node graph helpers
def _input(node, *names):
    """The first input socket matching one of the identifiers / names."""
    for nm in names:
        for s in node.inputs:
            if s.identifier == nm:
                return s
        if nm in node.inputs:
            return node.inputs[nm]
    return None


def _value(node, *names, default=0.0):
    s = _input(node, *names)
    return float(s.default_value) if s is not None else float(default)


def _color_value(socket) -> tuple[float, float, float]:
    return _rgb(socket.default_value)


class _Ctx:
    """Where a colour comes from, for the messages."""

    def __init__(self, report, owner: str, has_uvs: bool = True, identity: bool = True):
        self.report = report
        self.owner = owner
        self.has_uvs = has_uvs
        self.identity = identity

    def warn(self, msg: str) -> None:
        self.report.warning(f"{self.owner}: {msg}")


# --------------------------------------------------------------------------- coordinates
def _coords(socket, ctx: _Ctx, default: str) -> tuple[str, np.ndarray]:
    """(coords, scale xyz) of a texture's Vector input: "uv" or "world", with a Mapping
    node's scale. ``default`` is what an unlinked input means for this node."""
    scale = np.ones(3)
    src = source(socket) if socket is not None else None
    if src is not None and src[0].type == "MAPPING":
        node = src[0]
        if node.vector_type not in ("POINT", "TEXTURE"):
            ctx.warn(f"Mapping type {node.vector_type} not supported; ignored")
        loc = _input(node, "Location")
        rot = _input(node, "Rotation")
        sc = _input(node, "Scale")
        if loc is not None and (loc.is_linked or np.any(np.abs(loc.default_value) > 0)):
            ctx.warn("Mapping location ignored")
        if rot is not None and (rot.is_linked or np.any(np.abs(rot.default_value) > 0)):
            ctx.warn("Mapping rotation ignored")
        if sc is not None and not sc.is_linked:
            scale = np.array(sc.default_value[:3], dtype=np.float64)
        src = source(node.inputs[0])
        if src is None:
            return _coords_default(default, ctx), scale
    if src is None:
        return _coords_default(default, ctx), scale
    node, out = src
    if node.type == "UVMAP" or (node.type == "TEX_COORD" and out.name == "UV"):
        if node.type == "UVMAP" and node.uv_map:
            ctx.warn(f"UV map {node.uv_map!r}: the mesh's active UV map is used")
        return ("uv" if ctx.has_uvs else "world"), scale
    if node.type == "TEX_COORD" and out.name == "Object":
        if getattr(node, "object", None) is not None or not ctx.identity:
            ctx.warn("Object texture coordinates approximated by world coordinates (the "
                     "object's transform is not the identity)")
        return "world", scale
    if node.type == "TEX_COORD" and out.name == "Generated":
        return _coords_default("generated", ctx), scale
    ctx.warn(f"texture coordinates from {node.name!r} not supported; using "
             f"{'UV' if ctx.has_uvs else 'world'} coordinates")
    return ("uv" if ctx.has_uvs else "world"), scale


def _coords_default(default: str, ctx: _Ctx) -> str:
    if default == "uv":
        if not ctx.has_uvs:
            ctx.warn("image texture without UVs; using world x, y")
            return "world"
        return "uv"
    ctx.warn("Generated texture coordinates not supported; using "
             f"{'UV' if ctx.has_uvs else 'world'} coordinates")
    return "uv" if ctx.has_uvs else "world"


# --------------------------------------------------------------------------- colour sources
def _image_texture(node, ctx: _Ctx) -> Texture | None:
    img = node.image
    if img is None:
        ctx.warn(f"image texture {node.name!r} has no image; using black")
        return Texture(kind="constant", color=(0.0, 0.0, 0.0))
    px = image_pixels(img)
    if px is None:
        ctx.warn(f"image {img.name!r} could not be read; using grey")
        return Texture(kind="constant", color=DEFAULT_COLOR)
    if node.projection != "FLAT":
        ctx.warn(f"image projection {node.projection} not supported; flat")
    if node.extension != "REPEAT":
        ctx.warn(f"image extension {node.extension} not supported; repeat")
    if node.interpolation != "Linear":
        ctx.warn(f"image interpolation {node.interpolation} -> linear")
    coords, scale = _coords(_input(node, "Vector"), ctx, "uv")
    if not np.allclose(scale[:2], scale[0]):
        ctx.warn("non-uniform Mapping scale on an image; using the x scale")
    return Texture(kind="image", image=px, path=bpy_path(img), coords=coords,
                   scale=float(scale[0]))


def bpy_path(img) -> str | None:
    return img.filepath or None


def _checker(node, ctx: _Ctx) -> Texture:
    c1, c2 = _input(node, "Color1"), _input(node, "Color2")
    for s in (c1, c2):
        if s.is_linked:
            ctx.warn(f"linked checker colour {s.name} not supported; its own value is used")
    sc = _input(node, "Scale")
    if sc.is_linked:
        ctx.warn("linked checker scale not supported; its own value is used")
    coords, mscale = _coords(_input(node, "Vector"), ctx, "generated")
    s = float(sc.default_value) * mscale
    dims = 2 if coords == "uv" else 3
    # Blender: color1 where the integer coordinates sum odd; core: color where they sum even.
    a, b = _color_value(c2), _color_value(c1)
    zero = np.abs(s[:dims]) < 1e-12
    if zero.sum() == dims - 1:
        axis = int(np.flatnonzero(~zero)[0])
        return Texture(kind="stripes", color=a, color2=b, scale=float(s[axis]), axis=axis,
                       coords=coords)
    if not np.allclose(s[:dims], s[0]):
        ctx.warn(f"non-uniform checker scale {tuple(np.round(s[:dims], 4))}; using {s[0]:g}")
    return Texture(kind="checker", color=a, color2=b, scale=float(s[0]), coords=coords)


def _gradient_value(socket, ctx: _Ctx):
    """A scalar input computing clamp((c[axis] - start) / (end - start)): returns
    (coords, axis, start, end) or None."""
    src = source(socket)
    if src is None:
        return None
    node, out = src
    start, end = 0.0, 1.0
    if node.type == "MAP_RANGE":
        if node.data_type != "FLOAT" or node.interpolation_type != "LINEAR":
            return None
        if _value(node, "To Min") != 0.0 or _value(node, "To Max") != 1.0 or not node.clamp:
            ctx.warn("Map Range must map to [0, 1] with Clamp on; treated as such")
        start, end = _value(node, "From Min"), _value(node, "From Max")
        src = source(_input(node, "Value"))
        if src is None:
            return None
        node, out = src
    if node.type != "SEPXYZ":
        return None
    axis = {"X": 0, "Y": 1, "Z": 2}[out.name]
    coords, scale = _coords(node.inputs[0], ctx, "generated")
    if abs(scale[axis]) < 1e-12:
        return None
    return coords, axis, start / scale[axis], end / scale[axis]


def _ramp_stops(node, ctx: _Ctx):
    ramp = node.color_ramp
    els = list(ramp.elements)
    if len(els) != 2 or ramp.interpolation != "LINEAR" or ramp.color_mode != "RGB":
        ctx.warn(f"color ramp {node.name!r}: only 2 stops, linear RGB, are exact; using its "
                 "first and last stops")
    e0, e1 = els[0], els[-1]
    return float(e0.position), float(e1.position), _rgb(e0.color), _rgb(e1.color)


def color_texture(socket, ctx: _Ctx) -> Texture:
    """The core Texture equal (or closest) to the colour at an input socket."""
    src = source(socket)
    if src is None:
        return Texture(kind="constant", color=_color_value(socket))
    node, out = src
    if node.type == "TEX_IMAGE":
        return _image_texture(node, ctx)
    if node.type == "TEX_CHECKER":
        if out.name != "Color":
            ctx.warn("checker Fac output used as a colour; using its colours")
        return _checker(node, ctx)
    if node.type == "VALTORGB":
        g = _gradient_value(_input(node, "Fac", "Factor"), ctx)
        p0, p1, c0, c1 = _ramp_stops(node, ctx)
        if g is not None:
            coords, axis, a, b = g
            return Texture(kind="gradient", color=c0, color2=c1, axis=axis,
                           start=a + p0 * (b - a), end=a + p1 * (b - a), coords=coords)
        ctx.warn(f"color ramp {node.name!r}: its factor is not a coordinate gradient; using "
                 "the first stop's colour")
        return Texture(kind="constant", color=c0)
    if node.type in ("MIX", "MIX_RGB"):
        if node.type == "MIX":
            if node.data_type != "RGBA":
                return _fallback(socket, node, ctx)
            fac, a, b = (_input(node, "Factor_Float"), _input(node, "A_Color"),
                         _input(node, "B_Color"))
        else:
            fac, a, b = _input(node, "Fac", "Factor"), _input(node, "Color1"), _input(node, "Color2")
        if node.blend_type != "MIX" or a.is_linked or b.is_linked:
            return _fallback(socket, node, ctx)
        g = _gradient_value(fac, ctx)
        if g is None:
            if fac.is_linked:
                return _fallback(socket, node, ctx)
            t = float(fac.default_value)
            ca, cb = np.array(_color_value(a)), np.array(_color_value(b))
            return Texture(kind="constant", color=tuple(float(x) for x in (1 - t) * ca + t * cb))
        coords, axis, start, end = g
        return Texture(kind="gradient", color=_color_value(a), color2=_color_value(b),
                       axis=axis, start=start, end=end, coords=coords)
    return _fallback(socket, node, ctx)


def _fallback(socket, node, ctx: _Ctx) -> Texture:
    col = _color_value(socket) if hasattr(socket, "default_value") else DEFAULT_COLOR
    ctx.warn(f"colour from node {node.name!r} ({node.type}) not supported; using "
             f"({col[0]:.3g}, {col[1]:.3g}, {col[2]:.3g})")
    return Texture(kind="constant", color=col)


def _const_color(socket, ctx: _Ctx, what: str) -> tuple[float, float, float]:
    if socket.is_linked:
        tex = color_texture(socket, ctx)
        col = tex.color if tex.kind != "image" else tuple(float(x) for x in tex.image.reshape(-1, 3).mean(0))
        ctx.warn(f"textured {what} is not simulated on the specular object; using "
                 f"({col[0]:.3g}, {col[1]:.3g}, {col[2]:.3g})")
        return col
    return _color_value(socket)


def _const_value(socket, ctx: _Ctx, what: str) -> float:
    if socket.is_linked:
        ctx.warn(f"linked {what} not supported; using {float(socket.default_value):g}")
    return float(socket.default_value)


# --------------------------------------------------------------------------- the shader
def _surface_shader(tree, ctx: _Ctx):
    out = output_node(tree) if tree is not None else None
    if out is None:
        return None
    src = source(out.inputs["Surface"])
    if src is None:
        return None
    node = src[0]
    depth = 0
    while node.type == "MIX_SHADER" and depth < 8:
        fac = node.inputs[0]
        t = float(fac.default_value)
        pick = 2 if (not fac.is_linked and t >= 0.5) else 1
        other = 1 if pick == 2 else 2
        s = source(node.inputs[pick]) or source(node.inputs[other])
        ctx.warn(f"Mix Shader {node.name!r}: core simulates one shader; using input {pick}")
        if s is None:
            return None
        node = s[0]
        depth += 1
    return node


def _roughness(node, ctx: _Ctx) -> None:
    r = _input(node, "Roughness")
    if r is not None and (r.is_linked or float(r.default_value) > ROUGH_OK):
        ctx.warn(f"roughness {float(r.default_value):.3g} ignored: core simulates perfectly "
                 "sharp reflection/refraction")


def _highlight(mat, node) -> dict:
    """The specular object's highlight (ObjectMaterial specular, shininess): the material's
    RI-Tree Highlight and Shininess when *Custom Highlight* is on; else from the shader's
    Roughness: none up to ROUGH_SHARP (a sharp surface's highlights are the lights it
    reflects: its reflected rays see the area lights), above it the Blinn-Phong lobe of that
    roughness with the surface's reflectance (1 for metals and Glossy, F0(IOR) otherwise)."""
    if mat.riray.custom_highlight:
        return dict(specular=float(mat.riray.specular), shininess=float(mat.riray.shininess))
    rough = _input(node, "Roughness") if node is not None else None
    r = float(rough.default_value) if rough is not None else 0.0
    if r <= ROUGH_SHARP:
        return dict(specular=0.0, shininess=1.0)
    metal = node.type in ("BSDF_GLOSSY", "BSDF_ANISOTROPIC") or (
        node.type == "BSDF_PRINCIPLED" and _value(node, "Metallic") >= SNAP)
    ior = _value(node, "IOR", default=1.5)
    f0 = 1.0 if metal else ((ior - 1.0) / (ior + 1.0)) ** 2
    return dict(specular=float(f0), shininess=roughness_shininess(r))


def is_sharp_specular(mat) -> bool:
    """Whether the Blender material ``mat`` is one a specular object renders (what makes an
    object one without its panel's mark): its surface shader a Glass, Refraction or Glossy
    BSDF, or a Principled BSDF with Transmission or Metallic of at least SNAP, sharp
    (Roughness up to ROUGH_OK; rougher surfaces are environment, shaded with their lobe)."""
    if mat is None:
        return False
    node = _surface_shader(compat.shader_tree(mat), _Ctx(Report(), mat.name))
    if node is None:
        return False
    rough = _input(node, "Roughness")
    if rough is not None and (rough.is_linked or float(rough.default_value) > ROUGH_OK):
        return False
    if node.type in ("BSDF_GLASS", "BSDF_REFRACTION", "BSDF_GLOSSY"):
        return True
    return node.type == "BSDF_PRINCIPLED" and max(
        _value(node, "Transmission Weight", "Transmission"), _value(node, "Metallic")) >= SNAP


def object_material(mat, report, owner: str = "") -> ObjectMaterial:
    """The specular object's ObjectMaterial from a Blender material (None: a mirror)."""
    name = f"{owner}: material {mat.name!r}" if mat is not None else owner
    ctx = _Ctx(report, name)
    if mat is None:
        report.warning(f"{owner}: no material; rendered as a mirror")
        return ObjectMaterial(kind="mirror", tint=(1.0, 1.0, 1.0), specular=0.25, shininess=96.0)
    node = _surface_shader(compat.shader_tree(mat), ctx)
    hl = _highlight(mat, node)
    if node is None:
        ctx.warn("no shader connected to the Material Output; rendered as a mirror tinted with "
                 "the viewport colour")
        return ObjectMaterial(kind="mirror", tint=_rgb(mat.diffuse_color), **hl)
    t = node.type
    if t == "BSDF_GLOSSY":
        _roughness(node, ctx)
        return ObjectMaterial(kind="mirror", tint=_const_color(_input(node, "Color"), ctx, "colour"),
                              **hl)
    if t in ("BSDF_REFRACTION", "BSDF_GLASS"):
        _roughness(node, ctx)
        ior = _const_value(_input(node, "IOR"), ctx, "IOR")
        return ObjectMaterial(kind="glass" if t == "BSDF_REFRACTION" else "dielectric",
                              ior=max(ior, 1e-3),
                              tint=_const_color(_input(node, "Color"), ctx, "colour"), **hl)
    if t == "BSDF_PRINCIPLED":
        base = _const_color(_input(node, "Base Color"), ctx, "base colour")
        metal = _const_value(_input(node, "Metallic"), ctx, "metallic")
        trans = _const_value(_input(node, "Transmission Weight", "Transmission"), ctx,
                             "transmission")
        ior = _const_value(_input(node, "IOR"), ctx, "IOR")
        _roughness(node, ctx)
        for nm in ("Coat Weight", "Sheen Weight", "Subsurface Weight"):
            s = _input(node, nm)
            if s is not None and (s.is_linked or float(s.default_value) > 0):
                ctx.warn(f"{nm} ignored")
        if trans >= SNAP:
            if trans < 1.0 or metal > 0:
                ctx.warn(f"transmission {trans:g} / metallic {metal:g} -> a clear dielectric")
            return ObjectMaterial(kind="dielectric", ior=max(ior, 1e-3), tint=base, **hl)
        if metal >= SNAP:
            if metal < 1.0:
                ctx.warn(f"metallic {metal:g} -> a full mirror")
            return ObjectMaterial(kind="mirror", tint=base, **hl)
        f0 = ((ior - 1.0) / (ior + 1.0)) ** 2
        ctx.warn(f"non-metallic opaque Principled BSDF -> a mirror coat (reflectance {f0:.3g}) "
                 "over a diffuse base")
        return ObjectMaterial(kind="mirror", tint=(1.0, 1.0, 1.0), base_color=base,
                              diffuse=float(1.0 - f0), **hl)
    if t == "BSDF_DIFFUSE":
        ctx.warn("Diffuse BSDF on the specular object -> diffuse shading only")
        return ObjectMaterial(kind="mirror", tint=(0.0, 0.0, 0.0),
                              base_color=_const_color(_input(node, "Color"), ctx, "colour"),
                              diffuse=1.0, **hl)
    ctx.warn(f"shader {node.name!r} ({t}) cannot be simulated; rendered as a mirror")
    return ObjectMaterial(kind="mirror", tint=(1.0, 1.0, 1.0), **hl)


def environment_material(mat, report, obj, has_uvs: bool = True,
                         surface: SurfaceContext | None = None, camera=None) -> Material:
    """A core environment Material (named after the Blender material): a fixed pattern when
    one describes the tree exactly, else its node graph (``surface`` and ``camera``, the scene
    camera's 4 x 4 matrix, give the graph its object and camera coordinates)."""
    return _environment_material(mat, report, obj, has_uvs, surface, camera)[0]


def _environment_material(mat, report, obj, has_uvs, surface, camera):
    """(Material, whether it holds data of ``surface``'s object)."""
    probe = Report()
    legacy = _fixed_environment_material(mat, probe, obj, has_uvs)
    if not probe or mat is None:
        return legacy, False
    graph, dependent = surface_graph(compat.shader_tree(mat), report, f"material {mat.name!r}",
                                     surface or SurfaceContext(), camera)
    if graph is None:
        for level, msg in probe.items:
            report.add(level, msg)
        return legacy, False
    return Material(name=mat.name, kind="nodes", graph=graph,
                    **_graph_glossy(mat, report)), dependent


def _graph_glossy(mat, report) -> dict:
    """The glossy layer (metallic, roughness, specular) of a node-graph material whose output
    is a Principled BSDF with constant inputs; a metallic Principled elsewhere in the tree is
    reported (shaded as diffuse)."""
    tree = compat.shader_tree(mat)
    ctx = _Ctx(report, f"material {mat.name!r}")
    root = _surface_shader(tree, _Ctx(Report(), ""))
    if root is not None and root.type == "BSDF_PRINCIPLED":
        return dict(metallic=min(max(_const_value(_input(root, "Metallic"), ctx, "metallic"),
                                     0.0), 1.0),
                    roughness=min(max(_const_value(_input(root, "Roughness"), ctx,
                                                   "roughness"), 0.0), 1.0),
                    specular=_specular_layer(root, ctx))
    for node in tree.nodes:
        if node.type == "BSDF_PRINCIPLED" and _value(node, "Metallic") > 0:
            ctx.warn(f"node {node.name!r}: metallic is shaded as diffuse (only a Principled BSDF "
                     "at the Material Output reflects)")
    return {}


class EnvironmentMaterials:
    """Core materials for the environment's Blender materials, translated once each; a node
    graph holding one object's data (object coordinates, Object Info) is translated again for
    every object, as ``"<material> [<object>]"``."""

    def __init__(self, report, camera=None):
        self.report, self.camera = report, camera
        self.shared: dict = {}          # Blender material name -> Material or None (per object)
        self.per_object: dict = {}      # (material name, object name) -> Material

    def get(self, mat, obj, name: str, has_uvs: bool, surface: SurfaceContext) -> Material:
        key = mat.name if mat is not None else "__default__"
        got = self.shared.get(key, False)
        if got is False:
            m, dependent = _environment_material(mat, self.report, obj, has_uvs, surface,
                                                 self.camera)
            self.shared[key] = None if dependent else m
            if dependent:
                m.name = f"{key} [{name}]"
                self.per_object[(key, name)] = m
            return m
        if got is not None:
            return got
        if (key, name) not in self.per_object:
            m, _ = _environment_material(mat, self.report, obj, has_uvs, surface, self.camera)
            m.name = f"{key} [{name}]"
            self.per_object[(key, name)] = m
        return self.per_object[(key, name)]


def _fixed_environment_material(mat, report, obj, has_uvs: bool) -> Material:
    """The environment Material from the fixed patterns (texture kinds), approximations
    reported."""
    ident = True
    try:
        m = np.array(obj.matrix_world)
        ident = bool(np.allclose(m, np.eye(4), atol=1e-9))
    except (AttributeError, TypeError):
        pass
    if mat is None:
        return Material(name="__default__", kind="diffuse",
                        color=Texture(kind="constant", color=DEFAULT_COLOR))
    ctx = _Ctx(report, f"material {mat.name!r}", has_uvs=has_uvs, identity=ident)
    node = _surface_shader(compat.shader_tree(mat), ctx)
    if node is None:
        return Material(name=mat.name, kind="diffuse",
                        color=Texture(kind="constant", color=_rgb(mat.diffuse_color)))
    t = node.type
    if t == "EMISSION":
        return Material(name=mat.name, kind="emission",
                        color=color_texture(_input(node, "Color"), ctx),
                        strength=_const_value(_input(node, "Strength"), ctx, "strength"))
    if t == "BSDF_PRINCIPLED":
        es = _input(node, "Emission Strength")
        ec = _input(node, "Emission Color")
        if es is not None and float(es.default_value) > 0 and (
                ec.is_linked or max(_color_value(ec)) > 0):
            return Material(name=mat.name, kind="emission", color=color_texture(ec, ctx),
                            strength=float(es.default_value))
        tr = _input(node, "Transmission Weight", "Transmission")
        if tr is not None and (tr.is_linked or float(tr.default_value) > 0):
            ctx.warn("transmissive environment surfaces are shaded as diffuse")
        return Material(name=mat.name, kind="diffuse",
                        color=color_texture(_input(node, "Base Color"), ctx),
                        metallic=min(max(_const_value(_input(node, "Metallic"), ctx,
                                                      "metallic"), 0.0), 1.0),
                        roughness=min(max(_const_value(_input(node, "Roughness"), ctx,
                                                       "roughness"), 0.0), 1.0),
                        specular=_specular_layer(node, ctx))
    if t == "BSDF_DIFFUSE":
        return Material(name=mat.name, kind="diffuse", color=color_texture(_input(node, "Color"), ctx))
    col = _input(node, "Color")
    ctx.warn(f"shader {t} is shaded as diffuse in the environment (only the specular object "
             "reflects)")
    tex = color_texture(col, ctx) if col is not None else Texture(kind="constant",
                                                                  color=DEFAULT_COLOR)
    return Material(name=mat.name, kind="diffuse", color=tex)


def _specular_layer(node, ctx: _Ctx) -> float:
    """A Principled BSDF's dielectric layer as its normal reflectance: F0(IOR) * 2 * Specular
    IOR Level (Blender's scale: 0.5 leaves F0 as the IOR gives it), within [0, 1]."""
    ior = _const_value(_input(node, "IOR"), ctx, "IOR")
    level = _input(node, "Specular IOR Level")
    scale = 2.0 * _const_value(level, ctx, "specular IOR level") if level is not None else 1.0
    return min(max(((ior - 1.0) / (ior + 1.0)) ** 2 * scale, 0.0), 1.0)


def export_world(world, report, camera=None) -> World:
    """The core World: colour, horizon->zenith gradient or equirectangular image when one
    describes the world's tree exactly, else its node graph (``camera``: the scene camera's
    4 x 4 matrix, for camera coordinates)."""
    if world is None:
        report.info("the scene has no world; the background is black")
        return World(kind="color", color=(0.0, 0.0, 0.0))
    probe = Report()
    out = _fixed_world(world, probe)
    if probe:
        graph = world_graph(compat.shader_tree(world), report, f"world {world.name!r}", camera)
        if graph is None:
            for level, msg in probe.items:
                report.add(level, msg)
        else:
            out = World(kind="nodes", graph=graph, ambient=float(world.riray.ambient))
    out.sky = True              # as in Cycles, the world lights the scene
    return out


def _fixed_world(world, report) -> World:
    """The World from the fixed patterns (kinds color / gradient / image)."""
    ambient = float(world.riray.ambient)
    ctx = _Ctx(report, f"world {world.name!r}")
    tree = compat.shader_tree(world)
    out = output_node(tree) if tree is not None else None
    src = source(out.inputs["Surface"]) if out is not None else None
    if src is None:
        return World(kind="color", color=_rgb(world.color), ambient=ambient)
    node = src[0]
    if node.type != "BACKGROUND":
        ctx.warn(f"world shader {node.type} not supported; using the world colour")
        return World(kind="color", color=_rgb(world.color), ambient=ambient)
    strength = _const_value(_input(node, "Strength"), ctx, "strength")
    col = _input(node, "Color")
    csrc = source(col)
    if csrc is None:
        return World(kind="color", color=_color_value(col), strength=strength, ambient=ambient)
    cnode = csrc[0]
    if cnode.type == "TEX_ENVIRONMENT":
        if cnode.projection != "EQUIRECTANGULAR":
            ctx.warn(f"environment projection {cnode.projection} not supported; equirectangular")
        if source(cnode.inputs[0]) is not None:
            ctx.warn("environment texture vector input ignored")
        px = image_pixels(cnode.image) if cnode.image is not None else None
        if px is None:
            ctx.warn("environment texture has no image; using black")
            return World(kind="color", color=(0.0, 0.0, 0.0), strength=strength, ambient=ambient)
        return World(kind="image", image=px, path=bpy_path(cnode.image), strength=strength,
                     ambient=ambient)
    if cnode.type == "VALTORGB":
        s = source(_input(cnode, "Fac", "Factor"))
        ok = (s is not None and s[0].type == "SEPXYZ" and s[1].name == "Z")
        if ok:
            d = source(s[0].inputs[0])
            ok = d is None or (d[0].type == "TEX_COORD" and d[1].name in ("Generated", "Normal",
                                                                          "Object"))
        p0, p1, c0, c1 = _ramp_stops(cnode, ctx)
        if ok:
            if abs(p0) > 1e-6 or abs(p1 - 1.0) > 1e-6:
                ctx.warn("sky gradient stops not at 0 and 1; stretched to horizon -> zenith")
            return World(kind="gradient", color=c0, zenith=c1, strength=strength, ambient=ambient)
        ctx.warn("world colour ramp not driven by the view direction's Z; using its first stop")
        return World(kind="color", color=c0, strength=strength, ambient=ambient)
    ctx.warn(f"world colour from {cnode.name!r} ({cnode.type}) not supported; using "
             f"{_color_value(col)}")
    return World(kind="color", color=_color_value(col), strength=strength, ambient=ambient)
