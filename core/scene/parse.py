"""JSON scene dict -> Scene (``scene_from_dict``): every field validated, errors naming its
JSON path (``validate``); image files loaded through ``images``."""

from __future__ import annotations

import os

import numpy as np

from ..geometry.knots import MAX_DEGREE, GeometryError, check_surface
from ..geometry.nurbs import NurbsSurface
from ..imageio import MAX_IMAGE_SIDE
from .format import (AREA_SHAPES, CAMERA_FIELDS, CAMERA_KINDS, FORMAT, LIGHT_KINDS,
                     MATERIAL_KINDS, GLOSSY_FIELDS, OBJECT_MATERIAL_KINDS, SENSOR_FITS,
                     TEXTURE_KINDS, TOP_KEYS, VERSION, WORLD_KINDS)
from .graph import GraphError, graph_from_dict
from .images import SceneImages
from .model import (Camera, Light, Material, Mesh, ObjectMaterial, Patch, RenderSettings, Scene,
                    SpecularObject, Texture, World)
from .validate import (MAX_COORD, SceneError, read_array, at_key, read_boolean, check_object_offset,
                       read_coords, fail, read_integer, read_kind, read_list, read_number, read_fields, read_point3,
                       check_positive, read_corner_normals, read_rgb, read_string, type_name,
                       check_unique, degenerate_reason, read_vec3)

# Most surface events per ray (render.max_events): each is one intersection pass over the rays
# still bouncing, so a ray trapped in the object costs max_events passes.
MAX_EVENTS = 1000
RIGID_TOL = 1e-6       # max |R^T R - I| for a camera rotation (dimensionless)
MAX_IOR = 100.0
MAX_CLASS_ID = 2 ** 31 - 1     # class ids are Blender integer properties (32-bit)
UNIT_TOL = 1e-9        # sun directions further than this from unit length are normalized on load
PERP_TOL = 1e-5        # max |cos| between an area light's axis and direction (float32 matrices
                       # give ~1e-7); the axis is then made exactly perpendicular


def _texture(v, path: str, images: SceneImages) -> Texture:
    if isinstance(v, (list, tuple)):
        return Texture(kind="constant", color=read_rgb(v, path))
    kind = read_kind(v, path, TEXTURE_KINDS, "constant")
    fields = TEXTURE_KINDS[kind]
    read_fields(v, path, ("path",) if kind == "image" else (), ("kind",) + fields,
         f" for texture kind {kind!r}")
    t = Texture(kind=kind)
    t.coords = read_string(v.get("coords", "uv" if kind == "image" else "world"), at_key(path, "coords"),
                       ("world", "uv"), "coords")
    if "color" in fields:
        t.color = read_rgb(v.get("color", t.color), at_key(path, "color"))
    if "color2" in fields:
        t.color2 = read_rgb(v.get("color2", t.color2), at_key(path, "color2"))
    if "scale" in fields:
        t.scale = read_number(v.get("scale", t.scale), at_key(path, "scale"), gt=0)
    if "axis" in fields:
        t.axis = read_integer(v.get("axis", 1 if t.coords == "uv" else 2), at_key(path, "axis"), 0,
                          1 if t.coords == "uv" else 2)
    if kind == "gradient":
        t.start = read_number(v.get("start", t.start), at_key(path, "start"))
        t.end = read_number(v.get("end", t.end), at_key(path, "end"))
        if t.start == t.end:
            fail(at_key(path, "end"), f"must differ from start (both {t.start!r})")
    if kind == "image":
        t.path = read_string(v["path"], at_key(path, "path"))
        t.image = images(t.path, at_key(path, "path"))
    return t


# Pixels standing in for graph images when a scene is only validated (save_scene): the graph
# checks that every image node has pixels, not what they are.
UNLOADED_IMAGE = np.zeros((1, 1, 3))


def _graph(v, path: str, images: SceneImages, owner: str):
    """A shader node graph (riray.scene.graph); errors name ``owner`` and the node."""
    def load(rel, where, encoded):
        img = images(rel, at_key(path, where), encoded)
        return UNLOADED_IMAGE if img is None else img

    try:
        return graph_from_dict(v, load)
    except GraphError as e:
        fail(at_key(path, e.where) if e.where else path, f"{owner}: {e.msg}")


