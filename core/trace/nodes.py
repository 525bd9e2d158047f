"""Evaluation of shader node graphs (``riray.scene.graph``), vectorized over shading points.

``evaluate(graph, points)`` runs every node once over all N points (no per-point loops): float
values are arrays of shape (N,) or () for constants, vectors and colours (N, 3) or (3,), so
constant sub-graphs stay scalars and broadcast. The result is a :class:`Closure`: emitted
radiance (W/m^2/sr, linear RGB) and a diffuse albedo, which Environment shades as
``emission + albedo / pi * (ambient + irradiance)`` (a Whitted renderer's reading of Cycles'
closures: Emission / Background / Principled emission -> emission, Diffuse / Principled base
colour -> albedo, Mix Shader -> weighted sum, Add Shader -> sum).

The node formulas follow Cycles' SVM kernels (intern/cycles/kernel/svm/), in float64:
safe division and modulo give 0 for a zero divisor, colour ramps are read from a 257-entry table
of the ramp as Cycles does (so stops between table entries are smoothed as in Cycles), images
are sampled with pixel centres at (i + 0.5) / W like Cycles' CPU kernel. Non-finite results
(0 ** -1, exp overflow) become 0, as Cycles drops non-finite samples.

Shading points (:class:`ShadingPoints`) follow Cycles' ShaderData: ``normal`` and
``true_normal`` are turned towards the incoming ray, ``incoming`` points back along it. For the
world (``ShadingPoints.world``) the position is the ray direction D and the normals and
incoming vector are -D, as in Cycles' background shading.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scene.graph import COLOR, FLOAT, LUMA, NODE_TYPES, SHADER, VECTOR, ShaderGraph

# Cycles reads colour ramps from a table of 257 entries, the ramp at i / 256 (Blender's colour
# band table, CM_TABLE + 1), blended linearly: measured against Cycles 4.2 and 5.0, where a stop
# between two entries is smoothed over their interval.
RAMP_TABLE = 257
FLT_EPSILON = 1.1920929e-07   # Cycles' Compare uses max(epsilon input, FLT_EPSILON)
CHECKER_BIAS = 1e-6           # Cycles' svm_checker: p = (p + 1e-6) * (1 - 1e-6)
SPHERE_BIAS = 0.999999        # Cycles' spherical gradients: r = max(0.999999 - |p|, 0)


@dataclass
class ShadingPoints:
    """N points being shaded (world space, float64). ``normal`` (shading) and ``true_normal``
    (geometric) face the incoming ray; ``incoming`` is the unit vector back towards the ray
    origin; ``uv`` the mesh's texture coordinates (zeros without a UV map); ``backfacing`` where
    the ray hit the side the winding normal points away from."""

    position: np.ndarray      # (N, 3)
    normal: np.ndarray        # (N, 3)
    true_normal: np.ndarray   # (N, 3)
    incoming: np.ndarray      # (N, 3)
    uv: np.ndarray            # (N, 2)
    backfacing: np.ndarray    # (N,) bool

    @classmethod
    def world(cls, dirs: np.ndarray) -> "ShadingPoints":
        """Background shading of unit ray directions ``dirs`` (N, 3): position D, normals and
        incoming -D, uv 0 (Cycles' shader_setup_from_background)."""
        d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        return cls(position=d, normal=-d, true_normal=-d, incoming=-d,
                   uv=np.zeros((len(d), 2)), backfacing=np.zeros(len(d), bool))

    def __len__(self) -> int:
        return len(self.position)


@dataclass
class Closure:
    """Emitted radiance and diffuse albedo, (N, 3) each (or broadcastable constants inside the
    evaluator)."""

    emission: np.ndarray
    albedo: np.ndarray


# --------------------------------------------------------------------------- value kinds
def _gray(c):
    return c @ np.asarray(LUMA)


def _convert(v, src: str, dst: str):
    """A value of kind ``src`` as kind ``dst`` (graph.py's conversion rules)."""
    if src == dst or {src, dst} == {VECTOR, COLOR}:
        return v
    if dst == SHADER:
        return Closure(emission=_convert(v, src, COLOR), albedo=np.zeros(3))
    if src == FLOAT:
        return np.asarray(v)[..., None] * np.ones(3)
    return _gray(v) if src == COLOR else np.mean(v, axis=-1)


def _f(x):
    """``x`` (a float value) shaped to broadcast against vectors."""
    return np.asarray(x)[..., None]


def _safe_divide(a, b):
    b = np.asarray(b)
    return np.where(b != 0, a / np.where(b != 0, b, 1.0), 0.0)


def _safe_normalize(v):
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n != 0, v / np.where(n != 0, n, 1.0), v)


def _dot(a, b):
    return np.sum(np.asarray(a) * np.asarray(b), axis=-1)


def _affine(m: np.ndarray, p):
    return np.asarray(p) @ m[:3, :3].T + m[:3, 3]


def _saturate(x):
    return np.clip(x, 0.0, 1.0)


# --------------------------------------------------------------------------- math
def _safe_pow(a, b):
    a, b = np.broadcast_arrays(np.asarray(a, float), np.asarray(b, float))
    bad = (a < 0) & (b != np.trunc(b))
    return np.where(bad, 0.0, np.power(np.where(bad, 1.0, a), b))


