"""Shader node graphs (riray.scene.graph, riray.trace.nodes) against closed forms: every node
type on points whose answer is known by hand, the shading of graph materials and worlds, and
the scene format's validation and round trip."""

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from riray.scene import io
from riray.scene.graph import (LUMA, MATH_OPS, NODE_TYPES, GraphError, GraphNode, Link,
                               ShaderGraph, graph_from_dict, graph_to_dict)
from riray.scene.model import Light, Material, Mesh, Patch, Scene, SpecularObject, World
from riray.trace.nodes import RAMP_TABLE, ShadingPoints, evaluate, sample_image, srgb_to_linear
from riray.trace.shading import Environment
from riray.trace.textures import eval_world

EPS = 1e-12         # float64 evaluation of closed forms: rounding only


def points(p, n=None, uv=None, back=None):
    """Shading points at positions p (N, 3) with normal n (default +z), incoming = normal."""
    p = np.atleast_2d(np.asarray(p, float))
    n = np.broadcast_to(np.asarray((0, 0, 1.0) if n is None else n, float), p.shape).copy()
    uv = np.zeros((len(p), 2)) if uv is None else np.asarray(uv, float)
    back = np.zeros(len(p), bool) if back is None else np.asarray(back)
    return ShadingPoints(position=p, normal=n, true_normal=n, incoming=n, uv=uv,
                         backfacing=back)


def emit(nodes, link, pts):
    """Emission (N, 3) of a graph whose ``link`` (any kind) is the emission colour."""
    nodes = list(nodes) + [GraphNode("out", "emission", links={"color": link})]
    return evaluate(ShaderGraph(nodes=nodes, output=Link("out", "emission")), pts).emission


def one(node_type, output, inputs=None, links=None, extra=(), pts=None, **props):
    """The value (N, 3) of ``output`` of one node (float outputs come back as (f, f, f))."""
    node = GraphNode("n", node_type, inputs=dict(inputs or {}), links=dict(links or {}),
                     props=props)
    return emit(list(extra) + [node], Link("n", output), pts if pts is not None else points([0, 0, 0]))


def sep(i):
    """Links that read coordinate i of the position (a Separate XYZ node named 'p')."""
    return Link("p", "xyz"[i])


POS = [GraphNode("g", "geometry"), GraphNode("p", "separate_xyz",
                                             links={"vector": Link("g", "position")})]


# --------------------------------------------------------------------------- math
def _math_closed_form(op, a, b, c):
    """Blender's documented Math node results, scalar by scalar."""
    if op == "divide":
        return a / b if b != 0 else 0.0
    if op == "power":
        return 0.0 if a < 0 and b != int(b) else a ** b
    if op == "logarithm":
        return math.log(a) / math.log(b) if a > 0 and b > 0 and b != 1 else 0.0
    if op == "sqrt":
        return math.sqrt(max(a, 0.0))
    if op == "inverse_sqrt":
        return 1 / math.sqrt(a) if a > 0 else 0.0
    if op == "compare":
        return float(abs(a - b) <= max(c, 1.1920929e-07))
    if op in ("smooth_min", "smooth_max"):
        s = 1 if op == "smooth_min" else -1
        x, y = s * a, s * b
        h = max(c - abs(x - y), 0.0) / c if c else 0.0
        return s * (min(x, y) - h ** 3 * c / 6)
    if op == "round":
        return math.floor(a + 0.5)
    if op == "modulo":
        return math.fmod(a, b) if b else 0.0
    if op == "floored_modulo":
        return a - math.floor(a / b) * b if b else 0.0
    if op == "wrap":      # into [c, b)
        return a - (b - c) * math.floor((a - c) / (b - c)) if b != c else c
    if op == "snap":
        return math.floor(a / b) * b if b else 0.0
    if op == "pingpong":  # triangle wave 0 -> b -> 0 of period 2 b
        return abs(((a - b) / (2 * b)) % 1 * 2 * b - b) if b else 0.0
    if op == "arcsine":
        return math.asin(min(max(a, -1), 1))
    if op == "arccosine":
        return math.acos(min(max(a, -1), 1))
    simple = {"add": a + b, "subtract": a - b, "multiply": a * b, "multiply_add": a * b + c,
              "absolute": abs(a), "exponent": math.exp(a), "minimum": min(a, b),
              "maximum": max(a, b), "less_than": float(a < b), "greater_than": float(a > b),
              "sign": float(a > 0) - float(a < 0), "floor": math.floor(a), "ceil": math.ceil(a),
              "trunc": float(math.trunc(a)), "fract": a - math.floor(a), "sine": math.sin(a),
              "cosine": math.cos(a), "tangent": math.tan(a), "arctangent": math.atan(a),
              "arctan2": math.atan2(a, b), "sinh": math.sinh(a), "cosh": math.cosh(a),
              "tanh": math.tanh(a), "radians": math.radians(a), "degrees": math.degrees(a)}
    return simple[op]


