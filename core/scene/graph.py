"""Shader node graphs for environment surfaces and the world (docs/scene-format.md, "graph").

A :class:`ShaderGraph` is a small dataflow graph of typed nodes, the subset of Blender's shader
nodes that environments are built from; ``riray.trace.nodes`` evaluates it, vectorized over all
shading points at once. This module holds the node types (:data:`NODE_TYPES`: inputs with their
kind and default, outputs with their kind, properties), the model and its validation, and the
conversion from / to the JSON form. It never imports bpy.

Socket kinds: "float" (N,), "vector" and "color" (N, 3), "shader" (a closure: emitted radiance
plus a diffuse albedo). A link may join different kinds; the value is converted as Cycles does:
float -> vector/color (f, f, f); color -> float the luminance LUMA . c; vector -> float the
mean of the components; vector <-> color unchanged; float/vector/color -> shader an emission of
that colour with strength 1. Shader outputs link only to shader inputs.

Errors raise :class:`GraphError`, whose ``where`` is the path inside the graph's JSON form
(``nodes[3].inputs.b``) and whose message names the node.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

GRAPH_VERSION = 1
FLOAT, VECTOR, COLOR, SHADER = "float", "vector", "color", "shader"
# Rec. 709 luminance (Blender's default scene-linear space): colour -> float conversion.
LUMA = (0.2126729, 0.7151522, 0.0721750)
MAX_STOPS = 32          # Blender's colour ramps hold at most 32 stops
MAX_NUMBER = 1e12       # every number, as in the rest of the scene format (validate.MAX_NUMBER)
MAX_NODES = 4096        # a graph bigger than this is a mistake, not an environment
IDENTITY4 = tuple(tuple(float(i == j) for j in range(4)) for i in range(4))
IDENTITY3 = tuple(tuple(float(i == j) for j in range(3)) for i in range(3))

MATH_OPS = ("add", "subtract", "multiply", "divide", "multiply_add", "power", "logarithm",
            "sqrt", "inverse_sqrt", "absolute", "exponent", "minimum", "maximum", "less_than",
            "greater_than", "sign", "compare", "smooth_min", "smooth_max", "round", "floor",
            "ceil", "trunc", "fract", "modulo", "floored_modulo", "wrap", "snap", "pingpong",
            "sine", "cosine", "tangent", "arcsine", "arccosine", "arctangent", "arctan2",
            "sinh", "cosh", "tanh", "radians", "degrees")
VECTOR_MATH_OPS = ("add", "subtract", "multiply", "divide", "multiply_add", "cross_product",
                   "project", "reflect", "refract", "faceforward", "dot_product", "distance",
                   "length", "scale", "normalize", "absolute", "power", "sign", "minimum",
                   "maximum", "floor", "ceil", "fraction", "modulo", "wrap", "snap", "sine",
                   "cosine", "tangent")
BLEND_MODES = ("mix", "darken", "multiply", "burn", "lighten", "screen", "dodge", "add",
               "overlay", "soft_light", "linear_light", "difference", "exclusion", "subtract",
               "divide")
EXTENSIONS = ("repeat", "extend", "clip", "mirror")
NOISE_TYPES = ("fbm", "multifractal", "hybrid_multifractal", "ridged_multifractal",
               "hetero_terrain")
INTERPOLATIONS = ("closest", "linear")


@dataclass(frozen=True)
class Prop:
    """A node property: kind "enum" (``choices``), "bool", "number", "vec3", "matrix4"
    (4 x 4, bottom row 0 0 0 1), "matrix3", "stops" (colour ramp) or "image"."""

    kind: str
    default: Any = None
    choices: tuple = ()


@dataclass(frozen=True)
class NodeType:
    inputs: dict            # name -> (kind, default)
    outputs: dict           # name -> kind
    props: dict = field(default_factory=dict)   # name -> Prop


def _t(inputs=(), outputs=(), **props) -> NodeType:
    return NodeType(dict(inputs), dict(outputs), props)


_V0, _V1, _GREY = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (0.8, 0.8, 0.8)
_IMAGE_PROPS = dict(image=Prop("image"), interpolation=Prop("enum", "linear", INTERPOLATIONS),
                    srgb=Prop("bool", False))

NODE_TYPES: dict[str, NodeType] = {
    # -- inputs: where the shading point is
    "tex_coord": _t(outputs=[("generated", VECTOR), ("normal", VECTOR), ("uv", VECTOR),
                             ("object", VECTOR), ("camera", VECTOR), ("reflection", VECTOR)],
                    generated_matrix=Prop("matrix4", IDENTITY4),
                    normal_matrix=Prop("matrix3", IDENTITY3),
                    object_matrix=Prop("matrix4", IDENTITY4),
                    camera_matrix=Prop("matrix4", IDENTITY4)),
    "geometry": _t(outputs=[("position", VECTOR), ("normal", VECTOR), ("true_normal", VECTOR),
                            ("incoming", VECTOR), ("backfacing", FLOAT)]),
    "object_info": _t(outputs=[("location", VECTOR), ("color", COLOR), ("alpha", FLOAT),
                               ("object_index", FLOAT), ("material_index", FLOAT),
                               ("random", FLOAT)],
                      location=Prop("vec3", _V0), color=Prop("vec3", _V1),
                      alpha=Prop("number", 1.0), object_index=Prop("number", 0.0),
                      material_index=Prop("number", 0.0), random=Prop("number", 0.0)),
    # -- vectors and numbers
    "mapping": _t([("vector", (VECTOR, _V0)), ("location", (VECTOR, _V0)),
                   ("rotation", (VECTOR, _V0)), ("scale", (VECTOR, _V1))],
                  [("vector", VECTOR)],
                  vector_type=Prop("enum", "point", ("point", "texture", "vector", "normal"))),
    "separate_xyz": _t([("vector", (VECTOR, _V0))], [("x", FLOAT), ("y", FLOAT), ("z", FLOAT)]),
    "combine_xyz": _t([("x", (FLOAT, 0.0)), ("y", (FLOAT, 0.0)), ("z", (FLOAT, 0.0))],
                      [("vector", VECTOR)]),
    "separate_color": _t([("color", (COLOR, _GREY))],
                         [("red", FLOAT), ("green", FLOAT), ("blue", FLOAT)]),
    "combine_color": _t([("red", (FLOAT, 0.0)), ("green", (FLOAT, 0.0)), ("blue", (FLOAT, 0.0))],
                        [("color", COLOR)]),
    "math": _t([("a", (FLOAT, 0.5)), ("b", (FLOAT, 0.5)), ("c", (FLOAT, 0.5))],
               [("value", FLOAT)],
               operation=Prop("enum", "add", MATH_OPS), clamp=Prop("bool", False)),
    "vector_math": _t([("a", (VECTOR, _V0)), ("b", (VECTOR, _V0)), ("c", (VECTOR, _V0)),
                       ("scale", (FLOAT, 1.0))],
                      [("vector", VECTOR), ("value", FLOAT)],
                      operation=Prop("enum", "add", VECTOR_MATH_OPS)),
    "map_range": _t([("value", (FLOAT, 1.0)), ("from_min", (FLOAT, 0.0)),
                     ("from_max", (FLOAT, 1.0)), ("to_min", (FLOAT, 0.0)),
                     ("to_max", (FLOAT, 1.0)), ("steps", (FLOAT, 4.0))],
                    [("result", FLOAT)],
                    interpolation=Prop("enum", "linear", ("linear", "stepped", "smoothstep",
                                                          "smootherstep")),
                    clamp=Prop("bool", True)),
    "map_range_vector": _t([("vector", (VECTOR, _V0)), ("from_min", (VECTOR, _V0)),
                            ("from_max", (VECTOR, _V1)), ("to_min", (VECTOR, _V0)),
                            ("to_max", (VECTOR, _V1)), ("steps", (VECTOR, (4.0, 4.0, 4.0)))],
                           [("vector", VECTOR)],
                           interpolation=Prop("enum", "linear", ("linear", "stepped",
                                                                 "smoothstep", "smootherstep")),
                           clamp=Prop("bool", True)),
    "clamp": _t([("value", (FLOAT, 1.0)), ("min", (FLOAT, 0.0)), ("max", (FLOAT, 1.0))],
                [("result", FLOAT)], clamp_type=Prop("enum", "minmax", ("minmax", "range"))),
    # -- colours
    "mix_float": _t([("factor", (FLOAT, 0.5)), ("a", (FLOAT, 0.0)), ("b", (FLOAT, 0.0))],
                    [("result", FLOAT)], clamp_factor=Prop("bool", True)),
    "mix_vector": _t([("factor", (VECTOR, (0.5, 0.5, 0.5))), ("a", (VECTOR, _V0)),
                      ("b", (VECTOR, _V0))],
                     [("result", VECTOR)], clamp_factor=Prop("bool", True)),
    "mix_color": _t([("factor", (FLOAT, 0.5)), ("a", (COLOR, (0.5, 0.5, 0.5))),
                     ("b", (COLOR, (0.5, 0.5, 0.5)))],
                    [("result", COLOR)], blend=Prop("enum", "mix", BLEND_MODES),
                    clamp_factor=Prop("bool", True), clamp_result=Prop("bool", False)),
    "color_ramp": _t([("factor", (FLOAT, 0.5))], [("color", COLOR), ("alpha", FLOAT)],
                     interpolation=Prop("enum", "linear", ("linear", "ease", "constant")),
                     stops=Prop("stops", ((0.0, (0.0, 0.0, 0.0), 1.0),
                                          (1.0, (1.0, 1.0, 1.0), 1.0)))),
    "invert": _t([("factor", (FLOAT, 1.0)), ("color", (COLOR, _V0))], [("color", COLOR)]),
    "gamma": _t([("color", (COLOR, _V1)), ("gamma", (FLOAT, 1.0))], [("color", COLOR)]),
    "bright_contrast": _t([("color", (COLOR, _V1)), ("bright", (FLOAT, 0.0)),
                           ("contrast", (FLOAT, 0.0))], [("color", COLOR)]),
    "rgb_to_bw": _t([("color", (COLOR, (0.5, 0.5, 0.5)))], [("value", FLOAT)]),
    # -- textures
    "checker": _t([("vector", (VECTOR, _V0)), ("color1", (COLOR, _GREY)),
                   ("color2", (COLOR, (0.2, 0.2, 0.2))), ("scale", (FLOAT, 5.0))],
                  [("color", COLOR), ("fac", FLOAT)]),
    "gradient": _t([("vector", (VECTOR, _V0))], [("color", COLOR), ("fac", FLOAT)],
                   gradient_type=Prop("enum", "linear", ("linear", "quadratic", "easing",
                                                         "diagonal", "spherical",
                                                         "quadratic_sphere", "radial"))),
    "image": _t([("vector", (VECTOR, _V0))], [("color", COLOR)],
                projection=Prop("enum", "flat", ("flat", "box")), blend=Prop("number", 0.0),
                extension=Prop("enum", "repeat", EXTENSIONS),
                normal_matrix=Prop("matrix3", IDENTITY3), **_IMAGE_PROPS),
    "environment": _t([("vector", (VECTOR, _V0))], [("color", COLOR)], **_IMAGE_PROPS),
    "noise": _t([("vector", (VECTOR, _V0)), ("scale", (FLOAT, 5.0)), ("detail", (FLOAT, 2.0)),
                 ("roughness", (FLOAT, 0.5)), ("lacunarity", (FLOAT, 2.0)),
                 ("offset", (FLOAT, 0.0)), ("gain", (FLOAT, 1.0)),
                 ("distortion", (FLOAT, 0.0))], [("fac", FLOAT), ("color", COLOR)],
                noise_type=Prop("enum", "fbm", NOISE_TYPES), normalize=Prop("bool", True)),
    # -- shaders
    "emission": _t([("color", (COLOR, _V1)), ("strength", (FLOAT, 1.0))],
                   [("emission", SHADER)]),
    "background": _t([("color", (COLOR, _GREY)), ("strength", (FLOAT, 1.0))],
                     [("background", SHADER)]),
    "diffuse": _t([("color", (COLOR, _GREY))], [("bsdf", SHADER)]),
    "principled": _t([("base_color", (COLOR, _GREY)), ("emission_color", (COLOR, _V1)),
                      ("emission_strength", (FLOAT, 0.0))], [("bsdf", SHADER)]),
    "mix_shader": _t([("factor", (FLOAT, 0.5)), ("shader1", (SHADER, None)),
                      ("shader2", (SHADER, None))], [("shader", SHADER)]),
    "add_shader": _t([("shader1", (SHADER, None)), ("shader2", (SHADER, None))],
                     [("shader", SHADER)]),
}


class GraphError(ValueError):
    """An invalid graph; ``where`` is the path of the field inside the graph's JSON form."""

    def __init__(self, where: str, msg: str):
        super().__init__(f"{where}: {msg}" if where else msg)
        self.where, self.msg = where, msg