def _wrap(v, hi, lo):
    rng = np.asarray(hi) - lo
    return np.where(rng != 0, v - rng * np.floor(_safe_divide(v - lo, rng)), lo)


def _smooth_min(a, b, k):
    k = np.asarray(k, float)
    kk = np.where(k != 0, k, 1.0)
    h = np.maximum(kk - np.abs(a - b), 0.0) / kk
    return np.where(k != 0, np.minimum(a, b) - h ** 3 * kk / 6.0, np.minimum(a, b))


def _sign(a):
    return np.sign(a).astype(float)


def _math(op: str, a, b, c):
    """Cycles' svm_math (kernel/svm/math_util.h) for one operation."""
    if op == "add":
        return a + b
    if op == "subtract":
        return a - b
    if op == "multiply":
        return a * b
    if op == "divide":
        return _safe_divide(a, b)
    if op == "multiply_add":
        return a * b + c
    if op == "power":
        return _safe_pow(a, b)
    if op == "logarithm":
        ok = (np.asarray(a) > 0) & (np.asarray(b) > 0)
        return np.where(ok, _safe_divide(np.log(np.where(ok, a, 1.0)),
                                         np.log(np.where(ok, b, 2.0))), 0.0)
    if op == "sqrt":
        return np.sqrt(np.maximum(a, 0.0))
    if op == "inverse_sqrt":
        return np.where(np.asarray(a) > 0, 1.0 / np.sqrt(np.where(np.asarray(a) > 0, a, 1.0)),
                        0.0)
    if op == "absolute":
        return np.abs(a)
    if op == "exponent":
        return np.exp(a)
    if op == "minimum":
        return np.minimum(a, b)
    if op == "maximum":
        return np.maximum(a, b)
    if op == "less_than":
        return (np.asarray(a) < b).astype(float)
    if op == "greater_than":
        return (np.asarray(a) > b).astype(float)
    if op == "sign":
        return _sign(a)
    if op == "compare":
        return ((np.asarray(a) == b) | (np.abs(a - b) <= np.maximum(c, FLT_EPSILON))).astype(float)
    if op == "smooth_min":
        return _smooth_min(a, b, c)
    if op == "smooth_max":
        return -_smooth_min(-np.asarray(a), -np.asarray(b), c)
    if op == "round":
        return np.floor(np.asarray(a) + 0.5)
    if op == "floor":
        return np.floor(a)
    if op == "ceil":
        return np.ceil(a)
    if op == "trunc":
        return np.trunc(a)
    if op == "fract":
        return a - np.floor(a)
    if op == "modulo":
        b = np.asarray(b)
        return np.where(b != 0, np.fmod(a, np.where(b != 0, b, 1.0)), 0.0)
    if op == "floored_modulo":
        return np.where(np.asarray(b) != 0, a - np.floor(_safe_divide(a, b)) * b, 0.0)
    if op == "wrap":
        return _wrap(a, b, c)
    if op == "snap":
        return np.floor(_safe_divide(a, b)) * b
    if op == "pingpong":
        b = np.asarray(b)
        bb = np.where(b != 0, b, 1.0)
        t = (a - bb) / (bb * 2.0)
        return np.where(b != 0, np.abs((t - np.floor(t)) * bb * 2.0 - bb), 0.0)
    if op == "sine":
        return np.sin(a)
    if op == "cosine":
        return np.cos(a)
    if op == "tangent":
        return np.tan(a)
    if op == "arcsine":
        return np.arcsin(np.clip(a, -1.0, 1.0))
    if op == "arccosine":
        return np.arccos(np.clip(a, -1.0, 1.0))
    if op == "arctangent":
        return np.arctan(a)
    if op == "arctan2":
        return np.arctan2(a, b)
    if op == "sinh":
        return np.sinh(a)
    if op == "cosh":
        return np.cosh(a)
    if op == "tanh":
        return np.tanh(a)
    if op == "radians":
        return a * (np.pi / 180.0)
    if op == "degrees":
        return a * (180.0 / np.pi)
    raise AssertionError(op)


def _vector_math(op: str, a, b, c, s):
    """(vector, value) of Cycles' svm_vector_math; the output an operation does not produce
    is 0 (Blender hides it)."""
    zero_v, zero_f = np.zeros(3), np.asarray(0.0)
    if op == "dot_product":
        return zero_v, _dot(a, b)
    if op == "distance":
        return zero_v, np.linalg.norm(np.asarray(a) - b, axis=-1)
    if op == "length":
        return zero_v, np.linalg.norm(a, axis=-1)
    if op == "cross_product":
        return np.cross(*np.broadcast_arrays(a, b)), zero_f
    if op == "project":
        ll = _dot(b, b)
        return _f(_safe_divide(_dot(a, b), ll)) * b, zero_f
    if op == "reflect":
        n = _safe_normalize(b)
        return a - 2.0 * _f(_dot(a, n)) * n, zero_f
    if op == "refract":
        n = _safe_normalize(b)
        d = _dot(n, a)
        k = 1.0 - s * s * (1.0 - d * d)
        r = _f(s) * a - _f(s * d + np.sqrt(np.maximum(k, 0.0))) * n
        return np.where(_f(k) < 0, 0.0, r), zero_f
    if op == "faceforward":
        return np.where(_f(_dot(c, b)) < 0, a, -np.asarray(a)), zero_f
    if op == "multiply_add":
        return np.asarray(a) * b + c, zero_f
    if op == "scale":
        return np.asarray(a) * _f(s), zero_f
    if op == "normalize":
        return _safe_normalize(a), zero_f
    if op == "fraction":
        return a - np.floor(a), zero_f
    if op == "sign":
        return _sign(a), zero_f
    if op == "modulo":
        return _math("modulo", a, b, None), zero_f
    if op == "wrap":
        return _wrap(a, b, c), zero_f
    simple = {"add", "subtract", "multiply", "divide", "absolute", "power", "minimum",
              "maximum", "floor", "ceil", "snap", "sine", "cosine", "tangent"}
    if op in simple:
        return _math(op, np.asarray(a), np.asarray(b), None), zero_f
    raise AssertionError(op)