MATH_SAMPLES = [(0.7, 2.0, 0.3), (-1.3, 0.5, 0.4), (2.5, -1.5, 1.0), (-0.4, 0.0, 0.0),
                (3.0, 3.0, 0.5), (0.0, 2.5, -1.0), (-2.7, -0.8, 0.25), (1.0, 1.0 + 1e-8, 0.0)]


@pytest.mark.parametrize("op", MATH_OPS)
def test_math_operations(op):
    """Every Math operation on values with a zero divisor, negative bases, equal operands: the
    a, b, c inputs come from the position, so one graph answers all samples at once."""
    p = np.array(MATH_SAMPLES)
    got = one("math", "value", links={"a": sep(0), "b": sep(1), "c": sep(2)}, extra=POS,
              pts=points(p), operation=op)[:, 0]
    want = [_math_closed_form(op, *s) for s in MATH_SAMPLES]
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=EPS)


def test_math_clamp_and_non_finite_results():
    p = points([[3.0, 2.0, 0], [-3.0, 2.0, 0], [0.0, -1.0, 0]])
    got = one("math", "value", links={"a": sep(0), "b": sep(1)}, extra=POS, pts=p,
              operation="multiply", clamp=True)[:, 0]
    np.testing.assert_array_equal(got, [1.0, 0.0, 0.0])
    # 0 ** -1 is inf in floating point; non-finite components become 0, as in Cycles
    got = one("math", "value", links={"a": sep(0), "b": sep(1)}, extra=POS, pts=p,
              operation="power")[:, 0]
    np.testing.assert_allclose(got, [9.0, 9.0, 0.0])


# --------------------------------------------------------------------------- vector math
A, B, C = np.array([0.3, -1.2, 2.0]), np.array([0.0, 0.6, 0.8]), np.array([1.0, -2.0, 0.5])


def _vec(op, scale=1.0, output="vector"):
    nodes = [GraphNode("v", "vector_math", inputs={"a": tuple(A), "b": tuple(B), "c": tuple(C),
                                                    "scale": scale}, props={"operation": op})]
    return emit(nodes, Link("v", output), points([0, 0, 0]))[0]


def test_vector_math_closed_forms():
    n = B / np.linalg.norm(B)
    per_axis = lambda op: [_math_closed_form(op, *abc) for abc in zip(A, B, C)]  # noqa: E731
    cases = {
        "cross_product": np.cross(A, B), "project": np.dot(A, B) / np.dot(B, B) * B,
        "reflect": A - 2 * np.dot(A, n) * n, "faceforward": A if np.dot(C, B) < 0 else -A,
        "scale": A * 2.5, "normalize": A / np.linalg.norm(A), "absolute": np.abs(A),
        "multiply_add": A * B + C, "fraction": A - np.floor(A), "sign": np.sign(A),
        "sine": np.sin(A), "cosine": np.cos(A), "tangent": np.tan(A),
        **{op: per_axis(op) for op in ("add", "subtract", "multiply", "divide", "power",
                                       "minimum", "maximum", "floor", "ceil", "modulo",
                                       "wrap", "snap")},
    }
    for op, want in cases.items():
        np.testing.assert_allclose(_vec(op, scale=2.5), want, atol=1e-12, err_msg=op)
    for op, want in {"dot_product": np.dot(A, B), "length": np.linalg.norm(A),
                     "distance": np.linalg.norm(A - B)}.items():
        np.testing.assert_allclose(_vec(op, output="value"), want, atol=1e-12, err_msg=op)
        np.testing.assert_array_equal(_vec(op), 0.0)          # its vector output is 0


def test_vector_refract_obeys_snell():
    """A unit incident refracts into a unit vector with sin(refracted) = eta sin(incident) on
    the other side of the normal; beyond the critical angle the result is 0."""
    d = np.array([0.6, 0.0, -0.8])
    for eta, tir in ((0.8, False), (1 / 0.8, False), (1.7, True)):
        r = one("vector_math", "vector", inputs={"a": tuple(d), "b": (0, 0, 2.0),
                                                 "scale": eta}, operation="refract")[0]
        if tir:
            np.testing.assert_array_equal(r, 0.0)
            continue
        assert np.linalg.norm(r) == pytest.approx(1.0, abs=1e-12)
        assert r[0] == pytest.approx(eta * d[0], abs=1e-12) and r[2] < 0


# --------------------------------------------------------------------------- vectors, ranges
def _rz(t):
    return np.array([[math.cos(t), -math.sin(t), 0], [math.sin(t), math.cos(t), 0], [0, 0, 1]])