@dataclass(frozen=True)
class Link:
    """The output ``output`` of the node called ``node``."""

    node: str
    output: str


@dataclass
class GraphNode:
    """One node: ``inputs`` maps input names to constants (float, or a 3-tuple for vectors and
    colours), ``links`` input names to Links (a linked input's constant is not used); unset
    inputs and props take the type's defaults. Image props hold ``image`` (H, W, 3 float64,
    rows top first) and ``path``."""

    name: str
    type: str
    inputs: dict = field(default_factory=dict)
    links: dict = field(default_factory=dict)
    props: dict = field(default_factory=dict)


@dataclass
class ShaderGraph:
    """A validated graph: ``nodes`` in evaluation order (every node after the nodes it reads),
    defaults filled in; ``output`` is the link whose value the surface / world shows."""

    nodes: list
    output: Link
    version: int = GRAPH_VERSION

    def __post_init__(self):
        self.nodes = _checked(self.nodes, self.output)


# --------------------------------------------------------------------------- validation
def _what(i: int, node) -> str:
    return f"node {node.name!r}" if getattr(node, "name", None) else f"node {i}"


def _const(value, kind: str, where: str, who: str):
    """A constant for an input of ``kind``: float for float, 3-tuple of floats otherwise."""
    if kind == SHADER:
        raise GraphError(where, f"{who}: a shader input takes a link, not a value")
    if kind == FLOAT:
        if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
            raise GraphError(where, f"{who}: expected a number (got {value!r})")
        x = float(value)
        if not np.isfinite(x) or abs(x) > MAX_NUMBER:
            raise GraphError(where, f"{who}: must be finite, magnitude <= {MAX_NUMBER:g} "
                                    f"(got {x!r})")
        return x
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != (3,) or isinstance(value, (str, bytes)):
        raise GraphError(where, f"{who}: expected 3 numbers (got {value!r})")
    if not np.isfinite(arr).all() or np.abs(arr).max() > MAX_NUMBER:
        raise GraphError(where, f"{who}: must be finite, magnitude <= {MAX_NUMBER:g} "
                                f"(got {value!r})")
    return tuple(float(x) for x in arr)