def _map_range(interp: str, v, fmin, fmax, tmin, tmax, steps, clamp: bool, vector: bool):
    """Cycles' svm_node_map_range / svm_node_vector_map_range (+ the clamp Blender adds)."""
    if interp in ("linear", "stepped"):
        t = _safe_divide(v - fmin, np.asarray(fmax) - fmin)
        if interp == "stepped":
            st = np.asarray(steps)
            t = np.where(st > 0, np.floor(t * (st + 1.0)) / np.where(st > 0, st, 1.0), 0.0)
    else:
        if vector:
            t = _saturate(_safe_divide(v - fmin, np.asarray(fmax) - fmin))
        else:   # Cycles' smoothstep(edge0, edge1, x), flipped when from_min > from_max
            lo, hi = np.minimum(fmin, fmax), np.maximum(fmin, fmax)
            t = _saturate(_safe_divide(v - lo, hi - lo))
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


# --------------------------------------------------------------------------- colours
def _mix_color(blend: str, t, c1, c2):
    """Cycles' svm_mix (kernel/svm/color_util.h) with factor t (float values, broadcast)."""
    t = _f(t)
    tm = 1.0 - t
    c1, c2 = np.asarray(c1, float), np.asarray(c2, float)
    if blend == "mix":
        return c1 + t * (c2 - c1)
    if blend == "add":
        return c1 + t * c2
    if blend == "multiply":
        return c1 + t * (c1 * c2 - c1)
    if blend == "subtract":
        return c1 - t * c2
    if blend == "screen":
        return 1.0 - (tm + t * (1.0 - c2)) * (1.0 - c1)
    if blend == "overlay":
        return np.where(c1 < 0.5, c1 * (tm + 2.0 * t * c2),
                        1.0 - (tm + 2.0 * t * (1.0 - c2)) * (1.0 - c1))
    if blend == "divide":
        return np.where(c2 != 0, tm * c1 + t * _safe_divide(c1, c2), c1)
    if blend == "difference":
        return c1 + t * (np.abs(c1 - c2) - c1)
    if blend == "exclusion":
        return np.maximum(c1 + t * (c2 - 2.0 * c1 * c2), 0.0)
    if blend == "darken":
        return c1 + t * (np.minimum(c1, c2) - c1)
    if blend == "lighten":
        return c1 + t * (np.maximum(c1, c2) - c1)
    if blend == "dodge":
        tmp = 1.0 - t * c2
        q = np.where(tmp > 0, c1 / np.where(tmp > 0, tmp, 1.0), 1.0)
        return np.where(c1 != 0, np.where(tmp <= 0, 1.0, np.minimum(q, 1.0)), c1)
    if blend == "burn":
        tmp = tm + t * c2
        q = 1.0 - (1.0 - c1) / np.where(tmp > 0, tmp, 1.0)
        return np.where(tmp <= 0, 0.0, np.clip(q, 0.0, 1.0))
    if blend == "soft_light":
        scr = 1.0 - (1.0 - c2) * (1.0 - c1)
        return tm * c1 + t * ((1.0 - c1) * c2 * c1 + c1 * scr)
    if blend == "linear_light":
        return c1 + t * (2.0 * c2 - 1.0)
    raise AssertionError(blend)


def _ramp_table(stops, interpolation: str) -> np.ndarray:
    """(RAMP_TABLE, 4) RGBA of Blender's colour band evaluated at i / (RAMP_TABLE - 1)
    (BKE_colorband_evaluate, RGB mode): before the first stop its colour, after the last the
    last; between stops ``constant`` holds the left one, ``linear`` blends, ``ease`` blends
    with 3 f^2 - 2 f^3."""
    pos = np.array([s[0] for s in stops])
    rgba = np.array([tuple(s[1]) + (s[2],) for s in stops])
    x = np.arange(RAMP_TABLE) / (RAMP_TABLE - 1)
    if len(stops) == 1:
        return np.repeat(rgba, RAMP_TABLE, axis=0)
    a = np.searchsorted(pos, x, side="right")        # first stop with pos > x
    right, left = np.minimum(a, len(pos) - 1), np.maximum(a - 1, 0)
    span = pos[left] - pos[right]
    fac = np.where(span != 0, (x - pos[right]) / np.where(span != 0, span, 1.0), 0.0)
    if interpolation == "ease":
        fac = 3.0 * fac * fac - 2.0 * fac ** 3
    if interpolation == "constant":
        fac = np.ones_like(fac)
    out = (1.0 - fac)[:, None] * rgba[right] + fac[:, None] * rgba[left]
    out[x <= pos[0]] = rgba[0]
    out[a == len(pos)] = rgba[-1]
    return out


