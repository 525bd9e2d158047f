"""Blender shader node trees -> core shader graphs (riray.scene.graph), for environment surfaces
and the world.

``surface_graph`` / ``world_graph`` walk back from the output's Surface socket and translate
every node they reach that core evaluates (core/trace/nodes.py: the same formulas as Cycles'
SVM kernels) into a core GraphNode; socket identifiers are read, not labels (they are the same
in Blender 4.2 and 5.0). Value and RGB nodes become constants, reroutes and muted nodes are
followed, texture nodes with nothing on their Vector input get Cycles' default coordinates
(Generated, or UV for images). A node core does not evaluate is replaced by the value of the
socket it feeds, with one warning naming the node and the material, as before graphs existed;
shaders other than Emission / Background / Diffuse / Principled / Mix / Add are shaded as
diffuse with their Color (only the specular object reflects).

Object-dependent data (object and generated coordinates, the object's normal transform, Object
Info) is baked into the graph from ``SurfaceContext``; ``Builder.object_dependent`` tells the
caller that the graph is only valid for that object.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.scene.graph import (FLOAT, LUMA, NODE_TYPES, SHADER, GraphError, GraphNode, Link,
                                ShaderGraph)
from ..core.trace.nodes import hash_uint2
from .node_helpers import image_pixels, output_node, source

# Cycles' camera space looks down +Z (Blender's camera looks down -Z): world -> camera is
# diag(1, 1, -1) * inverse(camera matrix).
CAMERA_FLIP = np.diag([1.0, 1.0, -1.0, 1.0])
# Colour spaces whose 8-bit pixels are used as they are (sRGB ones are linearized after
# interpolation, as Cycles does).
LINEAR_SPACES = ("Non-Color", "Linear Rec.709", "Linear", "Raw")
MAX_NESTING = 100       # nodes deep (Python recursion) before a tree counts as broken


@dataclass
class SurfaceContext:
    """What object-dependent nodes need about the shaded object (world space): its 4 x 4
    matrix, the texture space of its mesh (Generated = (object coords - location) / (2 size)
    + 0.5), its Object Info values and its material's pass index. None fields: the world."""

    matrix: np.ndarray | None = None
    texspace_location: tuple = (0.0, 0.0, 0.0)
    texspace_size: tuple = (1.0, 1.0, 1.0)
    color: tuple = (1.0, 1.0, 1.0, 1.0)
    pass_index: int = 0
    material_index: int = 0
    random: float = 0.0


def object_random_id(name: str) -> int:
    """Cycles' random_id of an object that is not an instance: hash_uint2(hash_string(name), 0)
    (a string hash i = 37 i + c over the name's bytes, as C chars, then lookup3). Object Info's
    Random is this / (2^32 - 1)."""
    h = 0
    for byte in name.encode("utf-8"):
        h = (h * 37 + (byte - 256 if byte >= 128 else byte)) & 0xFFFFFFFF   # char is signed
    return int(hash_uint2(np.array([h], np.uint32), np.array([0], np.uint32))[0])


class Unsupported(Exception):
    """A node (or one of its settings) core does not evaluate; the message says which."""


def _rgb(v) -> tuple:
    return tuple(float(x) for x in tuple(v)[:3])


def _enum(value: str) -> str:
    return value.lower()


# --------------------------------------------------------------------------- node translators
# Each returns (core type, props, {core input: Blender input socket identifier or constant},
# {Blender output identifier: core output}).
def _tex_coord(b, node):
    return "tex_coord", b.coordinate_props(node.object), {}, {
        "Generated": "generated", "Normal": "normal", "UV": "uv", "Object": "object",
        "Camera": "camera", "Reflection": "reflection"}


def _geometry(b, node):
    return "geometry", {}, {}, {"Position": "position", "Normal": "normal",
                                "True Normal": "true_normal", "Incoming": "incoming",
                                "Backfacing": "backfacing"}


def _object_info(b, node):
    c = b.surface
    if c.matrix is None:
        raise Unsupported("Object Info in the world")
    b.object_dependent = True
    props = dict(location=tuple(float(x) for x in c.matrix[:3, 3]), color=_rgb(c.color),
                 alpha=float(c.color[3]), object_index=float(c.pass_index),
                 material_index=float(c.material_index), random=float(c.random))
    return "object_info", props, {}, {"Location": "location", "Color": "color",
                                      "Alpha": "alpha", "Object Index": "object_index",
                                      "Material Index": "material_index", "Random": "random"}