def _prop(value, prop: Prop, where: str, who: str):
    k = prop.kind
    if k == "enum":
        if value not in prop.choices:
            raise GraphError(where, f"{who}: unknown value {value!r} (expected one of: "
                                    f"{', '.join(prop.choices)})")
        return value
    if k == "bool":
        if not isinstance(value, (bool, np.bool_)):
            raise GraphError(where, f"{who}: expected true or false (got {value!r})")
        return bool(value)
    if k == "number":
        return _const(value, FLOAT, where, who)
    if k == "vec3":
        return _const(value, VECTOR, where, who)
    if k in ("matrix4", "matrix3"):
        n = 4 if k == "matrix4" else 3
        try:
            m = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            m = None
        if m is None or m.shape != (n, n) or not np.isfinite(m).all() or \
                np.abs(m).max() > MAX_NUMBER:
            raise GraphError(where, f"{who}: expected a {n} x {n} matrix of finite numbers "
                                    f"(magnitude <= {MAX_NUMBER:g})")
        if n == 4 and m[3].tolist() != [0.0, 0.0, 0.0, 1.0]:
            raise GraphError(where, f"{who}: bottom row must be [0, 0, 0, 1] "
                                    f"(got {m[3].tolist()})")
        return m
    if k == "stops":
        stops = list(value) if isinstance(value, (list, tuple)) else None
        if not stops or len(stops) > MAX_STOPS:
            raise GraphError(where, f"{who}: expected 1 to {MAX_STOPS} stops")
        out = []
        for j, s in enumerate(stops):
            w = f"{where}[{j}]"
            if not isinstance(s, (list, tuple)) or len(s) != 3:
                raise GraphError(w, f"{who}: a stop is (position, colour, alpha)")
            pos = _const(s[0], FLOAT, w, who)
            if not 0.0 <= pos <= 1.0:
                raise GraphError(w, f"{who}: stop position must lie in [0, 1] (got {pos!r})")
            if out and pos < out[-1][0]:
                raise GraphError(w, f"{who}: stop positions must be non-decreasing "
                                    f"(got {pos!r} after {out[-1][0]!r})")
            out.append((pos, _const(s[1], COLOR, w, who), _const(s[2], FLOAT, w, who)))
        return tuple(out)
    raise AssertionError(k)