def _ramp_lookup(table: np.ndarray, f, interpolate: bool) -> np.ndarray:
    """Cycles' rgb_ramp_lookup: f clamped to [0, 1], table entry floor(f * (RAMP_TABLE - 1)),
    blended with the next one unless ``interpolate`` is off."""
    g = _saturate(np.nan_to_num(np.asarray(f, float))) * (RAMP_TABLE - 1)
    i = np.clip(g.astype(np.int64), 0, RAMP_TABLE - 1)
    t = (g - i)[..., None]
    out = table[i]
    if interpolate:
        out = np.where(t > 0, (1.0 - t) * out + t * table[np.minimum(i + 1, RAMP_TABLE - 1)],
                       out)
    return out


def srgb_to_linear(c):
    """The sRGB transfer function inverted (Cycles' color_srgb_to_linear; negatives -> 0)."""
    c = np.asarray(c, float)
    return np.where(c < 0.04045, np.maximum(c, 0.0) / 12.92,
                    ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4)


# --------------------------------------------------------------------------- textures
def _checker(p) -> np.ndarray:
    q = np.abs(np.floor((np.asarray(p) + CHECKER_BIAS) * (1.0 - CHECKER_BIAS))) % 2
    return ((q[..., 0] == q[..., 1]) == (q[..., 2] == 1)).astype(float)


def _gradient(kind: str, p) -> np.ndarray:
    p = np.asarray(p, float)
    x, y = p[..., 0], p[..., 1]
    if kind == "linear":
        f = x
    elif kind == "quadratic":
        f = np.maximum(x, 0.0) ** 2
    elif kind == "easing":
        r = _saturate(x)
        f = 3.0 * r * r - 2.0 * r ** 3
    elif kind == "diagonal":
        f = (x + y) * 0.5
    elif kind == "radial":
        f = np.arctan2(y, x) / (2.0 * np.pi) + 0.5
    else:
        r = np.maximum(SPHERE_BIAS - np.linalg.norm(p, axis=-1), 0.0)
        f = r * r if kind == "quadratic_sphere" else r
    return _saturate(f)


def _wrap_index(i, n: int, extension: str):
    if extension == "repeat":
        return i % n
    if extension == "mirror":
        m = np.abs(i + (i < 0)) % (2 * n)
        return np.where(m >= n, 2 * n - m - 1, m)
    return np.clip(i, 0, n - 1)


def _read(image, ix, iy, extension: str):
    """Pixels at column ix, row iy counted from the bottom (Cycles' convention); with "clip"
    indices outside the image read black."""
    h, w = image.shape[:2]
    if extension == "clip":
        inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
        px = image[h - 1 - np.clip(iy, 0, h - 1), np.clip(ix, 0, w - 1)]
        return np.where(inside[..., None], px, 0.0)
    return image[h - 1 - _wrap_index(iy, h, extension), _wrap_index(ix, w, extension)]


def sample_image(image: np.ndarray, x, y, interpolation: str, extension: str,
                 srgb: bool) -> np.ndarray:
    """(N, 3) of an (H, W, 3) image (rows top first) at texture coordinates (x, y), (0, 0) the
    bottom-left corner, like Cycles' CPU image kernel: "closest" reads pixel floor(x W),
    "linear" blends the four pixels around (x W - 0.5, y H - 0.5); ``extension`` repeat /
    extend (clamp) / clip (black outside) / mirror. ``srgb``: the pixels are sRGB-encoded and
    are linearized after interpolation (Cycles' 8-bit sRGB images)."""
    h, w = image.shape[:2]
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    x, y = np.nan_to_num(x), np.nan_to_num(y)
    if interpolation == "closest":
        out = _read(image, np.floor(x * w).astype(np.int64), np.floor(y * h).astype(np.int64),
                    extension)
    else:
        fx, fy = x * w - 0.5, y * h - 0.5
        ix, iy = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
        tx, ty = (fx - ix)[..., None], (fy - iy)[..., None]
        out = ((1 - ty) * ((1 - tx) * _read(image, ix, iy, extension)
                           + tx * _read(image, ix + 1, iy, extension))
               + ty * ((1 - tx) * _read(image, ix, iy + 1, extension)
                       + tx * _read(image, ix + 1, iy + 1, extension)))
    return srgb_to_linear(out) if srgb else out


