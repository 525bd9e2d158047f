"""Vector and number nodes: Math, Vector Math, Map Range, Clamp, Mapping, Separate / Combine
and the float / vector Mix, after Cycles' svm kernels (kernel/svm/math_util.h, mapping.h,
map_range.h), in float64."""

from __future__ import annotations

import numpy as np

from ...scene.graph import NODE_TYPES
from .values import dot, expand, safe_divide, safe_normalize, saturate

FLT_EPSILON = 1.1920929e-07   # Cycles' Compare uses max(epsilon input, FLT_EPSILON)


def _safe_pow(a, b):
    a, b = np.broadcast_arrays(np.asarray(a, float), np.asarray(b, float))
    bad = (a < 0) & (b != np.trunc(b))
    return np.where(bad, 0.0, np.power(np.where(bad, 1.0, a), b))


def _wrap(v, hi, lo):
    rng = np.asarray(hi) - lo
    return np.where(rng != 0, v - rng * np.floor(safe_divide(v - lo, rng)), lo)


def _smooth_min(a, b, k):
    k = np.asarray(k, float)
    kk = np.where(k != 0, k, 1.0)
    h = np.maximum(kk - np.abs(a - b), 0.0) / kk
    return np.where(k != 0, np.minimum(a, b) - h ** 3 * kk / 6.0, np.minimum(a, b))


def _sign(a):
    return np.sign(a).astype(float)


def _logarithm(a, b, c):
    ok = (np.asarray(a) > 0) & (np.asarray(b) > 0)
    return np.where(ok, safe_divide(np.log(np.where(ok, a, 1.0)),
                                    np.log(np.where(ok, b, 2.0))), 0.0)


def _inverse_sqrt(a, b, c):
    return np.where(np.asarray(a) > 0, 1.0 / np.sqrt(np.where(np.asarray(a) > 0, a, 1.0)), 0.0)


def _modulo(a, b, c):
    b = np.asarray(b)
    return np.where(b != 0, np.fmod(a, np.where(b != 0, b, 1.0)), 0.0)


def _pingpong(a, b, c):
    b = np.asarray(b)
    bb = np.where(b != 0, b, 1.0)
    t = (a - bb) / (bb * 2.0)
    return np.where(b != 0, np.abs((t - np.floor(t)) * bb * 2.0 - bb), 0.0)


# Cycles' svm_math, one entry per operation: (a, b, c) -> value
MATH = {
    "add": lambda a, b, c: a + b,
    "subtract": lambda a, b, c: a - b,
    "multiply": lambda a, b, c: a * b,
    "divide": lambda a, b, c: safe_divide(a, b),
    "multiply_add": lambda a, b, c: a * b + c,
    "power": lambda a, b, c: _safe_pow(a, b),
    "logarithm": _logarithm,
    "sqrt": lambda a, b, c: np.sqrt(np.maximum(a, 0.0)),
    "inverse_sqrt": _inverse_sqrt,
    "absolute": lambda a, b, c: np.abs(a),
    "exponent": lambda a, b, c: np.exp(a),
    "minimum": lambda a, b, c: np.minimum(a, b),
    "maximum": lambda a, b, c: np.maximum(a, b),
    "less_than": lambda a, b, c: (np.asarray(a) < b).astype(float),
    "greater_than": lambda a, b, c: (np.asarray(a) > b).astype(float),
    "sign": lambda a, b, c: _sign(a),
    "compare": lambda a, b, c: ((np.asarray(a) == b)
                                | (np.abs(a - b) <= np.maximum(c, FLT_EPSILON))).astype(float),
    "smooth_min": lambda a, b, c: _smooth_min(a, b, c),
    "smooth_max": lambda a, b, c: -_smooth_min(-np.asarray(a), -np.asarray(b), c),
    "round": lambda a, b, c: np.floor(np.asarray(a) + 0.5),
    "floor": lambda a, b, c: np.floor(a),
    "ceil": lambda a, b, c: np.ceil(a),
    "trunc": lambda a, b, c: np.trunc(a),
    "fract": lambda a, b, c: a - np.floor(a),
    "modulo": _modulo,
    "floored_modulo": lambda a, b, c: np.where(np.asarray(b) != 0,
                                               a - np.floor(safe_divide(a, b)) * b, 0.0),
    "wrap": lambda a, b, c: _wrap(a, b, c),
    "snap": lambda a, b, c: np.floor(safe_divide(a, b)) * b,
    "pingpong": _pingpong,
    "sine": lambda a, b, c: np.sin(a),
    "cosine": lambda a, b, c: np.cos(a),
    "tangent": lambda a, b, c: np.tan(a),
    "arcsine": lambda a, b, c: np.arcsin(np.clip(a, -1.0, 1.0)),
    "arccosine": lambda a, b, c: np.arccos(np.clip(a, -1.0, 1.0)),
    "arctangent": lambda a, b, c: np.arctan(a),
    "arctan2": lambda a, b, c: np.arctan2(a, b),
    "sinh": lambda a, b, c: np.sinh(a),
    "cosh": lambda a, b, c: np.cosh(a),
    "tanh": lambda a, b, c: np.tanh(a),
    "radians": lambda a, b, c: a * (np.pi / 180.0),
    "degrees": lambda a, b, c: a * (180.0 / np.pi),
}