def _material(v, path: str, images: SceneImages) -> Material:
    if isinstance(v, dict) and v.get("kind") == "nodes":
        read_fields(v, path, ("name", "kind", "graph"), GLOSSY_FIELDS,
                    " for material kind 'nodes'")
        name = read_string(v["name"], at_key(path, "name"))
        m = Material(name=name, kind="nodes",
                     graph=_graph(v["graph"], at_key(path, "graph"), images, f"material {name!r}"))
        return _glossy(m, v, path)
    read_fields(v, path, ("name",), ("kind", "color", "strength") + GLOSSY_FIELDS)
    m = Material(name=read_string(v["name"], at_key(path, "name")))
    m.kind = read_string(v.get("kind", m.kind), at_key(path, "kind"), MATERIAL_KINDS, "kind")
    if "color" in v:
        m.color = _texture(v["color"], at_key(path, "color"), images)
    m.strength = read_number(v.get("strength", m.strength), at_key(path, "strength"), ge=0)
    for key in GLOSSY_FIELDS:
        if key in v and m.kind == "emission":
            fail(at_key(path, key), f"an 'emission' material has no {key}")
    return _glossy(m, v, path)


def _glossy(m: Material, v: dict, path: str) -> Material:
    """The glossy layer's fields (numbers in [0, 1])."""
    for key in GLOSSY_FIELDS:
        setattr(m, key, read_number(v.get(key, getattr(m, key)), at_key(path, key), ge=0, le=1))
    return m


def _object_material(v, path: str) -> ObjectMaterial:
    m = ObjectMaterial()
    read_fields(v, path, (), ("kind", "ior", "tint", "base_color", "diffuse", "specular", "shininess"))
    m.kind = read_string(v.get("kind", m.kind), at_key(path, "kind"), OBJECT_MATERIAL_KINDS, "kind")
    m.ior = read_number(v.get("ior", m.ior), at_key(path, "ior"), ge=1 / MAX_IOR, le=MAX_IOR)
    m.tint = read_rgb(v.get("tint", m.tint), at_key(path, "tint"))
    m.base_color = read_rgb(v.get("base_color", m.base_color), at_key(path, "base_color"))
    m.diffuse = read_number(v.get("diffuse", m.diffuse), at_key(path, "diffuse"), ge=0, le=1)
    m.specular = read_number(v.get("specular", m.specular), at_key(path, "specular"), ge=0)
    m.shininess = read_number(v.get("shininess", m.shininess), at_key(path, "shininess"), gt=0)
    return m


FACE_KEYS = ("triangles", "quads", "polygons")


def _faces(d: dict, path: str, nverts: int) -> np.ndarray:
    """Triangles (m, 3) int64 from any of "triangles", "quads" (split 0-1-2, 0-2-3) and
    "polygons" (convex, fan-triangulated from their first vertex), in that order."""
    parts = []
    for key in FACE_KEYS:
        if key not in d:
            continue
        p = at_key(path, key)
        if key == "polygons":
            if not isinstance(d[key], list):
                fail(p, f"expected a list (got {type_name(d[key])})")
            polys = [read_array(f, at_key(p, i), (None,), integer=True) for i, f in enumerate(d[key])]
            for i, f in enumerate(polys):
                if len(f) < 3:
                    fail(at_key(p, i), f"a polygon needs at least 3 vertices (got {len(f)})")
            flat = np.concatenate(polys) if polys else np.zeros(0, np.int64)
            arr = flat[:, None]
        else:
            arr = read_array(d[key], p, (None, 3 if key == "triangles" else 4), integer=True)
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
            fail(where, f"vertex index {val} out of range (the mesh has {nverts} vertices)")
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
        fail(path, f"missing faces: give one or more of {', '.join(map(repr, FACE_KEYS))}")
    tris = np.concatenate(parts or [np.zeros((0, 3), np.int64)]).astype(np.int64).reshape(-1, 3)
    if len(tris) == 0:
        fail(path, "the mesh has no faces")
    return tris