def _box_weights(n, blend: float) -> np.ndarray:
    """(N, 3) blend weights of the x, y, z projections for object-space normals ``n``
    (Cycles' svm_node_tex_image_box)."""
    a = np.abs(np.asarray(n, float))
    s = a.sum(axis=-1, keepdims=True)
    a = a / np.where(s > 0, s, 1.0)
    nx, ny, nz = a[..., 0], a[..., 1], a[..., 2]
    limit = 0.5 * (1.0 + blend)
    w = np.zeros(a.shape)
    cx = (nx > limit * (nx + ny)) & (nx > limit * (nx + nz))
    cy = ~cx & (ny > limit * (nx + ny)) & (ny > limit * (ny + nz))
    cz = ~cx & ~cy & (nz > limit * (nx + nz)) & (nz > limit * (ny + nz))
    rest = ~(cx | cy | cz)
    w[cx, 0] = w[cy, 1] = w[cz, 2] = 1.0
    if blend <= 0:
        w[rest, 0] = 1.0
        return w
    with np.errstate(all="ignore"):
        c4 = rest & (nz < (1.0 - limit) * (ny + nx))
        c5 = rest & ~c4 & (nx < (1.0 - limit) * (ny + nz))
        c6 = rest & ~c4 & ~c5 & (ny < (1.0 - limit) * (nx + nz))
        c7 = rest & ~(c4 | c5 | c6)
        off = 0.5 * (1.0 - blend)
        wx = _saturate((nx / (nx + ny) - off) / blend)
        w[c4, 0], w[c4, 1] = wx[c4], 1.0 - wx[c4]
        wy = _saturate((ny / (ny + nz) - off) / blend)
        w[c5, 1], w[c5, 2] = wy[c5], 1.0 - wy[c5]
        wx2 = _saturate((nx / (nx + nz) - off) / blend)
        w[c6, 0], w[c6, 2] = wx2[c6], 1.0 - wx2[c6]
        three = ((2.0 - limit) * a + (limit - 1.0)) / (2.0 * limit - 1.0)
    w[c7] = three[c7]
    return w


def _image(node, vec, pts: ShadingPoints) -> np.ndarray:
    pr = node.props
    img, interp, ext, srgb = pr["image"], pr["interpolation"], pr["extension"], pr["srgb"]
    co = np.broadcast_to(np.asarray(vec, float), (len(pts), 3))
    if pr["projection"] == "flat":
        return sample_image(img, co[:, 0], co[:, 1], interp, ext, srgb)
    n = pts.normal @ np.asarray(pr["normal_matrix"]).T
    w = _box_weights(n, float(pr["blend"]))
    x, y, z = co[:, 0], co[:, 1], co[:, 2]
    out = np.zeros((len(pts), 3))
    for k, (u, v) in enumerate(((np.where(n[:, 0] < 0, 1.0 - y, y), z),
                                (np.where(n[:, 1] > 0, 1.0 - x, x), z),
                                (np.where(n[:, 2] > 0, 1.0 - y, y), x))):
        sel = w[:, k] > 0
        if sel.any():
            out[sel] += w[sel, k, None] * sample_image(img, u[sel], v[sel], interp, ext, srgb)
    return out


def equirectangular(d) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) of Blender's equirectangular map for directions d: u = 0.5 - atan2(dy, dx)/(2 pi)
    (+X at the centre), v = 0.5 + atan2(dz, hypot(dx, dy))/pi (the zenith at the top)."""
    d = np.asarray(d, float)
    u = 0.5 - np.arctan2(d[..., 1], d[..., 0]) / (2.0 * np.pi)
    v = 0.5 + np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1])) / np.pi
    return u, v


# --------------------------------------------------------------------------- noise
def _rot32(x, k: int):
    return (x << np.uint32(k)) | (x >> np.uint32(32 - k))


def _lookup3(a, b, c):
    """Bob Jenkins' lookup3 final mix of three uint32 arrays; returns c."""
    for x, y, k in (("c", "b", 14), ("a", "c", 11), ("b", "a", 25), ("c", "b", 16),
                    ("a", "c", 4), ("b", "a", 14), ("c", "b", 24)):
        v = {"a": a, "b": b, "c": c}
        v[x] = (v[x] ^ v[y]) - _rot32(v[y], k)
        a, b, c = v["a"], v["b"], v["c"]
    return c


def hash_uint2(kx, ky):
    """Cycles' hash_uint2 of uint32 arrays (lookup3 with two words)."""
    init = np.uint32((0xDEADBEEF + (2 << 2) + 13) & 0xFFFFFFFF)
    kx, ky = np.asarray(kx, np.uint32), np.asarray(ky, np.uint32)
    return _lookup3(init + kx, init + ky, np.broadcast_to(init, np.broadcast(kx, ky).shape))


def _hash_uint3(kx, ky, kz):
    init = np.uint32((0xDEADBEEF + (3 << 2) + 13) & 0xFFFFFFFF)
    return _lookup3(init + kx, init + ky, init + kz)


def _float3_offset(seed: float) -> np.ndarray:
    """Cycles' random_float3_offset: 100 + 100 * hash((seed, i)) / (2^32 - 1) per axis, in
    float32 as Cycles computes it (the noise texture's seeds for its colour and distortion)."""
    bits = lambda x: np.float32(x).view(np.uint32)       # noqa: E731
    h = hash_uint2(np.full(3, bits(seed)), np.array([bits(i) for i in (0.0, 1.0, 2.0)]))
    unit = h.astype(np.float32) / np.float32(0xFFFFFFFF)
    return (np.float32(100.0) + unit * np.float32(100.0)).astype(np.float64)


NOISE_REPEAT = 100000.0     # Cycles' Perlin noise repeats every 1e5 on each axis
NOISE_SCALE3 = 0.9820       # Cycles' noise_scale3: 3D Perlin noise remapped to about [-1, 1]


