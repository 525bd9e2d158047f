"""Procedural texture nodes: Checker, Gradient and Noise (Cycles' fractal Perlin noise with its
lookup3 hashes), after Cycles' svm kernels (kernel/svm/checker.h, gradient.h, noise.h,
fractal_noise.h), in float64 (the noise's seed offsets in float32 as Cycles computes them)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .values import expand, saturate

CHECKER_BIAS = 1e-6           # Cycles' svm_checker: p = (p + 1e-6) * (1 - 1e-6)
SPHERE_BIAS = 0.999999        # Cycles' spherical gradients: r = max(0.999999 - |p|, 0)
NOISE_REPEAT = 100000.0       # Cycles' Perlin noise repeats every 1e5 on each axis
NOISE_SCALE3 = 0.9820         # Cycles' noise_scale3: 3D Perlin noise remapped to about [-1, 1]
HYBRID_MIN_WEIGHT = 0.001     # Cycles' hybrid multifractal stops adding octaves below this weight


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
        r = saturate(x)
        f = 3.0 * r * r - 2.0 * r ** 3
    elif kind == "diagonal":
        f = (x + y) * 0.5
    elif kind == "radial":
        f = np.arctan2(y, x) / (2.0 * np.pi) + 0.5
    else:
        r = np.maximum(SPHERE_BIAS - np.linalg.norm(p, axis=-1), 0.0)
        f = r * r if kind == "quadratic_sphere" else r
    return saturate(f)


# --------------------------------------------------------------------------- hashes
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



# --------------------------------------------------------------------------- fractal noise
@dataclass
class _Octaves:
    """A fractal's parameters per point: ``n`` whole octaves (int64) and the fraction ``rmd``
    of one more, ``top`` the most octaves of any point, ``one`` ones (N,); roughness,
    lacunarity, offset, gain per point and ``normalize`` (fBM only)."""

    n: np.ndarray
    rmd: np.ndarray
    top: int
    one: np.ndarray
    rough: np.ndarray
    lac: np.ndarray
    offset: np.ndarray
    gain: np.ndarray
    normalize: bool


def _fbm(p, o: _Octaves) -> np.ndarray:
    scale, amp, maxamp, total = o.one, o.one, 0.0 * o.one, 0.0 * o.one
    for i in range(o.top + 1):
        on = i <= o.n
        t = _snoise3(expand(scale) * p)
        total = np.where(on, total + t * amp, total)
        maxamp = np.where(on, maxamp + amp, maxamp)
        amp, scale = np.where(on, amp * o.rough, amp), np.where(on, scale * o.lac, scale)
    total2 = total + _snoise3(expand(scale) * p) * amp
    if o.normalize:
        a, b = 0.5 * total / maxamp + 0.5, 0.5 * total2 / (maxamp + amp) + 0.5
    else:
        a, b = total, total2
    return np.where(o.rmd != 0, a + o.rmd * (b - a), a)


def _multifractal(p, o: _Octaves) -> np.ndarray:
    value, pwr, q = o.one, o.one, p
    for i in range(o.top + 1):
        on = i <= o.n
        value = np.where(on, value * (pwr * _snoise3(q) + 1.0), value)
        pwr, q = np.where(on, pwr * o.rough, pwr), np.where(expand(on), q * expand(o.lac), q)
    return np.where(o.rmd != 0, value * (o.rmd * pwr * _snoise3(q) + 1.0), value)


def _hetero_terrain(p, o: _Octaves) -> np.ndarray:
    pwr, value, q = o.rough * o.one, o.offset + _snoise3(p), p * expand(o.lac)
    for i in range(1, o.top + 1):
        on = i <= o.n
        value = np.where(on, value + (_snoise3(q) + o.offset) * pwr * value, value)
        pwr, q = np.where(on, pwr * o.rough, pwr), np.where(expand(on), q * expand(o.lac), q)
    return np.where(o.rmd != 0, value + o.rmd * (_snoise3(q) + o.offset) * pwr * value, value)


def _hybrid_multifractal(p, o: _Octaves) -> np.ndarray:
    pwr, value, weight, q = o.one, 0.0 * o.one, o.one, p
    alive = np.ones(p.shape[:-1], bool)
    for i in range(o.top + 1):
        alive = alive & (weight > HYBRID_MIN_WEIGHT) & (i <= o.n)
        w = np.minimum(weight, 1.0)
        signal = (_snoise3(q) + o.offset) * pwr
        value = np.where(alive, value + w * signal, value)
        weight = np.where(alive, w * o.gain * signal, weight)
        pwr, q = np.where(alive, pwr * o.rough, pwr), np.where(expand(alive), q * expand(o.lac), q)
    last = (o.rmd != 0) & (weight > HYBRID_MIN_WEIGHT)
    signal = (_snoise3(q) + o.offset) * pwr
    return np.where(last, value + o.rmd * np.minimum(weight, 1.0) * signal, value)


def _ridged_multifractal(p, o: _Octaves) -> np.ndarray:
    """(No fractional octave.)"""
    signal = o.offset - np.abs(_snoise3(p))
    signal = signal * signal
    value, pwr, q = signal, o.rough * o.one, p
    for i in range(1, o.top + 1):
        on = i <= o.n
        q = np.where(expand(on), q * expand(o.lac), q)
        weight = saturate(signal * o.gain)
        s = o.offset - np.abs(_snoise3(q))
        s = s * s * weight
        value, signal = np.where(on, value + s * pwr, value), np.where(on, s, signal)
        pwr = np.where(on, pwr * o.rough, pwr)
    return value


FRACTALS = {"fbm": _fbm, "multifractal": _multifractal, "hetero_terrain": _hetero_terrain,
            "hybrid_multifractal": _hybrid_multifractal,
            "ridged_multifractal": _ridged_multifractal}


def _octaves(detail, rough, lac, offset, gain, normalize: bool) -> _Octaves:
    """The octave parameters of Cycles' fractal noise; a point stops at its own detail."""
    n = np.floor(detail).astype(np.int64)
    top = int(np.max(n)) if np.size(n) else 0
    return _Octaves(n=n, rmd=detail - np.floor(detail), top=top, one=np.ones(np.shape(detail)),
                    rough=rough, lac=lac, offset=offset, gain=gain, normalize=normalize)