def _patch(v, path: str) -> Patch:
    kind = read_kind(v, path, ("nurbs", "mesh"), None)
    if kind == "mesh":
        return _mesh_patch(v, path)
    read_fields(v, path, ("kind", "name", "class_id", "degree_u", "degree_v", "knots_u", "knots_v",
                   "points"), ("weights",), " for a nurbs patch")
    name = read_string(v["name"], at_key(path, "name"))
    class_id = read_integer(v["class_id"], at_key(path, "class_id"), 0, MAX_CLASS_ID)
    deg = {d: read_integer(v[f"degree_{d}"], at_key(path, f"degree_{d}"), 1, MAX_DEGREE) for d in "uv"}
    pts = read_coords(v["points"], at_key(path, "points"), (None, None, 3))
    counts = {"u": pts.shape[0], "v": pts.shape[1]}
    knots = {}
    for d in "uv":
        p = at_key(path, f"knots_{d}")
        if counts[d] < deg[d] + 1:
            fail(at_key(path, "points"), f"{counts[d]} control points along {d}; need at least "
                                       f"degree_{d} + 1 = {deg[d] + 1}")
        k = read_array(v[f"knots_{d}"], p, (None,))
        want = counts[d] + deg[d] + 1
        if len(k) != want:
            fail(p, f"expected n_{d} + degree_{d} + 1 = {counts[d]} + {deg[d]} + 1 = {want} "
                     f"knots (got {len(k)})")
        dec = np.diff(k) < 0
        if dec.any():
            i = int(np.argmax(dec)) + 1
            fail(at_key(p, i), f"knots must be non-decreasing "
                             f"(got {float(k[i])!r} after {float(k[i - 1])!r})")
        knots[d] = k
    if "weights" in v:
        w = read_array(v["weights"], at_key(path, "weights"), pts.shape[:2])
        check_positive(w, at_key(path, "weights"), "weight")
    else:
        w = np.ones(pts.shape[:2])
    surf = NurbsSurface(deg["u"], deg["v"], knots["u"], knots["v"], pts, w)
    try:
        check_surface(surf, path)
    except GeometryError as e:
        raise SceneError(str(e)) from None
    return Patch(name=name, class_id=class_id, surface=surf)


def _mesh_patch(v, path: str) -> Patch:
    """A mesh patch; its optional "normals" are per triangle corner, in the order the faces
    triangulate (``_faces``)."""
    read_fields(v, path, ("kind", "name", "class_id", "vertices"), FACE_KEYS + ("normals",),
                " for a mesh patch")
    verts = read_coords(v["vertices"], at_key(path, "vertices"), (None, 3))
    tris = _faces(v, path, len(verts))
    normals = (read_corner_normals(v["normals"], at_key(path, "normals"), len(tris))
               if "normals" in v else None)
    return Patch(name=read_string(v["name"], at_key(path, "name")),
                 class_id=read_integer(v["class_id"], at_key(path, "class_id"), 0, MAX_CLASS_ID),
                 vertices=verts, triangles=tris, normals=normals)


def _mesh(v, path: str, materials: dict) -> Mesh:
    read_fields(v, path, ("name", "vertices", "material"), FACE_KEYS + ("uvs", "smooth"))
    verts = read_coords(v["vertices"], at_key(path, "vertices"), (None, 3))
    mesh = Mesh(name=read_string(v["name"], at_key(path, "name")), vertices=verts,
                triangles=_faces(v, path, len(verts)),
                material=read_string(v["material"], at_key(path, "material")))
    if mesh.material not in materials:
        fail(at_key(path, "material"), f"material {mesh.material!r} is not defined "
                                     f"(materials: {', '.join(materials) or 'none'})")
    if "uvs" in v:
        mesh.uvs = read_array(v["uvs"], at_key(path, "uvs"), (len(verts), 2))
    mesh.smooth = read_boolean(v.get("smooth", False), at_key(path, "smooth"))
    tex = materials[mesh.material].color
    if tex.kind != "constant" and tex.coords == "uv" and mesh.uvs is None:
        fail(path, f"material {mesh.material!r} has a uv-mapped texture but the mesh has no 'uvs'")
    return mesh


def _light(v, path: str) -> Light:
    kind = read_kind(v, path, LIGHT_KINDS, "point")
    fields = LIGHT_KINDS[kind]
    read_fields(v, path, ("name",), ("kind",) + fields, f" for light kind {kind!r}")
    li = Light(name=read_string(v["name"], at_key(path, "name")), kind=kind)
    li.color = read_rgb(v.get("color", li.color), at_key(path, "color"))
    li.shadows = read_boolean(v.get("shadows", li.shadows), at_key(path, "shadows"))
    if kind in ("point", "area"):
        li.position = read_point3(v.get("position", li.position), at_key(path, "position"))
        li.power = read_number(v.get("power", li.power), at_key(path, "power"), ge=0)
    if kind in ("sun", "area"):
        li.direction = _unit(v.get("direction", li.direction), at_key(path, "direction"))
    if kind == "sun":
        li.strength = read_number(v.get("strength", li.strength), at_key(path, "strength"), ge=0)
    if kind == "area":
        _area_light(li, v, path)
    return li


def _unit(v, path: str) -> tuple[float, float, float]:
    """A non-zero vector, normalized when it is not of unit length."""
    d = np.array(read_vec3(v, path))
    n = float(np.linalg.norm(d))
    if not n > 0:
        fail(path, "must not be the zero vector")
    return tuple(float(x) for x in (d / n if abs(n - 1) > UNIT_TOL else d))


