"""The JSON scene format, version 1 (specified in docs/scene-format.md).

``load_scene`` / ``scene_from_dict`` validate everything and raise :class:`SceneError` naming the
JSON path of the offending field and the problem, e.g.
``object.patches[3].weights[2][1]: weight must be > 0 (got -1.0)``. ``save_scene`` /
``scene_to_dict`` write the canonical form (floats with repr precision, so save -> load is exact);
``save_scene`` validates the dict it writes and replaces the file atomically.
"""

from __future__ import annotations

import difflib
import json
import os
import sys

import numpy as np

from ..geometry.knots import MAX_DEGREE, GeometryError, check_surface
from ..geometry.nurbs import NurbsSurface
from ..render.image import (MAX_IMAGE_SIDE, ImageError, atomic_write, read_float_image, read_png,
                            read_png_samples, read_regular)
from .graph import GraphError, graph_from_dict, graph_to_dict
from .model import (Camera, Light, Material, Mesh, ObjectMaterial, Patch, RenderSettings, Scene,
                    SpecularObject, Texture, World)

FORMAT = "riray-scene"
VERSION = 1
# Largest scene file read, bytes: JSON parses to several times its size in Python objects.
MAX_SCENE_BYTES = 1 << 28
# Most surface events per ray (render.max_events): each is one intersection pass over the rays
# still bouncing, so a ray trapped in the object costs max_events passes.
MAX_EVENTS = 1000
RIGID_TOL = 1e-6       # max |R^T R - I| for a camera rotation (dimensionless)
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
MAX_IOR = 100.0
MAX_CLASS_ID = 2 ** 31 - 1     # class ids are Blender integer properties (32-bit)
UNIT_TOL = 1e-9        # sun directions further than this from unit length are normalized on load

TEXTURE_KINDS = {  # kind -> fields it uses (besides "kind")
    "constant": ("color",),
    "checker": ("color", "color2", "scale", "coords"),
    "stripes": ("color", "color2", "scale", "axis", "coords"),
    "gradient": ("color", "color2", "axis", "start", "end", "coords"),
    "image": ("path", "scale", "coords"),
}
LIGHT_KINDS = {"point": ("color", "position", "power", "shadows"),
               "sun": ("color", "direction", "strength", "shadows")}
WORLD_KINDS = {"color": ("color", "strength", "ambient"),
               "gradient": ("color", "zenith", "strength", "ambient"),
               "image": ("path", "strength", "ambient"),
               "nodes": ("graph", "strength", "ambient")}
MATERIAL_KINDS = ("diffuse", "emission", "nodes")
OBJECT_MATERIAL_KINDS = ("mirror", "glass", "dielectric")
CAMERA_KINDS = ("perspective", "orthographic")
SENSOR_FITS = ("AUTO", "HORIZONTAL", "VERTICAL")
CAMERA_FIELDS = ("kind", "lens", "sensor_width", "sensor_height", "sensor_fit", "shift_x",
                 "shift_y", "ortho_scale", "clip_start", "clip_end")
TOP_KEYS = ("format", "version", "name", "render", "object", "environment", "materials", "lights",
            "world", "cameras")


class SceneError(ValueError):
    """An invalid scene; the message starts with the JSON path of the field."""


# --------------------------------------------------------------------------- primitive checks
def _at(path: str, key: str | int) -> str:
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else key


def _index(path: str, idx) -> str:
    return path + "".join(f"[{int(i)}]" for i in idx)


def _fail(path: str, msg: str):
    raise SceneError(f"{path or 'top level'}: {msg}")


def _tname(v) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean",
            type(None): "null"}.get(type(v), type(v).__name__)


def _obj(v, path: str, required=(), optional=(), what: str = "") -> dict:
    """Check that ``v`` is a JSON object with all ``required`` and no unknown keys."""
    if not isinstance(v, dict):
        _fail(path, f"expected an object (got {_tname(v)})")
    allowed = tuple(required) + tuple(optional)
    for k in v:
        if k not in allowed:
            near = difflib.get_close_matches(k, allowed, n=1)
            hint = f"; did you mean {near[0]!r}?" if near else f"; allowed: {', '.join(allowed)}"
            _fail(path, f"unknown key {k!r}{what}{hint}")
    for k in required:
        if k not in v:
            _fail(path, f"missing required key {k!r}")
    return v


def _number(v, path: str, gt=None, ge=None, le=None) -> float:
    if type(v) not in (int, float):
        _fail(path, f"expected a number (got {_tname(v)} {v!r})")
    try:
        x = float(v)
    except OverflowError:
        _fail(path, f"must be finite (got {v!r})")
    if not np.isfinite(x):
        _fail(path, f"must be finite (got {x!r})")
    if abs(x) > MAX_NUMBER:
        _fail(path, f"magnitude must be <= {MAX_NUMBER:g} (got {x!r})")
    if gt is not None and not x > gt:
        _fail(path, f"must be > {gt} (got {x!r})")
    if ge is not None and not x >= ge:
        _fail(path, f"must be >= {ge} (got {x!r})")
    if le is not None and not x <= le:
        _fail(path, f"must be <= {le} (got {x!r})")
    return x


