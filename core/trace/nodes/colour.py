"""Colour nodes: Mix Color's blend modes, Color Ramp, Invert, Gamma, Bright / Contrast, RGB to
BW, after Cycles' svm kernels (kernel/svm/color_util.h, ramp.h), in float64; and the sRGB
transfer function."""

from __future__ import annotations

import numpy as np

from .values import expand, gray, safe_divide, saturate

# Cycles reads colour ramps from a table of 257 entries, the ramp at i / 256 (Blender's colour
# band table, CM_TABLE + 1), blended linearly: measured against Cycles 4.2 and 5.0, where a stop
# between two entries is smoothed over their interval.
RAMP_TABLE = 257


def srgb_to_linear(c):
    """The sRGB transfer function inverted (Cycles' color_srgb_to_linear; negatives -> 0)."""
    c = np.asarray(c, float)
    return np.where(c < 0.04045, np.maximum(c, 0.0) / 12.92,
                    ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4)


def _dodge(c1, c2, t, tm):
    tmp = 1.0 - t * c2
    q = np.where(tmp > 0, c1 / np.where(tmp > 0, tmp, 1.0), 1.0)
    return np.where(c1 != 0, np.where(tmp <= 0, 1.0, np.minimum(q, 1.0)), c1)


def _burn(c1, c2, t, tm):
    tmp = tm + t * c2
    q = 1.0 - (1.0 - c1) / np.where(tmp > 0, tmp, 1.0)
    return np.where(tmp <= 0, 0.0, np.clip(q, 0.0, 1.0))


def _soft_light(c1, c2, t, tm):
    scr = 1.0 - (1.0 - c2) * (1.0 - c1)
    return tm * c1 + t * ((1.0 - c1) * c2 * c1 + c1 * scr)


# Cycles' svm_mix, one entry per blend mode: (c1, c2, factor t, 1 - t) -> colour
BLEND = {
    "mix": lambda c1, c2, t, tm: c1 + t * (c2 - c1),
    "add": lambda c1, c2, t, tm: c1 + t * c2,
    "multiply": lambda c1, c2, t, tm: c1 + t * (c1 * c2 - c1),
    "subtract": lambda c1, c2, t, tm: c1 - t * c2,
    "screen": lambda c1, c2, t, tm: 1.0 - (tm + t * (1.0 - c2)) * (1.0 - c1),
    "overlay": lambda c1, c2, t, tm: np.where(c1 < 0.5, c1 * (tm + 2.0 * t * c2),
                                              1.0 - (tm + 2.0 * t * (1.0 - c2)) * (1.0 - c1)),
    "divide": lambda c1, c2, t, tm: np.where(c2 != 0, tm * c1 + t * safe_divide(c1, c2), c1),
    "difference": lambda c1, c2, t, tm: c1 + t * (np.abs(c1 - c2) - c1),
    "exclusion": lambda c1, c2, t, tm: np.maximum(c1 + t * (c2 - 2.0 * c1 * c2), 0.0),
    "darken": lambda c1, c2, t, tm: c1 + t * (np.minimum(c1, c2) - c1),
    "lighten": lambda c1, c2, t, tm: c1 + t * (np.maximum(c1, c2) - c1),
    "dodge": _dodge,
    "burn": _burn,
    "soft_light": _soft_light,
    "linear_light": lambda c1, c2, t, tm: c1 + t * (2.0 * c2 - 1.0),
}


def _mix_color(blend: str, t, c1, c2):
    """Cycles' svm_mix with factor t (float values, broadcast)."""
    t = expand(t)
    return BLEND[blend](np.asarray(c1, float), np.asarray(c2, float), t, 1.0 - t)


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
    g = saturate(np.nan_to_num(np.asarray(f, float))) * (RAMP_TABLE - 1)
    i = np.clip(g.astype(np.int64), 0, RAMP_TABLE - 1)
    t = (g - i)[..., None]
    out = table[i]
    if interpolate:
        out = np.where(t > 0, (1.0 - t) * out + t * table[np.minimum(i + 1, RAMP_TABLE - 1)],
                       out)
    return out


# --------------------------------------------------------------------------- nodes
# Every node evaluation: (node, inputs, shading points, wanted outputs) -> {output: value}
def mix_color(node, inp, pts, want) -> dict:
    pr = node.props
    f = np.asarray(inp["factor"], float)
    out = _mix_color(pr["blend"], saturate(f) if pr["clamp_factor"] else f, inp["a"], inp["b"])
    return {"result": saturate(out) if pr["clamp_result"] else out}


def color_ramp(node, inp, pts, want) -> dict:
    pr = node.props
    c = _ramp_lookup(_ramp_table(pr["stops"], pr["interpolation"]), inp["factor"],
                     pr["interpolation"] != "constant")
    return {"color": c[..., :3], "alpha": c[..., 3]}


def invert(node, inp, pts, want) -> dict:
    c = np.asarray(inp["color"], float)
    return {"color": c + expand(inp["factor"]) * (1.0 - 2.0 * c)}


def gamma(node, inp, pts, want) -> dict:
    c, g = np.asarray(inp["color"], float), expand(inp["gamma"])
    out = np.where(c > 0, np.power(np.where(c > 0, c, 1.0), g), c)
    return {"color": np.where(g == 0, 1.0, out)}


def bright_contrast(node, inp, pts, want) -> dict:
    a = 1.0 + expand(inp["contrast"])
    b = expand(inp["bright"]) - expand(inp["contrast"]) * 0.5
    return {"color": np.maximum(a * inp["color"] + b, 0.0)}


def rgb_to_bw(node, inp, pts, want) -> dict:
    return {"value": gray(np.asarray(inp["color"], float))}


NODES = {"mix_color": mix_color, "color_ramp": color_ramp, "invert": invert, "gamma": gamma,
         "bright_contrast": bright_contrast, "rgb_to_bw": rgb_to_bw}