# --------------------------------------------------------------------------- nodes
# Every node evaluation: (node, inputs, shading points, wanted outputs) -> {output: value}
def checker(node, inp, pts, want) -> dict:
    f = _checker(np.asarray(inp["vector"], float) * expand(inp["scale"]))
    return {"color": np.where(expand(f) == 1.0, inp["color1"], inp["color2"]), "fac": f}


def gradient(node, inp, pts, want) -> dict:
    f = _gradient(node.props["gradient_type"], inp["vector"])
    return {"color": expand(f) * np.ones(3), "fac": f}


def noise(node, inp, pts, want) -> dict:
    """Cycles' 3D Noise Texture: fractal Perlin noise of vector * scale, optionally distorted;
    Color is the value and two noises at offset points."""
    pr, n = node.props, len(pts)
    p = np.broadcast_to(np.asarray(inp["vector"], float), (n, 3)) * expand(inp["scale"])
    per_point = lambda k: np.broadcast_to(np.asarray(inp[k], float), (n,))   # noqa: E731
    octaves = _octaves(np.clip(per_point("detail"), 0.0, 15.0),
                       np.maximum(per_point("roughness"), 0.0), per_point("lacunarity"),
                       per_point("offset"), per_point("gain"), pr["normalize"])
    dist = per_point("distortion")
    if np.any(dist != 0):
        p = p + np.stack([_snoise3(p + _float3_offset(float(k))) for k in range(3)], -1) * \
            expand(dist)
    fractal = FRACTALS[pr["noise_type"]]
    value = fractal(p, octaves)
    out = {"fac": value}
    if "color" in want:
        out["color"] = np.stack([value] + [fractal(p + _float3_offset(s), octaves)
                                           for s in (3.0, 4.0)], -1)
    return out


NODES = {"checker": checker, "gradient": gradient, "noise": noise}