def test_mapping_types():
    v, loc, rot, sc = np.array([1.0, 2.0, -0.5]), (0.3, -0.2, 0.1), (0, 0, 0.7), (2.0, 0.5, 1.5)
    m = lambda kind: one("mapping", "vector", inputs={"vector": tuple(v), "location": loc,  # noqa
                                                      "rotation": rot, "scale": sc},
                         vector_type=kind)[0]
    np.testing.assert_allclose(m("point"), _rz(0.7) @ (v * sc) + loc, atol=EPS)
    np.testing.assert_allclose(m("vector"), _rz(0.7) @ (v * sc), atol=EPS)
    np.testing.assert_allclose(m("texture"), (_rz(0.7).T @ (v - loc)) / sc, atol=EPS)
    nrm = _rz(0.7) @ (v / sc)
    np.testing.assert_allclose(m("normal"), nrm / np.linalg.norm(nrm), atol=EPS)
    # Euler XYZ: x first, then y, then z
    r = one("mapping", "vector", inputs={"vector": (0.0, 1.0, 0.0),
                                         "rotation": (math.pi / 2, 0, math.pi / 2)})[0]
    np.testing.assert_allclose(r, [0.0, 0.0, 1.0], atol=EPS)


def test_map_range_and_clamp():
    v = np.array([[-0.5, 0, 0], [0.25, 0, 0], [0.5, 0, 0], [1.5, 0, 0]])

    def mr(interp, clamp=True, **ins):
        return one("map_range", "result", links={"value": sep(0)}, extra=POS, pts=points(v),
                   inputs={"to_min": 2.0, "to_max": 4.0, **ins}, interpolation=interp,
                   clamp=clamp)[:, 0]

    np.testing.assert_allclose(mr("linear"), [2.0, 2.5, 3.0, 4.0])
    np.testing.assert_allclose(mr("linear", clamp=False), [1.0, 2.5, 3.0, 5.0])
    np.testing.assert_allclose(mr("stepped", steps=4.0), [2.0, 2.5, 3.0, 4.0])
    np.testing.assert_allclose(mr("stepped", clamp=False, steps=4.0), [0.5, 2.5, 3.0, 5.5])
    np.testing.assert_allclose(mr("smoothstep"), [2.0, 2 + 2 * 0.15625, 3.0, 4.0])
    np.testing.assert_allclose(mr("smootherstep"), [2.0, 2 + 2 * 0.103515625, 3.0, 4.0])
    # a reversed source range runs backwards; an empty one gives 0
    np.testing.assert_allclose(mr("smoothstep", from_min=1.0, from_max=0.0),
                               [4.0, 4 - 2 * 0.15625, 3.0, 2.0])
    np.testing.assert_allclose(mr("linear", False, from_min=0.5, from_max=0.5), 0.0)
    np.testing.assert_allclose(mr("linear", from_min=0.5, from_max=0.5), 2.0)   # then clamped
    vec = one("map_range_vector", "vector", inputs={
        "vector": (0.25, 2.0, -1.0), "from_min": (0, 0, 0), "from_max": (1, 4, 0),
        "to_min": (0, 10, 1), "to_max": (1, 20, 2)}, interpolation="linear", clamp=False)[0]
    np.testing.assert_allclose(vec, [0.25, 15.0, 1.0])        # 0 width: safe division -> 0
    c = lambda t, lo, hi: one("clamp", "result", inputs={"value": 0.3, "min": lo, "max": hi},  # noqa
                              clamp_type=t)[0, 0]
    assert c("minmax", 0.5, 1.0) == 0.5 and c("minmax", 0.0, 0.2) == 0.2
    assert c("minmax", 0.6, 0.2) == 0.2 and c("range", 0.6, 0.2) == pytest.approx(0.3)


# --------------------------------------------------------------------------- colours
CA, CB = (0.6, 0.2, 0.9), (0.3, 0.8, 0.5)


def _blend(mode, t=1.0):
    return one("mix_color", "result", inputs={"factor": t, "a": CA, "b": CB}, blend=mode,
               clamp_factor=False)[0]


def test_mix_color_blend_modes():
    a, b = np.array(CA), np.array(CB)
    full = {"mix": b, "add": a + b, "multiply": a * b, "subtract": a - b,
            "screen": 1 - (1 - a) * (1 - b), "difference": np.abs(a - b),
            "exclusion": a + b - 2 * a * b, "darken": np.minimum(a, b),
            "lighten": np.maximum(a, b), "divide": a / b, "linear_light": a + 2 * b - 1,
            "overlay": np.where(a < 0.5, 2 * a * b, 1 - 2 * (1 - a) * (1 - b)),
            "dodge": np.minimum(a / (1 - b), 1.0), "burn": np.clip(1 - (1 - a) / b, 0, 1),
            "soft_light": (1 - a) * b * a + a * (1 - (1 - b) * (1 - a))}
    for mode, want in full.items():
        np.testing.assert_allclose(_blend(mode), want, atol=EPS, err_msg=mode)
        if mode not in ("dodge", "burn", "overlay", "screen", "exclusion"):  # linear in t
            np.testing.assert_allclose(_blend(mode, 0.25), a + 0.25 * (want - a), atol=EPS,
                                       err_msg=mode)
    clamped = one("mix_color", "result", inputs={"factor": 3.0, "a": CA, "b": CB},
                  blend="add", clamp_result=True)[0]
    np.testing.assert_allclose(clamped, np.minimum(a + b, 1.0))   # factor clamped to 1 too
    f = one("mix_float", "result", inputs={"factor": 1.5, "a": 1.0, "b": 3.0},
            clamp_factor=False)[0, 0]
    assert f == pytest.approx(4.0)
    vec = one("mix_vector", "result", inputs={"factor": (0.0, 0.5, 2.0), "a": (1, 1, 1),
                                              "b": (3, 3, 3)})[0]
    np.testing.assert_allclose(vec, [1.0, 2.0, 3.0])             # factor clamped per axis