def _checked(nodes: list, output: Link) -> list:
    """Validate names, types, inputs, props and links; fill defaults; order topologically."""
    if not isinstance(nodes, (list, tuple)) or not nodes:
        raise GraphError("nodes", "a graph needs at least one node")
    if len(nodes) > MAX_NODES:
        raise GraphError("nodes", f"more than {MAX_NODES} nodes")
    by_name = {}
    for i, n in enumerate(nodes):
        where = f"nodes[{i}]"
        if not isinstance(n.name, str) or not n.name:
            raise GraphError(f"{where}.name", f"node {i}: expected a non-empty name")
        if n.name in by_name:
            raise GraphError(f"{where}.name", f"duplicate node name {n.name!r}")
        if n.type not in NODE_TYPES:
            raise GraphError(f"{where}.type", f"{_what(i, n)}: unknown node type {n.type!r} "
                                              f"(known: {', '.join(NODE_TYPES)})")
        by_name[n.name] = (i, n)
    for i, n in enumerate(nodes):
        spec, who, where = NODE_TYPES[n.type], _what(i, n), f"nodes[{i}]"
        for key in list(n.inputs) + list(n.links):
            if key not in spec.inputs:
                raise GraphError(f"{where}.inputs.{key}", f"{who}: {n.type} has no input "
                                 f"{key!r} (inputs: {', '.join(spec.inputs) or 'none'})")
        for key in n.props:
            if key not in spec.props and not (key == "path" and "image" in spec.props):
                raise GraphError(f"{where}.{key}", f"{who}: {n.type} has no property {key!r}"
                                 f" (properties: {', '.join(spec.props) or 'none'})")
        inputs = {}
        for key, (kind, default) in spec.inputs.items():
            w = f"{where}.inputs.{key}"
            if key in n.links:
                _check_link(n.links[key], kind, by_name, w, who)
                continue
            v = n.inputs.get(key, default)
            if v is not None:
                inputs[key] = _const(v, kind, w, who)
        props = {}
        for key, prop in spec.props.items():
            if prop.kind == "image":
                img = n.props.get("image")
                if not isinstance(img, np.ndarray) or img.ndim != 3 or img.shape[2] != 3 \
                        or min(img.shape[:2]) < 1:
                    raise GraphError(f"{where}.path", f"{who}: the image is not loaded "
                                                      "(expected H x W x 3 pixels)")
                props["image"] = img
                props["path"] = n.props.get("path")
                continue
            props[key] = _prop(n.props.get(key, prop.default), prop, f"{where}.{key}", who)
        n.inputs, n.props = inputs, props
    _check_link(output, SHADER, by_name, "output", "the graph output")
    return _topological(nodes, by_name, output)