def _mapping(b, node):
    return "mapping", {"vector_type": _enum(node.vector_type)}, {
        "vector": "Vector", "location": "Location", "rotation": "Rotation",
        "scale": "Scale"}, {"Vector": "vector"}


def _sep_xyz(b, node):
    return "separate_xyz", {}, {"vector": "Vector"}, {"X": "x", "Y": "y", "Z": "z"}


def _comb_xyz(b, node):
    return "combine_xyz", {}, {"x": "X", "y": "Y", "z": "Z"}, {"Vector": "vector"}


def _sep_color(b, node):
    if getattr(node, "mode", "RGB") != "RGB":
        raise Unsupported(f"mode {node.mode}")
    ins = {"color": "Color" if node.type == "SEPARATE_COLOR" else "Image"}
    outs = ({"Red": "red", "Green": "green", "Blue": "blue"} if node.type == "SEPARATE_COLOR"
            else {"R": "red", "G": "green", "B": "blue"})
    return "separate_color", {}, ins, outs


def _comb_color(b, node):
    if getattr(node, "mode", "RGB") != "RGB":
        raise Unsupported(f"mode {node.mode}")
    if node.type == "COMBINE_COLOR":
        return "combine_color", {}, {"red": "Red", "green": "Green", "blue": "Blue"}, {
            "Color": "color"}
    return "combine_color", {}, {"red": "R", "green": "G", "blue": "B"}, {"Image": "color"}


def _math(b, node):
    return "math", {"operation": _enum(node.operation), "clamp": bool(node.use_clamp)}, {
        "a": "Value", "b": "Value_001", "c": "Value_002"}, {"Value": "value"}


def _vector_math(b, node):
    return "vector_math", {"operation": _enum(node.operation)}, {
        "a": "Vector", "b": "Vector_001", "c": "Vector_002", "scale": "Scale"}, {
        "Vector": "vector", "Value": "value"}


def _map_range(b, node):
    props = {"interpolation": _enum(node.interpolation_type), "clamp": bool(node.clamp)}
    if node.data_type == "FLOAT":
        return "map_range", props, {
            "value": "Value", "from_min": "From Min", "from_max": "From Max",
            "to_min": "To Min", "to_max": "To Max", "steps": "Steps"}, {"Result": "result"}
    return "map_range_vector", props, {
        "vector": "Vector", "from_min": "From_Min_FLOAT3", "from_max": "From_Max_FLOAT3",
        "to_min": "To_Min_FLOAT3", "to_max": "To_Max_FLOAT3", "steps": "Steps_FLOAT3"}, {
        "Vector": "vector"}


def _clamp(b, node):
    return "clamp", {"clamp_type": _enum(node.clamp_type)}, {
        "value": "Value", "min": "Min", "max": "Max"}, {"Result": "result"}


def _mix(b, node):
    blend = _enum(node.blend_type)
    if node.data_type == "FLOAT":
        return "mix_float", {"clamp_factor": bool(node.clamp_factor)}, {
            "factor": "Factor_Float", "a": "A_Float", "b": "B_Float"}, {"Result_Float": "result"}
    if node.data_type == "VECTOR":
        fac = "Factor_Float" if node.factor_mode == "UNIFORM" else "Factor_Vector"
        return "mix_vector", {"clamp_factor": bool(node.clamp_factor)}, {
            "factor": fac, "a": "A_Vector", "b": "B_Vector"}, {"Result_Vector": "result"}
    if node.data_type != "RGBA":
        raise Unsupported(f"data type {node.data_type}")
    if blend not in NODE_TYPES["mix_color"].props["blend"].choices:
        raise Unsupported(f"blend mode {node.blend_type}")
    return "mix_color", {"blend": blend, "clamp_factor": bool(node.clamp_factor),
                         "clamp_result": bool(node.clamp_result)}, {
        "factor": "Factor_Float", "a": "A_Color", "b": "B_Color"}, {"Result_Color": "result"}


def _mix_rgb(b, node):
    blend = _enum(node.blend_type)
    if blend not in NODE_TYPES["mix_color"].props["blend"].choices:
        raise Unsupported(f"blend mode {node.blend_type}")
    return "mix_color", {"blend": blend, "clamp_factor": True,
                         "clamp_result": bool(node.use_clamp)}, {
        "factor": "Fac", "a": "Color1", "b": "Color2"}, {"Color": "result"}