# Vector Math operations computed per component by the Math operation of the same name
_PER_COMPONENT = {"add", "subtract", "multiply", "divide", "absolute", "power", "minimum",
                  "maximum", "floor", "ceil", "snap", "sine", "cosine", "tangent"}


def _reflect(a, n):
    n = safe_normalize(n)
    return a - 2.0 * expand(dot(a, n)) * n


def _refract(a, n, s):
    n = safe_normalize(n)
    d = dot(n, a)
    k = 1.0 - s * s * (1.0 - d * d)
    r = expand(s) * a - expand(s * d + np.sqrt(np.maximum(k, 0.0))) * n
    return np.where(expand(k) < 0, 0.0, r)


# Cycles' svm_vector_math's operations with a vector result: (a, b, c, scale) -> vector
_VECTOR_OPS = {
    "cross_product": lambda a, b, c, s: np.cross(*np.broadcast_arrays(a, b)),
    "project": lambda a, b, c, s: expand(safe_divide(dot(a, b), dot(b, b))) * b,
    "reflect": lambda a, b, c, s: _reflect(a, b),
    "refract": lambda a, b, c, s: _refract(a, b, s),
    "faceforward": lambda a, b, c, s: np.where(expand(dot(c, b)) < 0, a, -np.asarray(a)),
    "multiply_add": lambda a, b, c, s: np.asarray(a) * b + c,
    "scale": lambda a, b, c, s: np.asarray(a) * expand(s),
    "normalize": lambda a, b, c, s: safe_normalize(a),
    "fraction": lambda a, b, c, s: a - np.floor(a),
    "sign": lambda a, b, c, s: _sign(a),
    "modulo": lambda a, b, c, s: _modulo(a, b, None),
    "wrap": lambda a, b, c, s: _wrap(a, b, c),
}

# ... and those with a float result: (a, b) -> value
_VALUE_OPS = {
    "dot_product": lambda a, b: dot(a, b),
    "distance": lambda a, b: np.linalg.norm(np.asarray(a) - b, axis=-1),
    "length": lambda a, b: np.linalg.norm(a, axis=-1),
}


def _vector_math(op: str, a, b, c, s):
    """(vector, value) of Cycles' svm_vector_math; the output an operation does not produce
    is 0 (Blender hides it)."""
    if op in _VALUE_OPS:
        return np.zeros(3), _VALUE_OPS[op](a, b)
    if op in _PER_COMPONENT:
        return MATH[op](np.asarray(a), np.asarray(b), None), np.asarray(0.0)
    return _VECTOR_OPS[op](a, b, c, s), np.asarray(0.0)


def _map_range(v, inp: dict, interp: str, clamp: bool, vector: bool):
    """Cycles' svm_node_map_range / svm_node_vector_map_range (+ the clamp Blender adds) of
    ``v`` from [from_min, from_max] to [to_min, to_max] (in ``inp``, with ``steps``)."""
    fmin, fmax, tmin, tmax = inp["from_min"], inp["from_max"], inp["to_min"], inp["to_max"]
    if interp in ("linear", "stepped"):
        t = safe_divide(v - fmin, np.asarray(fmax) - fmin)
        if interp == "stepped":
            st = np.asarray(inp["steps"])
            t = np.where(st > 0, np.floor(t * (st + 1.0)) / np.where(st > 0, st, 1.0), 0.0)
    else:
        if vector:
            t = saturate(safe_divide(v - fmin, np.asarray(fmax) - fmin))
        else:   # Cycles' smoothstep(edge0, edge1, x), flipped when from_min > from_max
            lo, hi = np.minimum(fmin, fmax), np.maximum(fmin, fmax)
            t = saturate(safe_divide(v - lo, hi - lo))
        t = t * t * (3.0 - 2.0 * t) if interp == "smoothstep" else \
            t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
        if not vector:
            t = np.where(np.asarray(fmin) > fmax, 1.0 - t, t)
    out = tmin + t * (np.asarray(tmax) - tmin)
    if not vector:
        out = np.where(np.asarray(fmax) != fmin, out, 0.0)
    if clamp and (vector is False or interp in ("linear", "stepped")):
        lo, hi = np.minimum(tmin, tmax), np.maximum(tmin, tmax)
        out = np.clip(out, lo, hi)
    return out