def test_color_ramp_interpolations():
    """Stops on table entries (multiples of 1/(RAMP_TABLE - 1)): the table reproduces the ramp
    exactly, so any factor gives the closed form."""
    k = RAMP_TABLE - 1
    stops = ((64 / k, (1.0, 0.0, 0.0), 0.2), (128 / k, (0.0, 1.0, 0.0), 0.6),
             (192 / k, (0.0, 0.0, 1.0), 1.0))
    f = np.array([0.0, 0.2, 96 / k, 0.6, 160.5 / k, 0.9, 1.3])
    p = points(np.column_stack([f, 0 * f, 0 * f]))

    def ramp(interp, output="color"):
        return one("color_ramp", output, links={"factor": sep(0)}, extra=POS, pts=p,
                   interpolation=interp, stops=stops)

    t = np.clip((f - 64 / k) / (64 / k), 0, 2)
    lin_r = np.where(t <= 1, 1 - t, 0.0)
    lin_g = np.where(t <= 1, t, 2 - t)
    lin_b = np.where(t <= 1, 0.0, t - 1)
    np.testing.assert_allclose(ramp("linear"), np.column_stack([lin_r, lin_g, lin_b]),
                               atol=1e-12)
    alpha = np.where(t <= 1, 0.2 + 0.4 * t, 0.6 + 0.4 * (t - 1))
    np.testing.assert_allclose(ramp("linear", "alpha")[:, 0], alpha, atol=1e-12)
    const = np.array([[1, 0, 0], [1, 0, 0], [1, 0, 0], [0, 1, 0], [0, 1, 0], [0, 0, 1],
                      [0, 0, 1]], float)
    np.testing.assert_allclose(ramp("constant"), const, atol=EPS)
    # ease at the middle of a span: 3 t^2 - 2 t^3 = 0.5
    np.testing.assert_allclose(ramp("ease")[2], [0.5, 0.5, 0.0], atol=1e-12)


def test_color_utilities_and_conversions():
    c = (0.2, 0.5, 0.8)
    np.testing.assert_allclose(one("invert", "color", inputs={"factor": 1.0, "color": c})[0],
                               1 - np.array(c))
    np.testing.assert_allclose(one("gamma", "color", inputs={"color": c, "gamma": 2.2})[0],
                               np.array(c) ** 2.2)
    np.testing.assert_allclose(one("bright_contrast", "color", inputs={
        "color": c, "bright": 0.1, "contrast": 0.5})[0], np.maximum(1.5 * np.array(c) - 0.15, 0))
    lum = np.dot(c, LUMA)
    np.testing.assert_allclose(one("rgb_to_bw", "value", inputs={"color": c})[0], lum)
    # colour -> float is the luminance, vector -> float the mean, float -> colour (f, f, f)
    nodes = [GraphNode("c", "combine_color", inputs={"red": 0.2, "green": 0.5, "blue": 0.8}),
             GraphNode("x", "combine_xyz", inputs={"x": 0.2, "y": 0.5, "z": 0.8}),
             GraphNode("m", "math", links={"a": Link("c", "color"), "b": Link("x", "vector")},
                       props={"operation": "subtract"})]
    np.testing.assert_allclose(emit(nodes, Link("m", "value"), points([0, 0, 0]))[0],
                               lum - 0.5)