def _color_ramp(b, node):
    ramp = node.color_ramp
    if ramp.color_mode != "RGB":
        raise Unsupported(f"colour mode {ramp.color_mode}")
    if ramp.interpolation not in ("LINEAR", "EASE", "CONSTANT"):
        raise Unsupported(f"interpolation {ramp.interpolation}")
    stops = [(float(e.position), _rgb(e.color), float(e.color[3])) for e in ramp.elements]
    return "color_ramp", {"interpolation": _enum(ramp.interpolation), "stops": stops}, {
        "factor": "Fac"}, {"Color": "color", "Alpha": "alpha"}


def _invert(b, node):
    return "invert", {}, {"factor": "Fac", "color": "Color"}, {"Color": "color"}


def _gamma(b, node):
    return "gamma", {}, {"color": "Color", "gamma": "Gamma"}, {"Color": "color"}


def _bright_contrast(b, node):
    return "bright_contrast", {}, {"color": "Color", "bright": "Bright",
                                   "contrast": "Contrast"}, {"Color": "color"}


def _rgb_to_bw(b, node):
    return "rgb_to_bw", {}, {"color": "Color"}, {"Val": "value"}


def _checker(b, node):
    return "checker", {}, {"vector": b.default_coords(node, "generated"), "color1": "Color1",
                           "color2": "Color2", "scale": "Scale"}, {"Color": "color",
                                                                  "Fac": "fac"}


def _gradient(b, node):
    return "gradient", {"gradient_type": _enum(node.gradient_type)}, {
        "vector": b.default_coords(node, "generated")}, {"Color": "color", "Fac": "fac"}


def _noise(b, node):
    if node.noise_dimensions != "3D":
        raise Unsupported(f"{node.noise_dimensions} noise")
    return "noise", {"noise_type": _enum(node.noise_type), "normalize": bool(node.normalize)}, {
        "vector": b.default_coords(node, "generated"), "scale": "Scale", "detail": "Detail",
        "roughness": "Roughness", "lacunarity": "Lacunarity", "offset": "Offset",
        "gain": "Gain", "distortion": "Distortion"}, {"Fac": "fac", "Color": "color"}


def _image_props(b, node) -> dict:
    img = node.image
    if img is None:
        raise Unsupported("no image")
    px = image_pixels(img, linearize=False)
    if px is None:
        raise Unsupported(f"image {img.name!r} has no pixels")
    space = img.colorspace_settings.name
    if not img.is_float and space not in LINEAR_SPACES + ("sRGB",):
        b.warn(f"image {img.name!r}: colour space {space!r} is read as linear")
    interp = _enum(node.interpolation)
    if interp not in ("closest", "linear"):
        b.warn(f"image {node.name!r}: {node.interpolation} interpolation is done as Linear")
        interp = "linear"
    srgb = not img.is_float and img.colorspace_settings.name == "sRGB"
    return {"image": px, "path": img.filepath or None, "interpolation": interp, "srgb": srgb}


def _image(b, node):
    props = _image_props(b, node)
    if node.projection not in ("FLAT", "BOX"):
        raise Unsupported(f"projection {node.projection}")
    props.update(projection=_enum(node.projection), blend=float(node.projection_blend),
                 extension=_enum(node.extension))
    if node.projection == "BOX":
        props["normal_matrix"] = b.normal_matrix()
    return "image", props, {"vector": b.default_coords(node, "uv")}, {"Color": "color"}


def _environment(b, node):
    if node.projection != "EQUIRECTANGULAR":
        raise Unsupported(f"projection {node.projection}")
    return "environment", _image_props(b, node), {
        "vector": b.default_coords(node, "position")}, {"Color": "color"}


def _emission(b, node):
    return "emission", {}, {"color": "Color", "strength": "Strength"}, {"Emission": "emission"}


def _background(b, node):
    return "background", {}, {"color": "Color", "strength": "Strength"}, {
        "Background": "background"}


def _diffuse(b, node):
    return "diffuse", {}, {"color": "Color"}, {"BSDF": "bsdf"}


def _principled(b, node):
    for name in ("Metallic", "Transmission Weight"):
        s = b.input(node, name)
        # a constant metallic is the material's glossy layer (riray_addon/materials.py)
        if s is not None and (s.is_linked or (name != "Metallic" and float(s.default_value) > 0)):
            b.warn(f"node {node.name!r}: {name.lower()} is shaded as diffuse (only the specular "
                   "object reflects)")
    return "principled", {}, {"base_color": "Base Color", "emission_color": "Emission Color",
                              "emission_strength": "Emission Strength"}, {"BSDF": "bsdf"}


def _mix_shader(b, node):
    return "mix_shader", {}, {"factor": "Fac", "shader1": "Shader", "shader2": "Shader_001"}, {
        "Shader": "shader"}