def _check_link(link: Link, kind: str, by_name: dict, where: str, who: str) -> None:
    if not isinstance(getattr(link, "node", None), str) or \
            not isinstance(getattr(link, "output", None), str):
        raise GraphError(where, f"{who}: expected a link to a node output (got {link!r})")
    if link.node not in by_name:
        raise GraphError(where, f"{who}: link from unknown node {link.node!r}")
    src = by_name[link.node][1]
    outs = NODE_TYPES[src.type].outputs
    if link.output not in outs:
        raise GraphError(where, f"{who}: node {src.name!r} ({src.type}) has no output "
                                f"{link.output!r} (outputs: {', '.join(outs)})")
    if outs[link.output] == SHADER and kind != SHADER:
        raise GraphError(where, f"{who}: a shader output ({src.name!r}.{link.output}) cannot "
                                f"feed a {kind} input")


def _topological(nodes: list, by_name: dict, output: Link) -> list:
    """Nodes in an order where each follows those it reads (GraphError on a cycle)."""
    state, order = {}, []

    def visit(name: str, chain: tuple):
        st = state.get(name)
        if st == 2:
            return
        if st == 1:
            cyc = " -> ".join(chain[chain.index(name):] + (name,))
            i = by_name[name][0]
            raise GraphError(f"nodes[{i}]", f"the graph has a cycle: {cyc}")
        state[name] = 1
        node = by_name[name][1]
        for v in node.links.values():
            visit(v.node, chain + (name,))
        state[name] = 2
        order.append(node)

    for n in nodes:
        visit(n.name, ())
    return order


