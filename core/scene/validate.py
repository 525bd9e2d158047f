"""Checks of JSON scene values: each returns the value as the model stores it or raises
:class:`SceneError` naming the field's JSON path (``at_key``) and the problem; the magnitude limits
of the format (docs/scene-format.md, "Supported range")."""

from __future__ import annotations

import difflib

import numpy as np

# Magnitudes (docs/scene-format.md, "Supported range"). Any number: products of a few stay far
# from float overflow (shading multiplies colours, powers, strengths). Positions (m): the
# tracer's tolerances are fractions of the object's size (1e-9 of its box diagonal D for a hit,
# 1e-7 between events), so one control point 1e9 m out makes them metres and the object
# vanishes. And the object must lie within MAX_OBJECT_OFFSET * D of the origin: coordinates
# are rounded to ~1.1e-16 |x|, which must stay below the Newton tolerance 1e-11 D (measured:
# a sphere 2e4 D from the origin traces as at the origin, 2e5 D away it does not).
MAX_NUMBER = 1e12
MAX_COORD = 1e5
MAX_OBJECT_OFFSET = 1e4
# A degenerate object has no surface to trace: its points (NURBS control points, mesh vertices)
# span at most COINCIDENT times their distance from the origin (or 1 m), one point up to float
# rounding; or they lie within COLLINEAR times the object's size of one line (a NURBS surface
# lies in the hull of its control points, so it has no area; COLLINEAR is the tracer's
# self-intersection guard, 1e-9 of the size).
COINCIDENT = 1e-12
COLLINEAR = 1e-9
# A mesh's corner normal must have length 1 within this (float32 normals, as Blender stores
# them, are unit to ~1e-7; a normal off by more was not normalized).
UNIT_NORMAL_TOL = 1e-3


class SceneError(ValueError):
    """An invalid scene; the message starts with the JSON path of the field."""


# --------------------------------------------------------------------------- primitive checks
def at_key(path: str, key: str | int) -> str:
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else key


def at_index(path: str, idx) -> str:
    return path + "".join(f"[{int(i)}]" for i in idx)


def fail(path: str, msg: str):
    raise SceneError(f"{path or 'top level'}: {msg}")


def type_name(v) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean",
            type(None): "null"}.get(type(v), type(v).__name__)


def read_fields(v, path: str, required=(), optional=(), what: str = "") -> dict:
    """Check that ``v`` is a JSON object with all ``required`` and no unknown keys."""
    if not isinstance(v, dict):
        fail(path, f"expected an object (got {type_name(v)})")
    allowed = tuple(required) + tuple(optional)
    for k in v:
        if k not in allowed:
            near = difflib.get_close_matches(k, allowed, n=1)
            hint = f"; did you mean {near[0]!r}?" if near else f"; allowed: {', '.join(allowed)}"
            fail(path, f"unknown key {k!r}{what}{hint}")
    for k in required:
        if k not in v:
            fail(path, f"missing required key {k!r}")
    return v


def read_number(v, path: str, gt=None, ge=None, le=None) -> float:
    if type(v) not in (int, float):
        fail(path, f"expected a number (got {type_name(v)} {v!r})")
    try:
        x = float(v)
    except OverflowError:
        fail(path, f"must be finite (got {v!r})")
    if not np.isfinite(x):
        fail(path, f"must be finite (got {x!r})")
    if abs(x) > MAX_NUMBER:
        fail(path, f"magnitude must be <= {MAX_NUMBER:g} (got {x!r})")
    if gt is not None and not x > gt:
        fail(path, f"must be > {gt} (got {x!r})")
    if ge is not None and not x >= ge:
        fail(path, f"must be >= {ge} (got {x!r})")
    if le is not None and not x <= le:
        fail(path, f"must be <= {le} (got {x!r})")
    return x


def read_integer(v, path: str, lo=None, hi=None) -> int:
    if type(v) is not int:
        fail(path, f"expected an integer (got {type_name(v)} {v!r})")
    if lo is not None and v < lo:
        fail(path, f"must be >= {lo} (got {v})")
    if hi is not None and v > hi:
        fail(path, f"must be <= {hi} (got {v})")
    return v


def read_string(v, path: str, choices=None, what: str = "value") -> str:
    if type(v) is not str or not v:
        fail(path, f"expected a non-empty string (got {type_name(v)} {v!r})")
    if choices is not None and v not in choices:
        fail(path, f"unknown {what} {v!r} (expected one of: {', '.join(choices)})")
    return v


def read_boolean(v, path: str) -> bool:
    if type(v) is not bool:
        fail(path, f"expected true or false (got {type_name(v)} {v!r})")
    return v