def _add_shader(b, node):
    return "add_shader", {}, {"shader1": "Shader", "shader2": "Shader_001"}, {
        "Shader": "shader"}


TRANSLATORS = {
    "TEX_COORD": _tex_coord, "NEW_GEOMETRY": _geometry, "OBJECT_INFO": _object_info,
    "MAPPING": _mapping, "SEPXYZ": _sep_xyz, "COMBXYZ": _comb_xyz,
    "SEPARATE_COLOR": _sep_color, "SEPRGB": _sep_color, "COMBINE_COLOR": _comb_color,
    "COMBRGB": _comb_color, "MATH": _math, "VECT_MATH": _vector_math, "MAP_RANGE": _map_range,
    "CLAMP": _clamp, "MIX": _mix, "MIX_RGB": _mix_rgb, "VALTORGB": _color_ramp,
    "INVERT": _invert, "GAMMA": _gamma, "BRIGHTCONTRAST": _bright_contrast,
    "RGBTOBW": _rgb_to_bw, "TEX_CHECKER": _checker, "TEX_GRADIENT": _gradient,
    "TEX_IMAGE": _image, "TEX_ENVIRONMENT": _environment, "TEX_NOISE": _noise,
    "EMISSION": _emission,
    "BACKGROUND": _background, "BSDF_DIFFUSE": _diffuse, "BSDF_PRINCIPLED": _principled,
    "MIX_SHADER": _mix_shader, "ADD_SHADER": _add_shader,
}