# --------------------------------------------------------------------------- textures
def test_checker_and_gradients():
    p = np.array([[0.1, 0.1, 0.1], [0.6, 0.1, 0.1], [0.6, 0.6, 0.1], [0.6, 0.6, 0.6],
                  [-0.1, 0.1, 0.1], [1.3, -0.2, 0.7]])
    got = one("checker", "fac", links={"vector": Link("g", "position")},
              inputs={"scale": 2.0}, extra=POS[:1], pts=points(p))[:, 0]
    cells = np.floor(p * 2)                 # Blender: 1 where the cell indices sum odd
    np.testing.assert_array_equal(got, (cells.sum(axis=1) % 2 == 1).astype(float))
    q = np.array([[0.3, 0.4, 0.0], [-0.2, 0.5, 0.1], [0.6, -0.3, 0.2], [1.4, 0.1, -0.1]])
    r = np.linalg.norm(q, axis=1)
    want = {"linear": q[:, 0], "quadratic": np.maximum(q[:, 0], 0) ** 2,
            "easing": (lambda x: 3 * x * x - 2 * x ** 3)(np.clip(q[:, 0], 0, 1)),
            "diagonal": (q[:, 0] + q[:, 1]) / 2,
            "radial": np.arctan2(q[:, 1], q[:, 0]) / (2 * np.pi) + 0.5,
            "spherical": np.maximum(0.999999 - r, 0),
            "quadratic_sphere": np.maximum(0.999999 - r, 0) ** 2}
    for kind, w in want.items():
        got = one("gradient", "fac", links={"vector": Link("g", "position")}, extra=POS[:1],
                  pts=points(q), gradient_type=kind)[:, 0]
        np.testing.assert_allclose(got, np.clip(w, 0, 1), atol=EPS, err_msg=kind)


IMG = np.arange(2 * 3 * 3, dtype=float).reshape(2, 3, 3) / 17.0      # 2 rows, 3 columns


def test_image_sampling_and_extensions():
    """Pixel (column i, row j, rows top first) has its centre at ((i + .5) / W, 1 - (j + .5)
    / H); "linear" blends neighbours, the extensions wrap, clamp, clip or mirror."""
    h, w = IMG.shape[:2]
    cx, cy = (np.arange(w) + 0.5) / w, 1 - (np.arange(h) + 0.5) / h
    xx, yy = np.meshgrid(cx, cy)
    for interp in ("closest", "linear"):
        got = sample_image(IMG, xx.ravel(), yy.ravel(), interp, "repeat", False)
        np.testing.assert_allclose(got, IMG.reshape(-1, 3), atol=EPS)
    mid = sample_image(IMG, [(cx[0] + cx[1]) / 2], [cy[0]], "linear", "extend", False)[0]
    np.testing.assert_allclose(mid, (IMG[0, 0] + IMG[0, 1]) / 2, atol=EPS)
    x = [cx[0] - 1.0, cx[0] - 0.5, -cx[0]]                  # one tile left, beyond, mirrored
    np.testing.assert_allclose(sample_image(IMG, x[:1], [cy[0]], "closest", "repeat", False),
                               IMG[:1, 0], atol=EPS)
    np.testing.assert_allclose(sample_image(IMG, x[1:2], [cy[0]], "closest", "extend", False),
                               IMG[:1, 0], atol=EPS)
    np.testing.assert_array_equal(sample_image(IMG, x[1:2], [cy[0]], "closest", "clip", False),
                                  0.0)
    np.testing.assert_allclose(sample_image(IMG, x[2:], [cy[0]], "closest", "mirror", False),
                               IMG[:1, 0], atol=EPS)
    # linear + clip at the border: half the texel is black
    edge = sample_image(IMG, [0.0], [cy[0]], "linear", "clip", False)[0]
    np.testing.assert_allclose(edge, IMG[0, 0] / 2, atol=EPS)
    # sRGB-encoded pixels are linearized after the blend
    s = sample_image(IMG, [(cx[0] + cx[1]) / 2], [cy[0]], "linear", "extend", True)[0]
    np.testing.assert_allclose(s, srgb_to_linear((IMG[0, 0] + IMG[0, 1]) / 2), atol=EPS)


def test_box_projection_weights():
    """A face along an axis reads one projection; with blend 1 the diagonal reads all three
    equally; the three projections map (x, y, z) as Cycles' box node."""
    props = dict(image=IMG, path=None, projection="box", extension="repeat",
                 interpolation="closest")
    co = (0.2, 0.7, 0.4)
    px = lambda u, v: sample_image(IMG, [u], [v], "closest", "repeat", False)[0]  # noqa: E731
    for n, want in (((1, 0, 0), px(co[1], co[2])), ((-1, 0, 0), px(1 - co[1], co[2])),
                    ((0, 1, 0), px(1 - co[0], co[2])), ((0, 0, -1), px(co[1], co[0]))):
        got = one("image", "color", inputs={"vector": co}, pts=points([0, 0, 0], n=n),
                  blend=0.0, **props)[0]
        np.testing.assert_allclose(got, want, atol=EPS, err_msg=str(n))
    d = np.ones(3) / np.sqrt(3)
    got = one("image", "color", inputs={"vector": co}, pts=points([0, 0, 0], n=-d), blend=1.0,
              **props)[0]
    np.testing.assert_allclose(got, (px(1 - co[1], co[2]) + px(co[0], co[2]) + px(co[1], co[0]))
                               / 3, atol=1e-12)