# --------------------------------------------------------------------------- JSON form
NODE_KEYS = ("name", "type", "inputs")


def graph_from_dict(d, load_image: Callable[[str, str, bool], np.ndarray]) -> ShaderGraph:
    """The ShaderGraph of a JSON-shaped dict; ``load_image(path, where, encoded)`` returns the
    pixels of an image file (H, W, 3 float64: linear, or sRGB-encoded as stored for ``encoded``,
    the image nodes with ``srgb``). Raises GraphError."""
    if not isinstance(d, dict):
        raise GraphError("", "expected an object with version, nodes and output")
    for key in d:
        if key not in ("version", "nodes", "output"):
            raise GraphError("", f"unknown key {key!r} (allowed: version, nodes, output)")
    for key in ("version", "nodes", "output"):
        if key not in d:
            raise GraphError("", f"missing required key {key!r}")
    if d["version"] != GRAPH_VERSION or type(d["version"]) is not int:
        raise GraphError("version", f"unsupported graph version {d['version']!r} (this riray "
                                    f"reads version {GRAPH_VERSION})")
    raw = d["nodes"]
    if not isinstance(raw, list):
        raise GraphError("nodes", "expected a list of nodes")
    nodes = [_node_from_dict(v, i, load_image) for i, v in enumerate(raw)]
    return ShaderGraph(nodes=nodes, output=_link_from_dict(d["output"], "output", "the output"))