# --------------------------------------------------------------------------- the builder
class Builder:
    """Translates one node tree; ``warn`` messages are prefixed with ``owner``."""

    def __init__(self, report, owner: str, surface: SurfaceContext | None,
                 camera_matrix: np.ndarray | None):
        self.report, self.owner, self.surface = report, owner, surface
        self.camera = camera_matrix
        self.nodes: dict[str, GraphNode] = {}
        self.outputs: dict[str, dict] = {}     # Blender node name -> output map (None: failed)
        self.object_dependent = False
        self.depth = 0

    def warn(self, msg: str) -> None:
        self.report.warning(f"{self.owner}: {msg}")

    @staticmethod
    def input(node, identifier: str):
        return next((s for s in node.inputs if s.identifier == identifier), None)

    # -- coordinates
    def _world_to_object(self, obj=None) -> np.ndarray:
        if obj is not None:
            return np.linalg.inv(np.array(obj.matrix_world, dtype=np.float64))
        if self.surface is None or self.surface.matrix is None:
            return np.eye(4)
        return np.linalg.inv(self.surface.matrix)

    def normal_matrix(self) -> np.ndarray:
        """A^T for the shaded object's 3 x 3 matrix A: world normals -> object normals."""
        if self.surface is None or self.surface.matrix is None:
            return np.eye(3)
        self.object_dependent = True
        return self.surface.matrix[:3, :3].T.copy()

    def coordinate_props(self, other_object) -> dict:
        """A tex_coord node's matrices (core/scene/graph.py) for the shaded object or the world;
        ``other_object``: the node's Object field."""
        surf = self.surface if self.surface is not None and self.surface.matrix is not None \
            else None
        if surf is not None:
            self.object_dependent = True
        to_obj = self._world_to_object()
        gen = np.eye(4)
        if surf is not None:
            size = np.asarray(surf.texspace_size, dtype=np.float64)
            size = np.where(size != 0, size, 1.0)
            gen[:3, :3] = np.diag(0.5 / size)
            gen[:3, 3] = 0.5 - np.asarray(surf.texspace_location) * 0.5 / size
            gen = gen @ to_obj
        cam = np.eye(4)
        if self.camera is not None:
            cam = CAMERA_FLIP @ np.linalg.inv(self.camera)
            if surf is None:            # the world: directions, so the rotation only
                cam[:3, 3] = 0.0
        return {"generated_matrix": gen, "normal_matrix": self.normal_matrix(),
                "object_matrix": self._world_to_object(other_object) if other_object is not None
                else to_obj, "camera_matrix": cam}

    def default_coords(self, node, which: str):
        """The link a texture node's Vector input gets: its own link when it has one, else
        Cycles' default ("generated", "uv" or "position")."""
        sock = self.input(node, "Vector")
        if sock is not None and source(sock) is not None:
            return "Vector"
        name = f"__{which}__"
        if name not in self.nodes:
            if which == "position":
                self.nodes[name] = GraphNode(name, "geometry")
            else:
                self.nodes[name] = GraphNode(name, "tex_coord", props=self.coordinate_props(None))
        return Link(name, which)

    # -- values
    @staticmethod
    def constant(socket, kind: str):
        """A socket's own value as a core constant of ``kind`` (None for shaders), converted as
        a link would be: colour -> float the luminance, vector -> float the mean."""
        dv = getattr(socket, "default_value", None)
        if dv is None:
            return None
        if kind == FLOAT:
            if np.ndim(dv) == 0:
                return float(dv)
            rgb = np.array(_rgb(dv))
            return float(rgb @ np.asarray(LUMA) if socket.type == "RGBA" else rgb.mean())
        if np.ndim(dv) == 0:
            return (float(dv),) * 3
        return _rgb(dv)

    def value(self, socket, kind: str):
        """A constant or a Link for a core input of ``kind`` fed by Blender input ``socket``."""
        src = source(socket)
        if src is None:
            return self.constant(socket, kind)
        node, out = src
        if node.type in ("VALUE", "RGB"):
            return self.constant(out, kind)
        link = self.translate(node, out)
        return link if link is not None else self.constant(socket, kind)

    def translate(self, node, out) -> Link | None:
        """The Link for output ``out`` of Blender ``node`` (translated once); None with a
        warning when core cannot evaluate it."""
        if node.name not in self.outputs:
            self.outputs[node.name] = self._translate(node)
        outs = self.outputs[node.name]
        if outs is None:
            return None
        if out.identifier not in outs:
            self.warn(f"output {out.name!r} of node {node.name!r} ({node.type}) is not "
                      "supported; using the value of the socket it feeds")
            return None
        return Link(node.name, outs[out.identifier])

    def _translate(self, node):
        fn = TRANSLATORS.get(node.type)
        shader_like = fn is None and any(o.type == "SHADER" for o in node.outputs)
        if shader_like:
            self.warn(f"shader {node.name!r} ({node.type}) is shaded as diffuse with its Color "
                      "(only the specular object reflects)")
            fn = _as_diffuse
        if fn is None or self.depth > MAX_NESTING:
            self.warn(f"node {node.name!r} ({node.type}) is not supported; using the value of "
                      "the socket it feeds")
            return None
        try:
            ctype, props, ins, outs = fn(self, node)
        except Unsupported as exc:
            self.warn(f"node {node.name!r} ({node.type}): {exc} is not supported; using the "
                      "value of the socket it feeds")
            return None
        self.depth += 1
        spec = NODE_TYPES[ctype]
        inputs, links = {}, {}
        for key, ref in ins.items():
            kind = spec.inputs[key][0]
            if isinstance(ref, Link):
                links[key] = ref
                continue
            sock = self.input(node, ref)
            v = self.value(sock, kind) if sock is not None else None
            if isinstance(v, Link):
                links[key] = v
            elif v is not None:
                inputs[key] = v
        self.depth -= 1
        if shader_like:
            outs = {o.identifier: "bsdf" for o in node.outputs if o.type == "SHADER"}
        self.nodes[node.name] = GraphNode(node.name, ctype, inputs, links, props)
        return outs

    def graph(self, socket) -> ShaderGraph | None:
        """The graph whose output is what ``socket`` (a Surface input) receives; None when
        nothing core can shade is linked."""
        out = self.value(socket, SHADER)
        if not isinstance(out, Link):
            return None
        try:
            return ShaderGraph(nodes=list(self.nodes.values()), output=out)
        except GraphError as exc:     # a translator bug, not the user's: report, do not crash
            self.warn(f"node graph not exported ({exc})")
            return None


def _as_diffuse(b, node):
    ins = {"color": "Color"} if b.input(node, "Color") is not None else {}
    return "diffuse", {}, ins, {}


def _output_surface(tree):
    out = output_node(tree) if tree is not None else None
    return None if out is None else out.inputs["Surface"]


def surface_graph(tree, report, owner: str, surface: SurfaceContext,
                  camera_matrix) -> tuple[ShaderGraph | None, bool]:
    """(graph of a material's node tree, whether it depends on the shaded object)."""
    sock = _output_surface(tree)
    if sock is None:
        return None, False
    b = Builder(report, owner, surface, camera_matrix)
    return b.graph(sock), b.object_dependent


def world_graph(tree, report, owner: str, camera_matrix) -> ShaderGraph | None:
    sock = _output_surface(tree)
    if sock is None:
        return None
    return Builder(report, owner, None, camera_matrix).graph(sock)