def _integer(v, path: str, lo=None, hi=None) -> int:
    if type(v) is not int:
        _fail(path, f"expected an integer (got {_tname(v)} {v!r})")
    if lo is not None and v < lo:
        _fail(path, f"must be >= {lo} (got {v})")
    if hi is not None and v > hi:
        _fail(path, f"must be <= {hi} (got {v})")
    return v


def _string(v, path: str, choices=None, what: str = "value") -> str:
    if type(v) is not str or not v:
        _fail(path, f"expected a non-empty string (got {_tname(v)} {v!r})")
    if choices is not None and v not in choices:
        _fail(path, f"unknown {what} {v!r} (expected one of: {', '.join(choices)})")
    return v


def _boolean(v, path: str) -> bool:
    if type(v) is not bool:
        _fail(path, f"expected true or false (got {_tname(v)} {v!r})")
    return v


def _array(v, path: str, shape: tuple, integer: bool = False,
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
                _fail(p, f"expected {what} (got {_tname(x)} {x!r})")
            return
        if not isinstance(x, (list, tuple)):
            _fail(p, f"expected a list (got {_tname(x)})")
        if dims[d] is None:
            dims[d] = len(x)
        elif len(x) != dims[d]:
            _fail(p, f"expected {dims[d]} entries (got {len(x)})")
        if d == len(dims) - 1 and all(type(e) in ok for e in x):
            return
        for i, e in enumerate(x):
            walk(e, _at(p, i), d + 1)

    walk(v, path, 0)
    dims = [0 if n is None else n for n in dims]
    try:
        arr = np.array(v, dtype=np.int64 if integer else np.float64).reshape(dims)
    except OverflowError:
        _fail(path, "integer out of range" if integer else "number out of range")
    if not integer:
        bad = ~np.isfinite(arr)
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            _fail(_index(path, idx), f"must be finite (got {float(arr[idx])!r})")
        big = np.abs(arr) > limit
        if big.any():
            idx = tuple(int(i) for i in np.argwhere(big)[0])
            _fail(_index(path, idx), f"magnitude must be <= {limit:g} (got {float(arr[idx])!r})")
    return arr


def _coords(v, path: str, shape: tuple) -> np.ndarray:
    """Positions in metres: an array whose entries lie within +-MAX_COORD."""
    return _array(v, path, shape, limit=MAX_COORD)


def _vec3(v, path: str) -> tuple[float, float, float]:
    return tuple(float(x) for x in _array(v, path, (3,)))


def _point3(v, path: str) -> tuple[float, float, float]:
    return tuple(float(x) for x in _coords(v, path, (3,)))


def _rgb(v, path: str) -> tuple[float, float, float]:
    c = _array(v, path, (3,))
    if (c < 0).any():
        i = int(np.argmax(c < 0))
        _fail(_at(path, i), f"colour components must be >= 0 (got {float(c[i])!r})")
    return tuple(float(x) for x in c)


def _positive_at(arr: np.ndarray, path: str, what: str) -> None:
    bad = ~(arr > 0)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        _fail(_index(path, idx), f"{what} must be > 0 (got {float(arr[idx])!r})")


def _kind(d, path: str, kinds, default: str | None) -> str:
    if not isinstance(d, dict):
        _fail(path, f"expected an object (got {_tname(d)})")
    if "kind" not in d and default is None:
        _fail(path, "missing required key 'kind'")
    return _string(d.get("kind", default), _at(path, "kind"), tuple(kinds), "kind")


# --------------------------------------------------------------------------- parsing
class _Images:
    """Loads image files relative to ``base_dir`` once each (or not at all when disabled)."""

    def __init__(self, base_dir: str | None, load: bool):
        self.base_dir, self.load, self.cache = base_dir, load, {}

    def __call__(self, rel: str, path: str, encoded: bool = False) -> np.ndarray | None:
        """Linear pixels, or with ``encoded`` a PNG's sRGB-encoded samples as stored (in
        [0, 1]; .npy files are always taken as they are)."""
        if not self.load:
            return None
        full = rel if self.base_dir is None else os.path.join(self.base_dir, rel)
        key = (full, encoded and full.lower().endswith(".png"))
        if key not in self.cache:
            ext = os.path.splitext(full)[1].lower()
            if ext not in (".png", ".npy"):
                _fail(path, f"unsupported image type {ext!r} (use .png or .npy)")
            if not os.path.exists(full):
                _fail(path, f"image file not found: {full}")
            try:
                img = _read_image(full, key[1])
            except ImageError as e:
                _fail(path, str(e))
            except OSError as e:
                _fail(path, f"cannot read {full} ({e.strerror})")
            _check_radiance(img, full, path)
            self.cache[key] = img
        return self.cache[key]


def _read_image(full: str, encoded: bool) -> np.ndarray:
    """(H, W, 3) float64 pixels of a .png or .npy file: linear, or with ``encoded`` (a PNG) its
    sRGB-encoded samples in [0, 1]. Sizes are checked from the headers before decoding."""
    if encoded:
        samples, maxcode = read_png_samples(full)
        img = samples[:, :, :3] if samples.shape[2] >= 3 else \
            np.repeat(samples[:, :, :1], 3, axis=2)
        return img.astype(np.float64) / maxcode
    return read_png(full) if full.lower().endswith(".png") else read_float_image(full)


def _check_radiance(img: np.ndarray, full: str, path: str) -> None:
    """Image pixels are radiance (or reflectance): finite and >= 0."""
    if not np.isfinite(img).all():
        _fail(path, f"image {full} contains NaN/inf")
    if (img < 0).any():
        i, j, c = (int(x) for x in np.argwhere(img < 0)[0])
        _fail(path, f"image {full} has negative values ({float(img[i, j, c])!r} at row {i} "
                    f"column {j} channel {c}): pixels are radiance, which is >= 0")


def _texture(v, path: str, images: _Images) -> Texture:
    if isinstance(v, (list, tuple)):
        return Texture(kind="constant", color=_rgb(v, path))
    kind = _kind(v, path, TEXTURE_KINDS, "constant")
    fields = TEXTURE_KINDS[kind]
    _obj(v, path, ("path",) if kind == "image" else (), ("kind",) + fields,
         f" for texture kind {kind!r}")
    t = Texture(kind=kind)
    t.coords = _string(v.get("coords", "uv" if kind == "image" else "world"), _at(path, "coords"),
                       ("world", "uv"), "coords")
    if "color" in fields:
        t.color = _rgb(v.get("color", t.color), _at(path, "color"))
    if "color2" in fields:
        t.color2 = _rgb(v.get("color2", t.color2), _at(path, "color2"))
    if "scale" in fields:
        t.scale = _number(v.get("scale", t.scale), _at(path, "scale"), gt=0)
    if "axis" in fields:
        t.axis = _integer(v.get("axis", 1 if t.coords == "uv" else 2), _at(path, "axis"), 0,
                          1 if t.coords == "uv" else 2)
    if kind == "gradient":
        t.start = _number(v.get("start", t.start), _at(path, "start"))
        t.end = _number(v.get("end", t.end), _at(path, "end"))
        if t.start == t.end:
            _fail(_at(path, "end"), f"must differ from start (both {t.start!r})")
    if kind == "image":
        t.path = _string(v["path"], _at(path, "path"))
        t.image = images(t.path, _at(path, "path"))
    return t


# Pixels standing in for graph images when a scene is only validated (save_scene): the graph
# checks that every image node has pixels, not what they are.
UNLOADED_IMAGE = np.zeros((1, 1, 3))


def _graph(v, path: str, images: _Images, owner: str):
    """A shader node graph (riray.scene.graph); errors name ``owner`` and the node."""
    def load(rel, where, encoded):
        img = images(rel, _at(path, where), encoded)
        return UNLOADED_IMAGE if img is None else img

    try:
        return graph_from_dict(v, load)
    except GraphError as e:
        _fail(_at(path, e.where) if e.where else path, f"{owner}: {e.msg}")


def _material(v, path: str, images: _Images) -> Material:
    if isinstance(v, dict) and v.get("kind") == "nodes":
        _obj(v, path, ("name", "kind", "graph"), (), " for material kind 'nodes'")
        name = _string(v["name"], _at(path, "name"))
        return Material(name=name, kind="nodes",
                        graph=_graph(v["graph"], _at(path, "graph"), images,
                                     f"material {name!r}"))
    _obj(v, path, ("name",), ("kind", "color", "strength"))
    m = Material(name=_string(v["name"], _at(path, "name")))
    m.kind = _string(v.get("kind", m.kind), _at(path, "kind"), MATERIAL_KINDS, "kind")
    if "color" in v:
        m.color = _texture(v["color"], _at(path, "color"), images)
    m.strength = _number(v.get("strength", m.strength), _at(path, "strength"), ge=0)
    return m


def _object_material(v, path: str) -> ObjectMaterial:
    m = ObjectMaterial()
    _obj(v, path, (), ("kind", "ior", "tint", "base_color", "diffuse", "specular", "shininess"))
    m.kind = _string(v.get("kind", m.kind), _at(path, "kind"), OBJECT_MATERIAL_KINDS, "kind")
    m.ior = _number(v.get("ior", m.ior), _at(path, "ior"), ge=1 / MAX_IOR, le=MAX_IOR)
    m.tint = _rgb(v.get("tint", m.tint), _at(path, "tint"))
    m.base_color = _rgb(v.get("base_color", m.base_color), _at(path, "base_color"))
    m.diffuse = _number(v.get("diffuse", m.diffuse), _at(path, "diffuse"), ge=0, le=1)
    m.specular = _number(v.get("specular", m.specular), _at(path, "specular"), ge=0)
    m.shininess = _number(v.get("shininess", m.shininess), _at(path, "shininess"), gt=0)
    return m


FACE_KEYS = ("triangles", "quads", "polygons")


def _faces(d: dict, path: str, nverts: int) -> np.ndarray:
    """Triangles (m, 3) int64 from any of "triangles", "quads" (split 0-1-2, 0-2-3) and
    "polygons" (convex, fan-triangulated from their first vertex), in that order."""
    parts = []
    for key in FACE_KEYS:
        if key not in d:
            continue
        p = _at(path, key)
        if key == "polygons":
            if not isinstance(d[key], list):
                _fail(p, f"expected a list (got {_tname(d[key])})")
            polys = [_array(f, _at(p, i), (None,), integer=True) for i, f in enumerate(d[key])]
            for i, f in enumerate(polys):
                if len(f) < 3:
                    _fail(_at(p, i), f"a polygon needs at least 3 vertices (got {len(f)})")
            flat = np.concatenate(polys) if polys else np.zeros(0, np.int64)
            arr = flat[:, None]
        else:
            arr = _array(d[key], p, (None, 3 if key == "triangles" else 4), integer=True)
        bad = (arr < 0) | (arr >= nverts)
        if bad.any():
            if key == "polygons":
                k = int(np.argmax(bad[:, 0]))
                sizes = np.cumsum([len(f) for f in polys])
                i = int(np.searchsorted(sizes, k, side="right"))
                j = k - (int(sizes[i - 1]) if i else 0)
                where, val = f"{p}[{i}][{j}]", int(flat[k])
            else:
                i, j = (int(x) for x in np.argwhere(bad)[0])
                where, val = f"{p}[{i}][{j}]", int(arr[i, j])
            _fail(where, f"vertex index {val} out of range (the mesh has {nverts} vertices)")
        if key == "triangles":
            parts.append(arr)
        elif key == "quads":
            parts.append(arr[:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3))
        elif polys:
            sizes = np.array([len(f) for f in polys])
            starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
            ntri = sizes - 2
            first = np.repeat(starts, ntri)
            j = np.arange(ntri.sum()) - np.repeat(np.cumsum(ntri) - ntri, ntri) + 1
            parts.append(np.stack([flat[first], flat[first + j], flat[first + j + 1]], axis=1))
    if not any(key in d for key in FACE_KEYS):
        _fail(path, f"missing faces: give one or more of {', '.join(map(repr, FACE_KEYS))}")
    tris = np.concatenate(parts or [np.zeros((0, 3), np.int64)]).astype(np.int64).reshape(-1, 3)
    if len(tris) == 0:
        _fail(path, "the mesh has no faces")
    return tris


def _patch(v, path: str) -> Patch:
    kind = _kind(v, path, ("nurbs", "mesh"), None)
    if kind == "mesh":
        _obj(v, path, ("kind", "name", "class_id", "vertices"), FACE_KEYS, " for a mesh patch")
        verts = _coords(v["vertices"], _at(path, "vertices"), (None, 3))
        return Patch(name=_string(v["name"], _at(path, "name")),
                     class_id=_integer(v["class_id"], _at(path, "class_id"), 0, MAX_CLASS_ID),
                     vertices=verts, triangles=_faces(v, path, len(verts)))
    _obj(v, path, ("kind", "name", "class_id", "degree_u", "degree_v", "knots_u", "knots_v",
                   "points"), ("weights",), " for a nurbs patch")
    name = _string(v["name"], _at(path, "name"))
    class_id = _integer(v["class_id"], _at(path, "class_id"), 0, MAX_CLASS_ID)
    deg = {d: _integer(v[f"degree_{d}"], _at(path, f"degree_{d}"), 1, MAX_DEGREE) for d in "uv"}
    pts = _coords(v["points"], _at(path, "points"), (None, None, 3))
    counts = {"u": pts.shape[0], "v": pts.shape[1]}
    knots = {}
    for d in "uv":
        p = _at(path, f"knots_{d}")
        if counts[d] < deg[d] + 1:
            _fail(_at(path, "points"), f"{counts[d]} control points along {d}; need at least "
                                       f"degree_{d} + 1 = {deg[d] + 1}")
        k = _array(v[f"knots_{d}"], p, (None,))
        want = counts[d] + deg[d] + 1
        if len(k) != want:
            _fail(p, f"expected n_{d} + degree_{d} + 1 = {counts[d]} + {deg[d]} + 1 = {want} "
                     f"knots (got {len(k)})")
        dec = np.diff(k) < 0
        if dec.any():
            i = int(np.argmax(dec)) + 1
            _fail(_at(p, i), f"knots must be non-decreasing "
                             f"(got {float(k[i])!r} after {float(k[i - 1])!r})")
        knots[d] = k
    if "weights" in v:
        w = _array(v["weights"], _at(path, "weights"), pts.shape[:2])
        _positive_at(w, _at(path, "weights"), "weight")
    else:
        w = np.ones(pts.shape[:2])
    surf = NurbsSurface(deg["u"], deg["v"], knots["u"], knots["v"], pts, w)
    try:
        check_surface(surf, path)
    except GeometryError as e:
        raise SceneError(str(e)) from None
    return Patch(name=name, class_id=class_id, surface=surf)


def _mesh(v, path: str, materials: dict) -> Mesh:
    _obj(v, path, ("name", "vertices", "material"), FACE_KEYS + ("uvs", "smooth"))
    verts = _coords(v["vertices"], _at(path, "vertices"), (None, 3))
    mesh = Mesh(name=_string(v["name"], _at(path, "name")), vertices=verts,
                triangles=_faces(v, path, len(verts)),
                material=_string(v["material"], _at(path, "material")))
    if mesh.material not in materials:
        _fail(_at(path, "material"), f"material {mesh.material!r} is not defined "
                                     f"(materials: {', '.join(materials) or 'none'})")
    if "uvs" in v:
        mesh.uvs = _array(v["uvs"], _at(path, "uvs"), (len(verts), 2))
    mesh.smooth = _boolean(v.get("smooth", False), _at(path, "smooth"))
    tex = materials[mesh.material].color
    if tex.kind != "constant" and tex.coords == "uv" and mesh.uvs is None:
        _fail(path, f"material {mesh.material!r} has a uv-mapped texture but the mesh has no 'uvs'")
    return mesh


def _light(v, path: str) -> Light:
    kind = _kind(v, path, LIGHT_KINDS, "point")
    fields = LIGHT_KINDS[kind]
    _obj(v, path, ("name",), ("kind",) + fields, f" for light kind {kind!r}")
    li = Light(name=_string(v["name"], _at(path, "name")), kind=kind)
    li.color = _rgb(v.get("color", li.color), _at(path, "color"))
    li.shadows = _boolean(v.get("shadows", li.shadows), _at(path, "shadows"))
    if kind == "point":
        li.position = _point3(v.get("position", li.position), _at(path, "position"))
        li.power = _number(v.get("power", li.power), _at(path, "power"), ge=0)
    else:
        d = np.array(_vec3(v.get("direction", li.direction), _at(path, "direction")))
        n = float(np.linalg.norm(d))
        if not n > 0:
            _fail(_at(path, "direction"), "must not be the zero vector")
        li.direction = tuple(float(x) for x in (d / n if abs(n - 1) > UNIT_TOL else d))
        li.strength = _number(v.get("strength", li.strength), _at(path, "strength"), ge=0)
    return li


def _world(v, path: str, images: _Images) -> World:
    kind = _kind(v, path, WORLD_KINDS, "color")
    fields = WORLD_KINDS[kind]
    _obj(v, path, {"image": ("path",), "nodes": ("graph",)}.get(kind, ()), ("kind",) + fields,
         f" for world kind {kind!r}")
    w = World(kind=kind)
    if "color" in fields:
        w.color = _rgb(v.get("color", w.color), _at(path, "color"))
    if kind == "gradient":
        w.zenith = _rgb(v.get("zenith", w.zenith), _at(path, "zenith"))
    if kind == "image":
        w.path = _string(v["path"], _at(path, "path"))
        w.image = images(w.path, _at(path, "path"))
    if kind == "nodes":
        w.graph = _graph(v["graph"], _at(path, "graph"), images, "the world")
    w.strength = _number(v.get("strength", w.strength), _at(path, "strength"), ge=0)
    w.ambient = _number(v.get("ambient", w.ambient), _at(path, "ambient"), ge=0)
    return w


def look_at_matrix(location, look_at, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world 4x4 for a camera at ``location`` looking at ``look_at`` (local -Z) with
    local +Y towards ``up``. Raises ValueError when the view direction is zero or parallel to up."""
    loc = np.asarray(location, dtype=np.float64)
    fwd = np.asarray(look_at, dtype=np.float64) - loc
    if not np.linalg.norm(fwd) > 0:
        raise ValueError("look_at equals location")
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, np.asarray(up, dtype=np.float64))
    if not np.linalg.norm(right) > 1e-9:
        raise ValueError("up is zero or parallel to the viewing direction")
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(right, fwd), -fwd, loc
    return m


def _camera(v, path: str) -> Camera:
    if isinstance(v, dict) and "matrix_world" in v:
        _obj(v, path, ("name", "matrix_world"), CAMERA_FIELDS,
             " (a camera has either matrix_world or location/look_at/up)")
        mp = _at(path, "matrix_world")
        m = _array(v["matrix_world"], mp, (4, 4))
        far = np.abs(m[:3, 3]) > MAX_COORD
        if far.any():
            i = int(np.argmax(far))
            _fail(f"{mp}[{i}][3]", f"magnitude must be <= {MAX_COORD:g} (got {float(m[i, 3])!r})")
        if m[3].tolist() != [0, 0, 0, 1]:
            _fail(_at(mp, 3), f"bottom row must be [0, 0, 0, 1] (got {m[3].tolist()})")
        r = m[:3, :3]
        err = float(np.abs(r.T @ r - np.eye(3)).max())
        if err > RIGID_TOL:
            _fail(mp, f"not rigid: rotation part is not orthonormal (max |R^T R - I| = {err:.3g} "
                      f"> {RIGID_TOL}); remove scale/shear")
        if np.linalg.det(r) < 0:
            _fail(mp, "not rigid: rotation part is a reflection (determinant < 0)")
    else:
        _obj(v, path, ("name", "location", "look_at"), ("up",) + CAMERA_FIELDS,
             " (a camera has either matrix_world or location/look_at/up)")
        loc = _point3(v["location"], _at(path, "location"))
        tgt = _point3(v["look_at"], _at(path, "look_at"))
        up = _vec3(v.get("up", (0.0, 0.0, 1.0)), _at(path, "up"))
        try:
            m = look_at_matrix(loc, tgt, up)
        except ValueError as e:
            _fail(path, str(e))
    c = Camera(name=_string(v["name"], _at(path, "name")), matrix_world=m)
    c.kind = _string(v.get("kind", c.kind), _at(path, "kind"), CAMERA_KINDS, "kind")
    c.sensor_fit = _string(v.get("sensor_fit", c.sensor_fit), _at(path, "sensor_fit"),
                           SENSOR_FITS, "sensor_fit")
    for key in ("lens", "sensor_width", "sensor_height", "ortho_scale", "clip_start"):
        setattr(c, key, _number(v.get(key, getattr(c, key)), _at(path, key), gt=0))
    for key in ("shift_x", "shift_y"):
        setattr(c, key, _number(v.get(key, getattr(c, key)), _at(path, key)))
    c.clip_end = _number(v.get("clip_end", c.clip_end), _at(path, "clip_end"), gt=c.clip_start)
    return c


def _check_object_offset(patches) -> None:
    """The object's points lie within MAX_OBJECT_OFFSET box diagonals of the origin."""
    pts = [p.surface.points.reshape(-1, 3) if p.surface is not None else p.vertices
           for p in patches]
    allp = np.concatenate(pts)
    diag = float(np.linalg.norm(allp.max(axis=0) - allp.min(axis=0)))
    far = np.abs(allp).max()
    if far > MAX_OBJECT_OFFSET * diag:
        i = next(i for i, q in enumerate(pts) if np.abs(q).max() == far)
        key = "vertices" if patches[i].surface is None else "points"
        _fail(f"object.patches[{i}].{key}", f"the object lies {far:.3g} m from the origin, more "
              f"than {MAX_OBJECT_OFFSET:g} times its size ({diag:.3g} m): coordinates that far "
              "out cannot be traced to the tracer's tolerance; move the scene to the origin")


def _list(v, path: str) -> list:
    if not isinstance(v, list):
        _fail(path, f"expected a list (got {_tname(v)})")
    return v


def _unique(items, path: str, what: str) -> None:
    seen = set()
    for i, it in enumerate(items):
        if it.name in seen:
            _fail(_at(_at(path, i), "name"), f"duplicate {what} name {it.name!r}")
        seen.add(it.name)


def _parse(d, base_dir: str | None, load_images: bool) -> Scene:
    if not isinstance(d, dict):
        _fail("", f"expected a JSON object (got {_tname(d)})")
    if d.get("format") != FORMAT:
        _fail("format", f"expected {FORMAT!r} (got {d.get('format')!r}); not a riray scene file")
    if d.get("version") != VERSION or type(d.get("version")) is not int:
        _fail("version", f"unsupported version {d.get('version')!r} (this riray reads version "
                         f"{VERSION})")
    _obj(d, "", ("format", "version", "object"), TOP_KEYS)
    images = _Images(base_dir, load_images)

    render = RenderSettings()
    r = _obj(d.get("render", {}), "render", (), ("width", "height", "max_events"))
    render.width = _integer(r.get("width", render.width), "render.width", 1, MAX_IMAGE_SIDE)
    render.height = _integer(r.get("height", render.height), "render.height", 1, MAX_IMAGE_SIDE)
    render.max_events = _integer(r.get("max_events", render.max_events), "render.max_events", 1,
                                 MAX_EVENTS)

    mats = [_material(m, _at("materials", i), images)
            for i, m in enumerate(_list(d.get("materials", []), "materials"))]
    _unique(mats, "materials", "material")
    materials = {m.name: m for m in mats}

    o = _obj(d["object"], "object", ("patches",), ("name", "material"))
    patches = [_patch(p, _at("object.patches", i))
               for i, p in enumerate(_list(o["patches"], "object.patches"))]
    if not patches:
        _fail("object.patches", "the specular object needs at least one patch")
    _check_object_offset(patches)
    obj = SpecularObject(name=_string(o.get("name", "object"), "object.name"), patches=patches,
                         material=_object_material(o.get("material", {}), "object.material"))

    env = _obj(d.get("environment", {}), "environment", (), ("meshes",))
    meshes = [_mesh(m, _at("environment.meshes", i), materials)
              for i, m in enumerate(_list(env.get("meshes", []), "environment.meshes"))]
    lights = [_light(li, _at("lights", i))
              for i, li in enumerate(_list(d.get("lights", []), "lights"))]
    world = _world(d.get("world", {}), "world", images)
    cameras = [_camera(c, _at("cameras", i))
               for i, c in enumerate(_list(d.get("cameras", []), "cameras"))]
    _unique(cameras, "cameras", "camera")
    return Scene(object=obj, meshes=meshes, materials=materials, lights=lights, world=world,
                 cameras=cameras, render=render, name=_string(d.get("name", "scene"), "name"))


def scene_from_dict(d: dict, base_dir: str | os.PathLike | None = None) -> Scene:
    """Validate a scene dict (JSON-shaped: dicts, lists, str, int, float, bool) and build the
    Scene; image paths resolve against ``base_dir`` (None: the current directory) and are loaded."""
    return _parse(d, None if base_dir is None else os.fspath(base_dir), load_images=True)


def _no_duplicates(pairs):
    d = dict(pairs)
    if len(d) != len(pairs):                # linear time: a set, not a count per key
        seen = set()
        for k, _ in pairs:
            if k in seen:
                raise SceneError(f"duplicate key {k!r} in a JSON object")
            seen.add(k)
    return d


class _LongInt:
    """Stands for an integer literal longer than Python converts to int
    (sys.get_int_max_str_digits) while the scene is parsed again to find where it is."""

    def __init__(self, digits: int):
        self.digits = digits


def _long_int_path(text: str) -> str:
    """The JSON path of the first integer literal in ``text`` too long to convert, and its size."""
    limit = sys.get_int_max_str_digits()
    unknown = f"an integer of more than {limit} digits is out of range"

    def parse_int(t: str):
        digits = len(t.lstrip("-"))
        return _LongInt(digits) if digits > limit else 0

    try:
        d = json.loads(text, parse_int=parse_int)
    except (ValueError, RecursionError):
        return unknown
    stack = [(d, "")]
    while stack:
        v, path = stack.pop()
        if isinstance(v, _LongInt):
            return f"{path or 'top level'}: integer of {v.digits} digits is out of range"
        items = v.items() if isinstance(v, dict) else enumerate(v) if isinstance(v, list) else ()
        stack.extend((x, _at(path, k)) for k, x in reversed(list(items)))
    return unknown


def _read_json(path: str):
    """The parsed JSON of the scene file ``path`` (a regular file of at most MAX_SCENE_BYTES)."""
    try:
        data = read_regular(path, MAX_SCENE_BYTES)
    except ValueError as e:
        raise SceneError(str(e)) from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise SceneError(f"{path}: not UTF-8 text (byte 0x{data[e.start]:02x} at offset "
                         f"{e.start}); scene files are UTF-8 JSON") from None
    try:
        return json.loads(text, object_pairs_hook=_no_duplicates)
    except json.JSONDecodeError as e:
        raise SceneError(f"{path}: invalid JSON at line {e.lineno} column {e.colno}: "
                         f"{e.msg}") from None
    except RecursionError:
        raise SceneError(f"{path}: JSON nested too deeply (no scene needs more than a few "
                         "levels)") from None
    except SceneError as e:                 # a duplicate key
        raise SceneError(f"{path}: {e}") from None
    except ValueError:                      # an integer too long to convert
        raise SceneError(f"{path}: {_long_int_path(text)}") from None


def load_scene(path: str | os.PathLike) -> Scene:
    """Read, validate and build a scene file; images load relative to the file's folder."""
    path = os.fspath(path)
    return scene_from_dict(_read_json(path), os.path.dirname(os.path.abspath(path)))


# --------------------------------------------------------------------------- writing
def _texture_dict(t: Texture) -> dict:
    if t.kind == "image" and not t.path:
        raise SceneError(f"an image texture needs a path to be saved (got {t.path!r})")
    out = {"kind": t.kind}
    for key in TEXTURE_KINDS.get(t.kind, ()):
        val = getattr(t, key)
        out[key] = list(map(float, val)) if key in ("color", "color2") else (
            float(val) if key in ("scale", "start", "end") else val)
    return out


def _camera_dict(c: Camera) -> dict:
    out = {"name": c.name, "matrix_world": np.asarray(c.matrix_world, dtype=np.float64).tolist()}
    for key in CAMERA_FIELDS:
        val = getattr(c, key)
        out[key] = val if isinstance(val, str) else float(val)
    return out


def _patch_dict(p: Patch) -> dict:
    if p.is_mesh:
        return {"kind": "mesh", "name": p.name, "class_id": int(p.class_id),
                "vertices": np.asarray(p.vertices, dtype=np.float64).tolist(),
                "triangles": np.asarray(p.triangles, dtype=np.int64).tolist()}
    s = p.surface
    return {"kind": "nurbs", "name": p.name, "class_id": int(p.class_id),
            "degree_u": int(s.degree_u), "degree_v": int(s.degree_v),
            "knots_u": np.asarray(s.knots_u, dtype=np.float64).tolist(),
            "knots_v": np.asarray(s.knots_v, dtype=np.float64).tolist(),
            "points": np.asarray(s.points, dtype=np.float64).tolist(),
            "weights": np.asarray(s.weights, dtype=np.float64).tolist()}


def _mesh_dict(m: Mesh) -> dict:
    out = {"name": m.name, "material": m.material,
           "vertices": np.asarray(m.vertices, dtype=np.float64).tolist(),
           "triangles": np.asarray(m.triangles, dtype=np.int64).tolist()}
    if m.uvs is not None:
        out["uvs"] = np.asarray(m.uvs, dtype=np.float64).tolist()
    out["smooth"] = bool(m.smooth)
    return out


def _light_dict(li: Light) -> dict:
    out = {"name": li.name, "kind": li.kind}
    for key in LIGHT_KINDS.get(li.kind, ()):
        val = getattr(li, key)
        out[key] = bool(val) if key == "shadows" else (
            float(val) if key in ("power", "strength") else list(map(float, val)))
    return out


def _graph_dict(g, owner: str) -> dict:
    try:
        return graph_to_dict(g)
    except GraphError as e:
        raise SceneError(f"{owner}: {e.msg}") from None


def _material_dict(m: Material) -> dict:
    if m.kind == "nodes":
        return {"name": m.name, "kind": "nodes",
                "graph": _graph_dict(m.graph, f"material {m.name!r}")}
    return {"name": m.name, "kind": m.kind, "color": _texture_dict(m.color),
            "strength": float(m.strength)}


def _world_dict(w: World) -> dict:
    if w.kind == "image" and not w.path:
        raise SceneError(f"an image world needs a path to be saved (got {w.path!r})")
    out = {"kind": w.kind}
    for key in WORLD_KINDS.get(w.kind, ()):
        val = getattr(w, key)
        out[key] = val if key == "path" else _graph_dict(val, "world") if key == "graph" else (
            float(val) if key in ("strength", "ambient") else list(map(float, val)))
    return out


def scene_to_dict(scene: Scene) -> dict:
    """The canonical JSON-ready dict of ``scene`` (every field written; images by path only)."""
    om = scene.object.material
    return {
        "format": FORMAT, "version": VERSION, "name": scene.name,
        "render": {"width": int(scene.render.width), "height": int(scene.render.height),
                   "max_events": int(scene.render.max_events)},
        "object": {
            "name": scene.object.name,
            "material": {"kind": om.kind, "ior": float(om.ior), "tint": list(map(float, om.tint)),
                         "base_color": list(map(float, om.base_color)),
                         "diffuse": float(om.diffuse), "specular": float(om.specular),
                         "shininess": float(om.shininess)},
            "patches": [_patch_dict(p) for p in scene.object.patches]},
        "environment": {"meshes": [_mesh_dict(m) for m in scene.meshes]},
        "materials": [_material_dict(m) for m in scene.materials.values()],
        "lights": [_light_dict(li) for li in scene.lights],
        "world": _world_dict(scene.world),
        "cameras": [_camera_dict(c) for c in scene.cameras],
    }


def in_memory_images(scene: Scene) -> list:
    """[(pixels, set_path)] for every image the scene holds (textures, the world, image nodes
    of graphs), ``set_path(path)`` storing the file it is to be saved as."""
    out = []
    holders = [m.color for m in scene.materials.values() if m.kind != "nodes"] + [scene.world]
    for h in holders:
        if h.image is not None:
            out.append((h.image, lambda p, h=h: setattr(h, "path", p)))
    graphs = [m.graph for m in scene.materials.values() if m.kind == "nodes"]
    graphs += [scene.world.graph] if scene.world.kind == "nodes" else []
    for g in graphs:
        for n in g.nodes:
            if "image" in n.props:
                out.append((n.props["image"], lambda p, n=n: n.props.__setitem__("path", p)))
    return out


def _dumps(v, indent: int = 0) -> str:
    """JSON text: objects one key per line, flat lists of scalars on one line."""
    pad = " " * (indent + 2)
    if isinstance(v, dict) and v:
        items = [f"{pad}{json.dumps(k)}: {_dumps(x, indent + 2)}" for k, x in v.items()]
        return "{\n" + ",\n".join(items) + "\n" + " " * indent + "}"
    if isinstance(v, list) and any(isinstance(x, (dict, list)) for x in v):
        items = [pad + _dumps(x, indent + 2) for x in v]
        return "[\n" + ",\n".join(items) + "\n" + " " * indent + "]"
    return json.dumps(v, allow_nan=False)


def save_scene(scene: Scene, path: str | os.PathLike) -> None:
    """Validate and write ``scene`` as JSON to ``path`` (temporary file + os.replace).

    Image paths are written as stored (relative to the scene file's folder, or absolute); the
    image files themselves are not written.
    """
    d = scene_to_dict(scene)
    _parse(d, None, load_images=False)
    text = _dumps(d) + "\n"
    atomic_write(path, lambda f: f.write(text.encode("utf-8")))