def _snoise3(p) -> np.ndarray:
    """Cycles' snoise_3d: signed 3D Perlin noise (lattice gradients from lookup3 hashes,
    quintic fade) of points p (..., 3)."""
    p = np.fmod(p, NOISE_REPEAT)
    cell = np.floor(p)
    f = p - cell
    ijk = (cell.astype(np.int64) & 0xFFFFFFFF).astype(np.uint32)
    u = f * f * f * (f * (f * 6.0 - 15.0) + 10.0)
    corner = {}
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                h = _hash_uint3(ijk[..., 0] + np.uint32(dx), ijk[..., 1] + np.uint32(dy),
                                ijk[..., 2] + np.uint32(dz)) & np.uint32(15)
                x, y, z = f[..., 0] - dx, f[..., 1] - dy, f[..., 2] - dz
                a = np.where(h < 8, x, y)
                b = np.where(h < 4, y, np.where((h == 12) | (h == 14), x, z))
                corner[dx, dy, dz] = np.where(h & 1, -a, a) + np.where(h & 2, -b, b)
    lerp = lambda a, b, t: (1.0 - t) * a + t * b       # noqa: E731
    ux, uy, uz = u[..., 0], u[..., 1], u[..., 2]
    yz = {(dy, dz): lerp(corner[0, dy, dz], corner[1, dy, dz], ux) for dy in (0, 1)
          for dz in (0, 1)}
    z0, z1 = lerp(yz[0, 0], yz[1, 0], uy), lerp(yz[0, 1], yz[1, 1], uy)
    return NOISE_SCALE3 * lerp(z0, z1, uz)


def _fractal(kind: str, p, detail, rough, lac, offset, gain, normalize: bool) -> np.ndarray:
    """Cycles' fractal noise (kernel/svm/fractal_noise.h) of points p (N, 3); the octave
    parameters may vary per point (a point stops at its own detail)."""
    n = np.floor(detail).astype(np.int64)
    rmd = detail - np.floor(detail)
    top = int(np.max(n)) if np.size(n) else 0
    one = np.ones(p.shape[:-1])
    if kind == "fbm":
        scale, amp, maxamp, total = one, one, 0.0 * one, 0.0 * one
        for i in range(top + 1):
            on = i <= n
            t = _snoise3(_f(scale) * p)
            total = np.where(on, total + t * amp, total)
            maxamp = np.where(on, maxamp + amp, maxamp)
            amp, scale = np.where(on, amp * rough, amp), np.where(on, scale * lac, scale)
        total2 = total + _snoise3(_f(scale) * p) * amp
        if normalize:
            a, b = 0.5 * total / maxamp + 0.5, 0.5 * total2 / (maxamp + amp) + 0.5
        else:
            a, b = total, total2
        return np.where(rmd != 0, a + rmd * (b - a), a)
    if kind == "multifractal":
        value, pwr, q = one, one, p
        for i in range(top + 1):
            on = i <= n
            value = np.where(on, value * (pwr * _snoise3(q) + 1.0), value)
            pwr, q = np.where(on, pwr * rough, pwr), np.where(_f(on), q * _f(lac), q)
        return np.where(rmd != 0, value * (rmd * pwr * _snoise3(q) + 1.0), value)
    if kind == "hetero_terrain":
        pwr, value, q = rough * one, offset + _snoise3(p), p * _f(lac)
        for i in range(1, top + 1):
            on = i <= n
            value = np.where(on, value + (_snoise3(q) + offset) * pwr * value, value)
            pwr, q = np.where(on, pwr * rough, pwr), np.where(_f(on), q * _f(lac), q)
        return np.where(rmd != 0, value + rmd * (_snoise3(q) + offset) * pwr * value, value)
    if kind == "hybrid_multifractal":
        pwr, value, weight, q, alive = one, 0.0 * one, one, p, np.ones(p.shape[:-1], bool)
        for i in range(top + 1):
            alive = alive & (weight > 0.001) & (i <= n)
            w = np.minimum(weight, 1.0)
            signal = (_snoise3(q) + offset) * pwr
            value = np.where(alive, value + w * signal, value)
            weight = np.where(alive, w * gain * signal, weight)
            pwr, q = np.where(alive, pwr * rough, pwr), np.where(_f(alive), q * _f(lac), q)
        last = (rmd != 0) & (weight > 0.001)
        signal = (_snoise3(q) + offset) * pwr
        return np.where(last, value + rmd * np.minimum(weight, 1.0) * signal, value)
    # ridged multifractal (no fractional octave)
    signal = offset - np.abs(_snoise3(p))
    signal = signal * signal
    value, pwr, q = signal, rough * one, p
    for i in range(1, top + 1):
        on = i <= n
        q = np.where(_f(on), q * _f(lac), q)
        weight = _saturate(signal * gain)
        s = offset - np.abs(_snoise3(q))
        s = s * s * weight
        value, signal = np.where(on, value + s * pwr, value), np.where(on, s, signal)
        pwr = np.where(on, pwr * rough, pwr)
    return value