def _area_light(li: Light, v, path: str) -> None:
    """The axis (made exactly perpendicular to the direction), size and shape of an area light."""
    d = np.array(li.direction)
    a = np.array(_unit(v.get("axis", li.axis), at_key(path, "axis")))
    cos = float(a @ d)
    if abs(cos) > PERP_TOL:
        fail(at_key(path, "axis"), f"must be perpendicular to direction (cosine {cos:.3g})")
    a = a - cos * d
    li.axis = tuple(float(x) for x in a / np.linalg.norm(a))
    size = read_coords(v.get("size", list(li.size)), at_key(path, "size"), (2,))
    check_positive(size, at_key(path, "size"), "a side")
    li.size = (float(size[0]), float(size[1]))
    li.shape = read_string(v.get("shape", li.shape), at_key(path, "shape"), AREA_SHAPES, "shape")


def _world(v, path: str, images: SceneImages) -> World:
    kind = read_kind(v, path, WORLD_KINDS, "color")
    fields = WORLD_KINDS[kind]
    read_fields(v, path, {"image": ("path",), "nodes": ("graph",)}.get(kind, ()), ("kind",) + fields,
         f" for world kind {kind!r}")
    w = World(kind=kind)
    if "color" in fields:
        w.color = read_rgb(v.get("color", w.color), at_key(path, "color"))
    if kind == "gradient":
        w.zenith = read_rgb(v.get("zenith", w.zenith), at_key(path, "zenith"))
    if kind == "image":
        w.path = read_string(v["path"], at_key(path, "path"))
        w.image = images(w.path, at_key(path, "path"))
    if kind == "nodes":
        w.graph = _graph(v["graph"], at_key(path, "graph"), images, "the world")
    w.strength = read_number(v.get("strength", w.strength), at_key(path, "strength"), ge=0)
    w.ambient = read_number(v.get("ambient", w.ambient), at_key(path, "ambient"), ge=0)
    w.sky = read_boolean(v.get("sky", w.sky), at_key(path, "sky"))
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
        read_fields(v, path, ("name", "matrix_world"), CAMERA_FIELDS,
             " (a camera has either matrix_world or location/look_at/up)")
        mp = at_key(path, "matrix_world")
        m = read_array(v["matrix_world"], mp, (4, 4))
        far = np.abs(m[:3, 3]) > MAX_COORD
        if far.any():
            i = int(np.argmax(far))
            fail(f"{mp}[{i}][3]", f"magnitude must be <= {MAX_COORD:g} (got {float(m[i, 3])!r})")
        if m[3].tolist() != [0, 0, 0, 1]:
            fail(at_key(mp, 3), f"bottom row must be [0, 0, 0, 1] (got {m[3].tolist()})")
        r = m[:3, :3]
        err = float(np.abs(r.T @ r - np.eye(3)).max())
        if err > RIGID_TOL:
            fail(mp, f"not rigid: rotation part is not orthonormal (max |R^T R - I| = {err:.3g} "
                      f"> {RIGID_TOL}); remove scale/shear")
        if np.linalg.det(r) < 0:
            fail(mp, "not rigid: rotation part is a reflection (determinant < 0)")
    else:
        read_fields(v, path, ("name", "location", "look_at"), ("up",) + CAMERA_FIELDS,
             " (a camera has either matrix_world or location/look_at/up)")
        loc = read_point3(v["location"], at_key(path, "location"))
        tgt = read_point3(v["look_at"], at_key(path, "look_at"))
        up = read_vec3(v.get("up", (0.0, 0.0, 1.0)), at_key(path, "up"))
        try:
            m = look_at_matrix(loc, tgt, up)
        except ValueError as e:
            fail(path, str(e))
    c = Camera(name=read_string(v["name"], at_key(path, "name")), matrix_world=m)
    c.kind = read_string(v.get("kind", c.kind), at_key(path, "kind"), CAMERA_KINDS, "kind")
    c.sensor_fit = read_string(v.get("sensor_fit", c.sensor_fit), at_key(path, "sensor_fit"),
                           SENSOR_FITS, "sensor_fit")
    for key in ("lens", "sensor_width", "sensor_height", "ortho_scale", "clip_start"):
        setattr(c, key, read_number(v.get(key, getattr(c, key)), at_key(path, key), gt=0))
    for key in ("shift_x", "shift_y"):
        setattr(c, key, read_number(v.get(key, getattr(c, key)), at_key(path, key)))
    c.clip_end = read_number(v.get("clip_end", c.clip_end), at_key(path, "clip_end"), gt=c.clip_start)
    return c