def test_texture_coordinates_and_geometry():
    p = np.array([[1.0, 2.0, 3.0], [-0.5, 0.25, 0.0]])
    n = np.array([[0.0, 0.6, 0.8], [1.0, 0.0, 0.0]])
    inc = np.array([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]])
    pts = ShadingPoints(position=p, normal=n, true_normal=-n, incoming=inc,
                        uv=np.array([[0.1, 0.2], [0.3, 0.4]]), backfacing=np.array([True, False]))
    obj = np.eye(4)
    obj[:3, :3], obj[:3, 3] = np.diag([2.0, 1.0, 0.5]), (1, 0, -1)        # world -> object
    tc = GraphNode("t", "tex_coord", props={"object_matrix": obj, "generated_matrix": obj,
                                            "normal_matrix": np.diag([1.0, 2.0, 1.0])})
    out = lambda name: emit([tc], Link("t", name), pts)  # noqa: E731
    np.testing.assert_allclose(out("object"), p * [2, 1, 0.5] + [1, 0, -1], atol=EPS)
    nn = n * [1, 2, 1]
    np.testing.assert_allclose(out("normal"), nn / np.linalg.norm(nn, axis=1)[:, None],
                               atol=EPS)
    np.testing.assert_allclose(out("uv"), [[0.1, 0.2, 0], [0.3, 0.4, 0]], atol=EPS)
    refl = 2 * np.sum(n * inc, axis=1)[:, None] * n - inc
    np.testing.assert_allclose(out("reflection"), refl, atol=EPS)
    geo = GraphNode("g", "geometry")
    for name, want in (("position", p), ("normal", n), ("true_normal", -n), ("incoming", inc),
                       ("backfacing", [[1, 1, 1], [0, 0, 0]])):
        np.testing.assert_allclose(emit([geo], Link("g", name), pts), want, atol=EPS)
    info = GraphNode("i", "object_info", props={"location": (1, 2, 3), "random": 0.25})
    np.testing.assert_allclose(emit([info], Link("i", "random"), pts), 0.25)


# --------------------------------------------------------------------------- shaders, shading
def _shader_graph(factor=0.25):
    nodes = [GraphNode("e", "emission", inputs={"color": (1.0, 0.5, 0.0), "strength": 2.0}),
             GraphNode("d", "diffuse", inputs={"color": (0.2, 0.4, 0.6)}),
             GraphNode("p", "principled", inputs={"base_color": (0.5, 0.5, 0.5),
                                                  "emission_color": (0.0, 0.0, 1.0),
                                                  "emission_strength": 3.0}),
             GraphNode("a", "add_shader", links={"shader1": Link("d", "bsdf"),
                                                 "shader2": Link("p", "bsdf")}),
             GraphNode("m", "mix_shader", inputs={"factor": factor},
                       links={"shader1": Link("e", "emission"), "shader2": Link("a", "shader")})]
    return ShaderGraph(nodes=nodes, output=Link("m", "shader"))


def test_shader_closures():
    cl = evaluate(_shader_graph(), points([0, 0, 0]))
    np.testing.assert_allclose(cl.emission[0], 0.75 * np.array([2.0, 1.0, 0.0]) + 0.25 * np.array(
        [0.0, 0.0, 3.0]))
    np.testing.assert_allclose(cl.albedo[0], 0.25 * np.array([0.7, 0.9, 1.1]))
    cl = evaluate(_shader_graph(factor=7.0), points([0, 0, 0]))       # factor clamped to 1
    np.testing.assert_allclose(cl.emission[0], [0.0, 0.0, 3.0])