def _noise(node, inp, n: int, want) -> dict:
    """Cycles' 3D Noise Texture: fractal Perlin noise of vector * scale, optionally distorted;
    Color is the value and two noises at offset points."""
    pr = node.props
    p = np.broadcast_to(np.asarray(inp["vector"], float), (n, 3)) * _f(inp["scale"])
    per_point = lambda k: np.broadcast_to(np.asarray(inp[k], float), (n,))   # noqa: E731
    detail = np.clip(per_point("detail"), 0.0, 15.0)
    args = (detail, np.maximum(per_point("roughness"), 0.0), per_point("lacunarity"),
            per_point("offset"), per_point("gain"), pr["normalize"])
    dist = per_point("distortion")
    if np.any(dist != 0):
        p = p + np.stack([_snoise3(p + _float3_offset(float(k))) for k in range(3)], -1) * \
            _f(dist)
    value = _fractal(pr["noise_type"], p, *args)
    out = {"fac": value}
    if "color" in want:
        out["color"] = np.stack([value] + [_fractal(pr["noise_type"], p + _float3_offset(s),
                                                    *args) for s in (3.0, 4.0)], -1)
    return out


# --------------------------------------------------------------------------- nodes
def _mapping(kind: str, v, loc, rot, scale):
    """Cycles' svm_mapping: rotation is Euler XYZ (R = Rz Ry Rx), radians."""
    rx, ry, rz = (np.asarray(rot, float)[..., i] for i in range(3))
    cx, cy, cz, sx, sy, sz = np.cos(rx), np.cos(ry), np.cos(rz), np.sin(rx), np.sin(ry), np.sin(rz)
    r = np.stack([np.stack([cy * cz, sy * sx * cz - cx * sz, sy * cx * cz + sx * sz], -1),
                  np.stack([cy * sz, sy * sx * sz + cx * cz, sy * cx * sz - sx * cz], -1),
                  np.stack([-sy, cy * sx, cy * cx], -1)], -2)
    rot_v = lambda m, x: np.einsum("...ij,...j->...i", m, x)
    v, loc, scale = np.asarray(v, float), np.asarray(loc, float), np.asarray(scale, float)
    if kind == "point":
        return rot_v(r, v * scale) + loc
    if kind == "texture":
        return _safe_divide(rot_v(np.swapaxes(r, -1, -2), v - loc), scale)
    if kind == "vector":
        return rot_v(r, v * scale)
    return _safe_normalize(rot_v(r, _safe_divide(v, scale)))


def _run(node, inp: dict, pts: ShadingPoints, want: set) -> dict:
    """Outputs of one node from its (converted) input values (at least those in ``want``)."""
    t, pr = node.type, node.props
    if t == "tex_coord":
        n, wi = pts.normal, pts.incoming
        return {"generated": _affine(pr["generated_matrix"], pts.position),
                "normal": _safe_normalize(n @ np.asarray(pr["normal_matrix"]).T),
                "uv": np.column_stack([pts.uv, np.zeros(len(pts))]),
                "object": _affine(pr["object_matrix"], pts.position),
                "camera": _affine(pr["camera_matrix"], pts.position),
                "reflection": 2.0 * _f(_dot(n, wi)) * n - wi}
    if t == "geometry":
        return {"position": pts.position, "normal": pts.normal, "true_normal": pts.true_normal,
                "incoming": pts.incoming, "backfacing": pts.backfacing.astype(float)}
    if t == "object_info":
        return {k: np.asarray(pr[k], float) for k in NODE_TYPES[t].outputs}
    if t == "mapping":
        return {"vector": _mapping(pr["vector_type"], inp["vector"], inp["location"],
                                   inp["rotation"], inp["scale"])}
    if t in ("separate_xyz", "separate_color"):
        v = np.asarray(inp["vector" if t == "separate_xyz" else "color"], float)
        names = NODE_TYPES[t].outputs
        return {k: v[..., i] for i, k in enumerate(names)}
    if t in ("combine_xyz", "combine_color"):
        names = list(NODE_TYPES[t].inputs)
        out = np.stack(np.broadcast_arrays(*(np.asarray(inp[k], float) for k in names)), -1)
        return {"vector" if t == "combine_xyz" else "color": out}
    if t == "math":
        r = _math(pr["operation"], np.asarray(inp["a"], float), np.asarray(inp["b"], float),
                  np.asarray(inp["c"], float))
        return {"value": _saturate(r) if pr["clamp"] else r}
    if t == "vector_math":
        vec, val = _vector_math(pr["operation"], np.asarray(inp["a"], float),
                                np.asarray(inp["b"], float), np.asarray(inp["c"], float),
                                np.asarray(inp["scale"], float))
        return {"vector": vec, "value": val}
    if t in ("map_range", "map_range_vector"):
        vector = t == "map_range_vector"
        out = _map_range(pr["interpolation"], np.asarray(inp["vector" if vector else "value"]),
                         inp["from_min"], inp["from_max"], inp["to_min"], inp["to_max"],
                         inp["steps"], pr["clamp"], vector)
        return {"vector" if vector else "result": out}
    if t == "clamp":
        lo, hi = np.asarray(inp["min"], float), np.asarray(inp["max"], float)
        if pr["clamp_type"] == "range":
            lo, hi = np.minimum(lo, hi), np.maximum(lo, hi)
        return {"result": np.minimum(np.maximum(inp["value"], lo), hi)}
    if t in ("mix_float", "mix_vector"):
        f = np.asarray(inp["factor"], float)
        f = _saturate(f) if pr["clamp_factor"] else f
        return {"result": np.asarray(inp["a"]) * (1.0 - f) + np.asarray(inp["b"]) * f}
    if t == "mix_color":
        f = np.asarray(inp["factor"], float)
        out = _mix_color(pr["blend"], _saturate(f) if pr["clamp_factor"] else f,
                         inp["a"], inp["b"])
        return {"result": _saturate(out) if pr["clamp_result"] else out}
    if t == "color_ramp":
        c = _ramp_lookup(_ramp_table(pr["stops"], pr["interpolation"]), inp["factor"],
                         pr["interpolation"] != "constant")
        return {"color": c[..., :3], "alpha": c[..., 3]}
    if t == "invert":
        c = np.asarray(inp["color"], float)
        return {"color": c + _f(inp["factor"]) * (1.0 - 2.0 * c)}
    if t == "gamma":
        c, g = np.asarray(inp["color"], float), _f(inp["gamma"])
        out = np.where(c > 0, np.power(np.where(c > 0, c, 1.0), g), c)
        return {"color": np.where(g == 0, 1.0, out)}
    if t == "bright_contrast":
        a = 1.0 + _f(inp["contrast"])
        b = _f(inp["bright"]) - _f(inp["contrast"]) * 0.5
        return {"color": np.maximum(a * inp["color"] + b, 0.0)}
    if t == "rgb_to_bw":
        return {"value": _gray(np.asarray(inp["color"], float))}
    if t == "checker":
        f = _checker(np.asarray(inp["vector"], float) * _f(inp["scale"]))
        return {"color": np.where(_f(f) == 1.0, inp["color1"], inp["color2"]), "fac": f}
    if t == "gradient":
        f = _gradient(pr["gradient_type"], inp["vector"])
        return {"color": _f(f) * np.ones(3), "fac": f}
    if t == "image":
        return {"color": _image(node, inp["vector"], pts)}
    if t == "noise":
        return _noise(node, inp, len(pts), want)
    if t == "environment":
        u, v = equirectangular(_safe_normalize(np.broadcast_to(
            np.asarray(inp["vector"], float), (len(pts), 3))))
        return {"color": sample_image(pr["image"], u, v, pr["interpolation"], "repeat",
                                      pr["srgb"])}
    if t in ("emission", "background"):
        e = np.asarray(inp["color"], float) * _f(inp["strength"])
        return {t: Closure(emission=e, albedo=np.zeros(3))}
    if t == "diffuse":
        return {"bsdf": Closure(emission=np.zeros(3), albedo=np.asarray(inp["color"], float))}
    if t == "principled":
        e = np.asarray(inp["emission_color"], float) * _f(inp["emission_strength"])
        return {"bsdf": Closure(emission=e, albedo=np.asarray(inp["base_color"], float))}
    if t == "mix_shader":
        f = _f(_saturate(np.asarray(inp["factor"], float)))
        a, b = _closure(inp["shader1"]), _closure(inp["shader2"])
        return {"shader": Closure(emission=(1.0 - f) * a.emission + f * b.emission,
                                  albedo=(1.0 - f) * a.albedo + f * b.albedo)}
    if t == "add_shader":
        a, b = _closure(inp["shader1"]), _closure(inp["shader2"])
        return {"shader": Closure(emission=a.emission + b.emission, albedo=a.albedo + b.albedo)}
    raise AssertionError(t)