def _specular_object(o, path: str, name_default: str | None) -> SpecularObject:
    """One specular object at ``path`` (its name defaults to ``name_default``; without one it
    is required, and the errors after it name the object too)."""
    named = () if name_default else ("name",)         # a list's objects are named
    o = read_fields(o, path, ("patches",) + named,
                    ("material",) + (("name",) if name_default else ()))
    name = read_string(o.get("name", name_default), at_key(path, "name"))
    try:
        patches = [_patch(p, at_key(at_key(path, "patches"), i))
                   for i, p in enumerate(read_list(o["patches"], at_key(path, "patches")))]
        if not patches:
            fail(at_key(path, "patches"), "the specular object needs at least one patch")
        reason = degenerate_reason(patches)
        if reason:
            fail(at_key(path, "patches"), f"the object is degenerate ({reason}): there is no "
                                          "surface to trace")
        check_object_offset(patches, path)
        material = _object_material(o.get("material", {}), at_key(path, "material"))
    except SceneError as e:
        if name_default:                  # the only object: its path says enough
            raise
        raise SceneError(f"specular object {name!r}: {e}") from None
    return SpecularObject(name=name, patches=patches, material=material)


def _specular_objects(d: dict) -> list[SpecularObject]:
    """The scene's specular objects: the list ``objects`` (each named, names unique), or one
    ``object`` (the older form)."""
    if "object" in d and "objects" in d:
        fail("", "give the specular objects as 'objects' (a list) or one as 'object', not both")
    if "object" not in d and "objects" not in d:
        fail("", "missing required key 'objects' (a list of specular objects; or 'object', "
                 "one)")
    if "object" in d:
        return [_specular_object(d["object"], "object", "object")]
    items = read_list(d["objects"], "objects")
    if not items:
        fail("objects", "the scene needs at least one specular object")
    objects = [_specular_object(o, at_key("objects", i), None) for i, o in enumerate(items)]
    check_unique(objects, "objects", "specular object")
    return objects


def parse_scene(d, base_dir: str | None, load_images: bool) -> Scene:
    if not isinstance(d, dict):
        fail("", f"expected a JSON object (got {type_name(d)})")
    if d.get("format") != FORMAT:
        fail("format", f"expected {FORMAT!r} (got {d.get('format')!r}); not a riray scene file")
    if d.get("version") != VERSION or type(d.get("version")) is not int:
        fail("version", f"unsupported version {d.get('version')!r} (this riray reads version "
                         f"{VERSION})")
    read_fields(d, "", ("format", "version"), TOP_KEYS)
    images = SceneImages(base_dir, load_images)

    render = RenderSettings()
    r = read_fields(d.get("render", {}), "render", (), ("width", "height", "max_events"))
    render.width = read_integer(r.get("width", render.width), "render.width", 1, MAX_IMAGE_SIDE)
    render.height = read_integer(r.get("height", render.height), "render.height", 1, MAX_IMAGE_SIDE)
    render.max_events = read_integer(r.get("max_events", render.max_events), "render.max_events", 1,
                                 MAX_EVENTS)

    mats = [_material(m, at_key("materials", i), images)
            for i, m in enumerate(read_list(d.get("materials", []), "materials"))]
    check_unique(mats, "materials", "material")
    materials = {m.name: m for m in mats}

    objects = _specular_objects(d)

    env = read_fields(d.get("environment", {}), "environment", (), ("meshes",))
    meshes = [_mesh(m, at_key("environment.meshes", i), materials)
              for i, m in enumerate(read_list(env.get("meshes", []), "environment.meshes"))]
    lights = [_light(li, at_key("lights", i))
              for i, li in enumerate(read_list(d.get("lights", []), "lights"))]
    world = _world(d.get("world", {}), "world", images)
    cameras = [_camera(c, at_key("cameras", i))
               for i, c in enumerate(read_list(d.get("cameras", []), "cameras"))]
    check_unique(cameras, "cameras", "camera")
    return Scene(objects=objects, meshes=meshes, materials=materials, lights=lights, world=world,
                 cameras=cameras, render=render, name=read_string(d.get("name", "scene"), "name"))


def scene_from_dict(d: dict, base_dir: str | os.PathLike | None = None) -> Scene:
    """Validate a scene dict (JSON-shaped: dicts, lists, str, int, float, bool) and build the
    Scene; image paths resolve against ``base_dir`` (None: the current directory) and are loaded."""
    return parse_scene(d, None if base_dir is None else os.fspath(base_dir), load_images=True)