def _floor_scene(graph, world=None, lights=()):
    floor = Mesh(name="floor", material="g", vertices=np.array(
        [[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], float),
        triangles=np.array([[0, 1, 2], [0, 2, 3]]))
    return Scene(objects=[SpecularObject("o", [Patch("p", 0, vertices=np.eye(3),
                                                    triangles=np.array([[0, 1, 2]]))])],
                 meshes=[floor], materials={"g": Material("g", kind="nodes", graph=graph)},
                 lights=list(lights), world=world or World(ambient=0.5))


def test_graph_material_is_shaded_with_its_emission_and_lit_albedo():
    """Radiance = emission + albedo / pi * (ambient + E), E = power / (4 pi r^2) cos for a
    point light (trace/shading.py), here on a floor seen from above."""
    light = Light("l", "point", position=(0.0, 0.0, 2.0), power=400.0, shadows=False)
    env = Environment(_floor_scene(_shader_graph(), lights=[light]))
    o = np.array([[0.0, 0.0, 5.0], [1.5, 0.0, 5.0]])
    col = env.shade_rays(o, np.array([[0, 0, -1.0]] * 2))
    r2 = np.array([4.0, 4.0 + 1.5 ** 2])
    e = 400.0 / (4 * np.pi * r2) * (2.0 / np.sqrt(r2))
    albedo = 0.25 * np.array([0.7, 0.9, 1.1])
    want = np.array([1.5, 0.75, 0.75]) + albedo * (0.5 + e[:, None]) / np.pi
    np.testing.assert_allclose(col, want, rtol=1e-12)


def test_world_graph_sees_directions():
    """The world's graph: Generated and Position are the ray direction, Incoming its opposite."""
    tc = GraphNode("t", "tex_coord")
    geo = GraphNode("g", "geometry")
    add = GraphNode("s", "vector_math", links={"a": Link("t", "generated"),
                                               "b": Link("g", "incoming")},
                    props={"operation": "subtract"})
    bg = GraphNode("b", "background", links={"color": Link("s", "vector")},
                   inputs={"strength": 0.5})
    w = World(kind="nodes", graph=ShaderGraph(nodes=[tc, geo, add, bg],
                                              output=Link("b", "background")), strength=2.0)
    d = np.array([[0.0, 0.6, 0.8], [1.0, 0.0, 0.0]])
    np.testing.assert_allclose(eval_world(w, d), 2.0 * d, atol=EPS)     # 2 (D - (-D)) / 2


# --------------------------------------------------------------------------- the scene format
def _scene_dict(graph):
    d = io.scene_to_dict(_floor_scene(_shader_graph()))
    d["materials"][0]["graph"] = graph
    return d


def _graph_json():
    return graph_to_dict(ShaderGraph(nodes=POS + [
        GraphNode("m", "math", links={"a": sep(0)}, inputs={"b": 2.0},
                  props={"operation": "multiply"}),
        GraphNode("r", "color_ramp", links={"factor": Link("m", "value")},
                  props={"stops": ((0.0, (1, 0, 0), 1.0), (1.0, (0, 0, 1), 1.0))}),
        GraphNode("e", "emission", links={"color": Link("r", "color")})],
        output=Link("e", "emission")))


def test_graph_round_trip(tmp_path):
    d = _scene_dict(_graph_json())
    path = tmp_path / "s.json"
    s1 = io.scene_from_dict(d)
    io.save_scene(s1, path)
    s2 = io.load_scene(path)
    assert io.scene_to_dict(s2) == io.scene_to_dict(s1)
    pts = points([[0.1, 0, 0], [0.3, 0, 0]])
    np.testing.assert_array_equal(evaluate(s2.materials["g"].graph, pts).emission,
                                  evaluate(s1.materials["g"].graph, pts).emission)
    text = json.loads(path.read_text())["materials"][0]
    assert text["kind"] == "nodes" and text["graph"]["version"] == 1


def _bad(mutate):
    g = _graph_json()
    mutate(g)
    with pytest.raises(io.SceneError) as e:
        io.scene_from_dict(_scene_dict(g))
    return str(e.value)


@pytest.mark.parametrize("mutate, message", [
    (lambda g: g["nodes"][2].update(type="sparkle"),
     "materials[0].graph.nodes[2].type: material 'g': node 'm': unknown node type 'sparkle'"),
    (lambda g: g["nodes"][2].update(operation="frobnicate"),
     "materials[0].graph.nodes[2].operation: material 'g': node 'm': unknown value "
     "'frobnicate'"),
    (lambda g: g["nodes"][2]["inputs"].update(z=1.0),
     "materials[0].graph.nodes[2].inputs.z: material 'g': node 'm': math has no input 'z'"),
    (lambda g: g["nodes"][2]["inputs"].update(a={"node": "ghost", "output": "x"}),
     "materials[0].graph.nodes[2].inputs.a: material 'g': node 'm': link from unknown node "
     "'ghost'"),
    (lambda g: g["nodes"][2]["inputs"].update(a={"node": "p", "output": "w"}),
     "node 'm': node 'p' (separate_xyz) has no output 'w'"),
    (lambda g: g["nodes"][2]["inputs"].update(a={"node": "e", "output": "emission"}),
     "node 'm': a shader output ('e'.emission) cannot feed a float input"),
    (lambda g: g["nodes"][0]["inputs"].update(x=1),
     "node 'g': geometry has no input 'x'"),
    (lambda g: g["nodes"][1]["inputs"].update(vector={"node": "m", "output": "value"}),
     "the graph has a cycle"),
    (lambda g: g["nodes"][2]["inputs"].update(b=[1, 2]),
     "nodes[2].inputs.b: material 'g': node 'm': expected a number"),
    (lambda g: g["nodes"][3]["stops"].reverse(),
     "nodes[3].stops[1]: material 'g': node 'r': stop positions must be non-decreasing"),
    (lambda g: g["nodes"][3]["stops"][0].update(position=1.5),
     "stop position must lie in [0, 1]"),
    (lambda g: g.update(version=2), "materials[0].graph.version: material 'g': unsupported "
                                    "graph version 2"),
    (lambda g: g.update(output={"node": "m", "output": "value", "extra": 1}),
     "materials[0].graph.output: material 'g': the output: a link is"),
    (lambda g: g["nodes"][1].update(name="g"), "duplicate node name 'g'"),
    (lambda g: g["nodes"].append({"name": "i", "type": "image"}),
     "nodes[5]: material 'g': node 'i': missing required key 'path'"),
    (lambda g: g["nodes"].append({"name": "i", "type": "image", "path": "nowhere.png"}),
     "nodes[5].path: image file not found"),
    (lambda g: g["nodes"][2]["inputs"].update(b=1e300), "magnitude <= 1e+12"),
])
def test_graph_validation_names_material_and_node(mutate, message):
    msg = _bad(mutate)
    assert message in msg and "\n" not in msg, msg


def test_graph_errors_from_code_name_the_node():
    with pytest.raises(GraphError, match="node 'x': clamp has no property 'mode'"):
        ShaderGraph(nodes=[GraphNode("x", "clamp", props={"mode": 1})], output=Link("x", "result"))
    with pytest.raises(GraphError, match="the image is not loaded"):
        ShaderGraph(nodes=[GraphNode("i", "image")], output=Link("i", "color"))
    with pytest.raises(GraphError, match="unknown key 'nodez'"):
        graph_from_dict({"version": 1, "nodez": [], "output": {}}, None)


def test_srgb_image_node_reads_the_png_samples(tmp_path):
    """With ``srgb`` an image node keeps a PNG's encoded samples and linearizes after the
    blend; without it the PNG is linearized on load (as textures are)."""
    from riray.imageio import linear_to_u8, write_png
    px = np.random.default_rng(2).uniform(0.0, 1.0, (2, 3, 3))
    write_png(tmp_path / "t.png", px)
    codes = linear_to_u8(px) / 255.0
    g = _graph_json()
    g["nodes"].append({"name": "i", "type": "image", "path": "t.png", "srgb": True,
                       "interpolation": "linear", "extension": "extend",
                       "inputs": {"vector": [0.5 / 3 + 1 / 6, 0.75, 0.0]}})
    g["output"] = {"node": "i", "output": "color"}
    enc = io.scene_from_dict(_scene_dict(g), tmp_path).materials["g"].graph
    g["nodes"][-1]["srgb"] = False
    lin = io.scene_from_dict(_scene_dict(g), tmp_path).materials["g"].graph
    np.testing.assert_allclose(enc.nodes[-1].props["image"], codes, atol=EPS)
    np.testing.assert_allclose(lin.nodes[-1].props["image"], srgb_to_linear(codes), atol=1e-12)
    got = evaluate(enc, points([0, 0, 0])).emission[0]          # between pixels 0 and 1
    np.testing.assert_allclose(got, srgb_to_linear((codes[0, 0] + codes[0, 1]) / 2), atol=1e-12)


def test_documented_graph_example_loads():
    """docs/scene-format.md: the node-graph example is a valid graph, and the node table lists
    every node type with every input and output."""
    doc = (Path(__file__).resolve().parents[2] / "docs" / "scene-format.md").read_text()
    section = doc[doc.index("## Node graphs"):doc.index("## Supported range")]
    g = graph_from_dict(json.loads(re.search(r"```\n(.*?)```", section, re.S).group(1)), None)
    assert [n.type for n in g.nodes][-1] == "emission"
    rows = {}
    for line in section.splitlines():
        cells = line.split("|")
        if len(cells) > 4 and cells[1].strip().startswith("`"):
            for name in re.findall(r"`(\w+)`", cells[1]):
                rows[name] = "|".join(cells[2:4])
    for t, spec in NODE_TYPES.items():
        assert t in rows, t
        for name in list(spec.inputs) + list(spec.outputs):
            assert f"`{name}`" in rows[t], (t, name)


def test_noise_vanishes_on_the_lattice_and_is_smooth():
    """Gradient noise is 0 at integer points, so one octave of normalized fBM is 0.5 there
    and a ridged multifractal offset^2; between lattice points it is continuous."""
    lattice = points([[0, 0, 0], [3, -2, 7], [-5, 1, 1], [12, 40, -3]])
    coords = [GraphNode("g", "geometry")]
    fac = lambda pts, **kw: one("noise", "fac", links={"vector": Link("g", "position")},  # noqa
                                extra=coords, pts=pts, **kw)[:, 0]
    ins = {"scale": 1.0, "detail": 0.0, "offset": 0.7}
    np.testing.assert_allclose(fac(lattice, inputs=ins), 0.5, atol=EPS)
    np.testing.assert_allclose(fac(lattice, inputs=ins, noise_type="ridged_multifractal"),
                               0.7 ** 2, atol=EPS)
    t = np.linspace(0.0, 1.0, 2001)
    line = points(np.column_stack([t + 0.3, 0.6 * t - 0.2, 0.1 - 0.4 * t]))
    v = fac(line, inputs={"scale": 1.3, "detail": 2.5})
    assert np.abs(np.diff(v)).max() < 0.01 and 0.2 < v.min() < v.max() < 0.8