def read_array(v, path: str, shape: tuple, integer: bool = False,
           limit: float = MAX_NUMBER) -> np.ndarray:
    """Nested JSON lists -> float64 (or int64) array of ``shape`` (None: any length, the same for
    all siblings); every entry must be a finite number of magnitude <= ``limit`` (an integer
    when ``integer``)."""
    dims = list(shape)
    ok = (int,) if integer else (int, float)

    def walk(x, p, d):
        if d == len(dims):
            if type(x) not in ok:
                what = "an integer" if integer else "a number"
                fail(p, f"expected {what} (got {type_name(x)} {x!r})")
            return
        if not isinstance(x, (list, tuple)):
            fail(p, f"expected a list (got {type_name(x)})")
        if dims[d] is None:
            dims[d] = len(x)
        elif len(x) != dims[d]:
            fail(p, f"expected {dims[d]} entries (got {len(x)})")
        if d == len(dims) - 1 and all(type(e) in ok for e in x):
            return
        for i, e in enumerate(x):
            walk(e, at_key(p, i), d + 1)

    walk(v, path, 0)
    dims = [0 if n is None else n for n in dims]
    try:
        arr = np.array(v, dtype=np.int64 if integer else np.float64).reshape(dims)
    except OverflowError:
        fail(path, "integer out of range" if integer else "number out of range")
    if not integer:
        bad = ~np.isfinite(arr)
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            fail(at_index(path, idx), f"must be finite (got {float(arr[idx])!r})")
        big = np.abs(arr) > limit
        if big.any():
            idx = tuple(int(i) for i in np.argwhere(big)[0])
            fail(at_index(path, idx), f"magnitude must be <= {limit:g} (got {float(arr[idx])!r})")
    return arr


def read_coords(v, path: str, shape: tuple) -> np.ndarray:
    """Positions in metres: an array whose entries lie within +-MAX_COORD."""
    return read_array(v, path, shape, limit=MAX_COORD)


def read_vec3(v, path: str) -> tuple[float, float, float]:
    return tuple(float(x) for x in read_array(v, path, (3,)))


def read_point3(v, path: str) -> tuple[float, float, float]:
    return tuple(float(x) for x in read_coords(v, path, (3,)))


def read_rgb(v, path: str) -> tuple[float, float, float]:
    c = read_array(v, path, (3,))
    if (c < 0).any():
        i = int(np.argmax(c < 0))
        fail(at_key(path, i), f"colour components must be >= 0 (got {float(c[i])!r})")
    return tuple(float(x) for x in c)


def read_corner_normals(v, path: str, count: int) -> np.ndarray:
    """A mesh's corner normals: (count, 3, 3), one finite unit vector per triangle corner,
    each of length 1 within UNIT_NORMAL_TOL."""
    arr = read_array(v, path, (count, 3, 3))
    length = np.linalg.norm(arr, axis=2)
    bad = np.abs(length - 1.0) > UNIT_NORMAL_TOL
    if bad.any():
        i, j = (int(x) for x in np.argwhere(bad)[0])
        fail(f"{path}[{i}][{j}]", f"a normal must have unit length (got length "
                                  f"{float(length[i, j]):.6g})")
    return arr / length[:, :, None]


def check_positive(arr: np.ndarray, path: str, what: str) -> None:
    bad = ~(arr > 0)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        fail(at_index(path, idx), f"{what} must be > 0 (got {float(arr[idx])!r})")


def read_kind(d, path: str, kinds, default: str | None) -> str:
    if not isinstance(d, dict):
        fail(path, f"expected an object (got {type_name(d)})")
    if "kind" not in d and default is None:
        fail(path, "missing required key 'kind'")
    return read_string(d.get("kind", default), at_key(path, "kind"), tuple(kinds), "kind")


def read_list(v, path: str) -> list:
    if not isinstance(v, list):
        fail(path, f"expected a list (got {type_name(v)})")
    return v


def check_unique(items, path: str, what: str) -> None:
    seen = set()
    for i, it in enumerate(items):
        if it.name in seen:
            fail(at_key(at_key(path, i), "name"), f"duplicate {what} name {it.name!r}")
        seen.add(it.name)


def degenerate_reason(patches) -> str | None:
    """Why the object made of ``patches`` is degenerate (its points coincide, or lie on one
    line), in words for its owner ("all its control points coincide"); None when it is not."""
    surf = [p.surface.points.reshape(-1, 3) for p in patches if p.surface is not None]
    mesh = [p.vertices for p in patches if p.surface is None]
    what = " and ".join(w for w, part in (("control points", surf), ("vertices", mesh)) if part)
    pts = np.concatenate(surf + mesh)
    rel = pts - pts[0]
    size = float(np.linalg.norm(np.ptp(pts, axis=0)))
    if size <= COINCIDENT * max(1.0, float(np.abs(pts).max())):
        return f"all its {what} coincide"
    far = rel[np.argmax(np.einsum("ij,ij->i", rel, rel))]
    axis = far / np.linalg.norm(far)
    off = rel - np.outer(rel @ axis, axis)
    if np.sqrt(np.einsum("ij,ij->i", off, off).max()) <= COLLINEAR * size:
        return f"all its {what} lie on one line, so it has no area"
    return None


def check_object_offset(patches, path: str = "object") -> None:
    """The points of the object at ``path`` lie within MAX_OBJECT_OFFSET box diagonals of the
    origin."""
    pts = [p.surface.points.reshape(-1, 3) if p.surface is not None else p.vertices
           for p in patches]
    allp = np.concatenate(pts)
    diag = float(np.linalg.norm(allp.max(axis=0) - allp.min(axis=0)))
    far = np.abs(allp).max()
    if far > MAX_OBJECT_OFFSET * diag:
        i = next(i for i, q in enumerate(pts) if np.abs(q).max() == far)
        key = "vertices" if patches[i].surface is None else "points"
        fail(f"{path}.patches[{i}].{key}", f"the object lies {far:.3g} m from the origin, more "
              f"than {MAX_OBJECT_OFFSET:g} times its size ({diag:.3g} m): coordinates that far "
              "out cannot be traced to the tracer's tolerance; move the scene to the origin")