def _link_from_dict(v, where: str, who: str) -> Link:
    if not isinstance(v, dict) or set(v) != {"node", "output"} or not all(
            isinstance(v[k], str) for k in v):
        raise GraphError(where, f"{who}: a link is {{\"node\": name, \"output\": name}} "
                                f"(got {v!r})")
    return Link(v["node"], v["output"])


def _node_from_dict(v, i: int, load_image) -> GraphNode:
    where = f"nodes[{i}]"
    if not isinstance(v, dict):
        raise GraphError(where, f"node {i}: expected an object")
    for key in ("name", "type"):
        if not isinstance(v.get(key), str) or not v.get(key):
            raise GraphError(f"{where}.{key}", f"node {i}: missing or empty {key!r}")
    node = GraphNode(name=v["name"], type=v["type"])
    who = _what(i, node)
    spec = NODE_TYPES.get(node.type)
    if spec is None:
        raise GraphError(f"{where}.type", f"{who}: unknown node type {node.type!r} (known: "
                                          f"{', '.join(NODE_TYPES)})")
    inputs = v.get("inputs", {})
    if not isinstance(inputs, dict):
        raise GraphError(f"{where}.inputs", f"{who}: expected an object of inputs")
    for key, val in inputs.items():
        if isinstance(val, dict):
            node.links[key] = _link_from_dict(val, f"{where}.inputs.{key}", who)
        else:
            node.inputs[key] = val
    for key, val in v.items():
        if key in NODE_KEYS:
            continue
        if key == "path" and "image" in spec.props:
            if not isinstance(val, str) or not val:
                raise GraphError(f"{where}.path", f"{who}: expected an image file path")
            node.props["path"] = val
            node.props["image"] = load_image(val, f"{where}.path", v.get("srgb") is True)
        elif key in spec.props and spec.props[key].kind == "image":
            raise GraphError(f"{where}.{key}", f"{who}: give the image as \"path\"")
        elif key in spec.props and spec.props[key].kind == "stops":
            node.props[key] = _stops_from_dict(val, f"{where}.{key}", who)
        else:
            node.props[key] = val
    if "image" in spec.props and "path" not in node.props:
        raise GraphError(where, f"{who}: missing required key 'path' (the image file)")
    return node


def _stops_from_dict(val, where: str, who: str) -> list:
    """JSON stops ``[{"position": p, "color": [r, g, b], "alpha": a}, ...]`` -> tuples."""
    if not isinstance(val, list):
        raise GraphError(where, f"{who}: expected a list of stops")
    out = []
    for j, s in enumerate(val):
        if not isinstance(s, dict) or not {"position", "color"} <= set(s) <= {
                "position", "color", "alpha"}:
            raise GraphError(f"{where}[{j}]", f"{who}: a stop is {{\"position\": p, "
                                              f"\"color\": [r, g, b], \"alpha\": a}}")
        out.append((s["position"], s["color"], s.get("alpha", 1.0)))
    return out


def _json_value(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, tuple):
        return [_json_value(x) for x in v]
    return v


def graph_to_dict(g: ShaderGraph) -> dict:
    """The canonical JSON form (every input and property written; images by path)."""
    nodes = []
    for n in g.nodes:
        d = {"name": n.name, "type": n.type,
             "inputs": {k: _json_value(n.inputs[k]) if k in n.inputs else _link_dict(n.links[k])
                        for k in NODE_TYPES[n.type].inputs if k in n.inputs or k in n.links}}
        for key, val in n.props.items():
            if key == "image":
                continue
            if key == "path":
                if not val:
                    raise GraphError("", f"node {n.name!r}: an image needs a path to be saved")
            if key == "stops":
                val = [{"position": p, "color": list(c), "alpha": a} for p, c, a in val]
            d[key] = _json_value(val)
        nodes.append(d)
    return {"version": g.version, "nodes": nodes, "output": _link_dict(g.output)}


def _link_dict(link) -> dict:
    return {"node": link.node, "output": link.output}