def _closure(c) -> Closure:
    return c if c is not None else Closure(emission=np.zeros(3), albedo=np.zeros(3))


def _needed(graph: ShaderGraph) -> set:
    """Names of the nodes the output depends on."""
    need, todo = set(), [graph.output.node]
    by_name = {n.name: n for n in graph.nodes}
    while todo:
        name = todo.pop()
        if name in need:
            continue
        need.add(name)
        todo.extend(v.node for v in by_name[name].links.values())
    return need


def evaluate(graph: ShaderGraph, pts: ShadingPoints) -> Closure:
    """The closure at the graph's output for every shading point: emission and albedo (N, 3),
    finite (non-finite components are 0)."""
    values: dict = {}
    need = _needed(graph)
    types = {n.name: n.type for n in graph.nodes}
    used = {(lk.node, lk.output) for n in graph.nodes for lk in n.links.values()}
    used.add((graph.output.node, graph.output.output))
    with np.errstate(all="ignore"):
        for node in graph.nodes:
            if node.name not in need:
                continue
            spec = NODE_TYPES[node.type]
            inp = {}
            for key, (kind, _) in spec.inputs.items():
                link = node.links.get(key)
                if link is not None:
                    src = NODE_TYPES[types[link.node]].outputs[link.output]
                    inp[key] = _convert(values[(link.node, link.output)], src, kind)
                else:
                    v = node.inputs.get(key)
                    inp[key] = v if kind == SHADER else np.asarray(v, float)
            want = {o for o in spec.outputs if (node.name, o) in used}
            for key, val in _run(node, inp, pts, want).items():
                values[(node.name, key)] = val
        out = graph.output
        kind = NODE_TYPES[types[out.node]].outputs[out.output]
        cl = _closure(_convert(values[(out.node, out.output)], kind, SHADER))
        n = len(pts)
        em = np.broadcast_to(np.asarray(cl.emission, float), (n, 3))
        al = np.broadcast_to(np.asarray(cl.albedo, float), (n, 3))
        return Closure(emission=np.where(np.isfinite(em), em, 0.0),
                       albedo=np.where(np.isfinite(al), al, 0.0))