def _mapping(kind: str, v, loc, rot, scale):
    """Cycles' svm_mapping: rotation is Euler XYZ (R = Rz Ry Rx), radians."""
    rx, ry, rz = (np.asarray(rot, float)[..., i] for i in range(3))
    cx, cy, cz, sx, sy, sz = np.cos(rx), np.cos(ry), np.cos(rz), np.sin(rx), np.sin(ry), np.sin(rz)
    r = np.stack([np.stack([cy * cz, sy * sx * cz - cx * sz, sy * cx * cz + sx * sz], -1),
                  np.stack([cy * sz, sy * sx * sz + cx * cz, sy * cx * sz - sx * cz], -1),
                  np.stack([-sy, cy * sx, cy * cx], -1)], -2)
    rot_v = lambda m, x: np.einsum("...ij,...j->...i", m, x)     # noqa: E731
    v, loc, scale = np.asarray(v, float), np.asarray(loc, float), np.asarray(scale, float)
    if kind == "point":
        return rot_v(r, v * scale) + loc
    if kind == "texture":
        return safe_divide(rot_v(np.swapaxes(r, -1, -2), v - loc), scale)
    if kind == "vector":
        return rot_v(r, v * scale)
    return safe_normalize(rot_v(r, safe_divide(v, scale)))


# --------------------------------------------------------------------------- nodes
# Every node evaluation: (node, inputs, shading points, wanted outputs) -> {output: value}
def mapping(node, inp, pts, want) -> dict:
    return {"vector": _mapping(node.props["vector_type"], inp["vector"], inp["location"],
                               inp["rotation"], inp["scale"])}


def _separate(input_name: str):
    def run(node, inp, pts, want) -> dict:
        v = np.asarray(inp[input_name], float)
        return {k: v[..., i] for i, k in enumerate(NODE_TYPES[node.type].outputs)}
    return run


def _combine(output_name: str):
    def run(node, inp, pts, want) -> dict:
        names = list(NODE_TYPES[node.type].inputs)
        out = np.stack(np.broadcast_arrays(*(np.asarray(inp[k], float) for k in names)), -1)
        return {output_name: out}
    return run


def math_node(node, inp, pts, want) -> dict:
    r = MATH[node.props["operation"]](np.asarray(inp["a"], float), np.asarray(inp["b"], float),
                                      np.asarray(inp["c"], float))
    return {"value": saturate(r) if node.props["clamp"] else r}


def vector_math(node, inp, pts, want) -> dict:
    vec, val = _vector_math(node.props["operation"], np.asarray(inp["a"], float),
                            np.asarray(inp["b"], float), np.asarray(inp["c"], float),
                            np.asarray(inp["scale"], float))
    return {"vector": vec, "value": val}


def _map_range_node(input_name: str, output_name: str, vector: bool):
    def run(node, inp, pts, want) -> dict:
        pr = node.props
        return {output_name: _map_range(np.asarray(inp[input_name]), inp, pr["interpolation"],
                                        pr["clamp"], vector)}
    return run


def clamp(node, inp, pts, want) -> dict:
    lo, hi = np.asarray(inp["min"], float), np.asarray(inp["max"], float)
    if node.props["clamp_type"] == "range":
        lo, hi = np.minimum(lo, hi), np.maximum(lo, hi)
    return {"result": np.minimum(np.maximum(inp["value"], lo), hi)}


def mix(node, inp, pts, want) -> dict:
    """Mix (float or vector): a (1 - factor) + b factor."""
    f = np.asarray(inp["factor"], float)
    f = saturate(f) if node.props["clamp_factor"] else f
    return {"result": np.asarray(inp["a"]) * (1.0 - f) + np.asarray(inp["b"]) * f}


NODES = {"mapping": mapping,
         "separate_xyz": _separate("vector"), "separate_color": _separate("color"),
         "combine_xyz": _combine("vector"), "combine_color": _combine("color"),
         "math": math_node, "vector_math": vector_math,
         "map_range": _map_range_node("value", "result", False),
         "map_range_vector": _map_range_node("vector", "vector", True),
         "clamp": clamp, "mix_float": mix, "mix_vector": mix}
