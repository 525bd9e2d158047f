"""The vocabulary of the JSON scene format, version 1 (docs/scene-format.md): its kinds and the
fields each uses; and the canonical dict of a Scene (``scene_to_dict``)."""

from __future__ import annotations

import numpy as np

from .graph import GraphError, graph_to_dict
from .model import (Camera, Light, Material, Mesh, Patch, Scene, SpecularObject, Texture,
                    World)
from .validate import SceneError

FORMAT = "riray-scene"
VERSION = 1
TEXTURE_KINDS = {  # kind -> fields it uses (besides "kind")
    "constant": ("color",),
    "checker": ("color", "color2", "scale", "coords"),
    "stripes": ("color", "color2", "scale", "axis", "coords"),
    "gradient": ("color", "color2", "axis", "start", "end", "coords"),
    "image": ("path", "scale", "coords"),
}
LIGHT_KINDS = {"point": ("color", "position", "power", "shadows"),
               "sun": ("color", "direction", "strength", "shadows"),
               "area": ("color", "position", "direction", "axis", "size", "shape", "power",
                        "shadows")}
AREA_SHAPES = ("rectangle", "ellipse")
WORLD_KINDS = {"color": ("color", "strength", "ambient", "sky"),
               "gradient": ("color", "zenith", "strength", "ambient", "sky"),
               "image": ("path", "strength", "ambient", "sky"),
               "nodes": ("graph", "strength", "ambient", "sky")}
MATERIAL_KINDS = ("diffuse", "emission", "nodes")
GLOSSY_FIELDS = ("metallic", "roughness", "specular")     # not "emission" materials
OBJECT_MATERIAL_KINDS = ("mirror", "glass", "dielectric")
CAMERA_KINDS = ("perspective", "orthographic")
SENSOR_FITS = ("AUTO", "HORIZONTAL", "VERTICAL")
CAMERA_FIELDS = ("kind", "lens", "sensor_width", "sensor_height", "sensor_fit", "shift_x",
                 "shift_y", "ortho_scale", "clip_start", "clip_end")
TOP_KEYS = ("format", "version", "name", "render", "objects", "object", "environment",
            "materials", "lights", "world", "cameras")


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
        return _mesh_patch_dict(p)
    s = p.surface
    return {"kind": "nurbs", "name": p.name, "class_id": int(p.class_id),
            "degree_u": int(s.degree_u), "degree_v": int(s.degree_v),
            "knots_u": np.asarray(s.knots_u, dtype=np.float64).tolist(),
            "knots_v": np.asarray(s.knots_v, dtype=np.float64).tolist(),
            "points": np.asarray(s.points, dtype=np.float64).tolist(),
            "weights": np.asarray(s.weights, dtype=np.float64).tolist()}


def _mesh_patch_dict(p: Patch) -> dict:
    out = {"kind": "mesh", "name": p.name, "class_id": int(p.class_id),
           "vertices": np.asarray(p.vertices, dtype=np.float64).tolist(),
           "triangles": np.asarray(p.triangles, dtype=np.int64).tolist()}
    if p.normals is not None:
        out["normals"] = np.asarray(p.normals, dtype=np.float64).tolist()
    return out


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
        out[key] = bool(val) if key == "shadows" else val if key == "shape" else (
            float(val) if key in ("power", "strength") else list(map(float, val)))
    return out


def _graph_dict(g, owner: str) -> dict:
    try:
        return graph_to_dict(g)
    except GraphError as e:
        raise SceneError(f"{owner}: {e.msg}") from None


def _material_dict(m: Material) -> dict:
    if m.kind == "nodes":
        out = {"name": m.name, "kind": "nodes",
               "graph": _graph_dict(m.graph, f"material {m.name!r}")}
    else:
        out = {"name": m.name, "kind": m.kind, "color": _texture_dict(m.color),
               "strength": float(m.strength)}
    if m.kind != "emission":
        out.update({key: float(getattr(m, key)) for key in GLOSSY_FIELDS})
    return out


def _world_dict(w: World) -> dict:
    if w.kind == "image" and not w.path:
        raise SceneError(f"an image world needs a path to be saved (got {w.path!r})")
    out = {"kind": w.kind}
    for key in WORLD_KINDS.get(w.kind, ()):
        val = getattr(w, key)
        out[key] = val if key == "path" else _graph_dict(val, "world") if key == "graph" else (
            bool(val) if key == "sky" else float(val) if key in ("strength", "ambient")
            else list(map(float, val)))
    return out


def _object_dict(obj: SpecularObject) -> dict:
    om = obj.material
    return {"name": obj.name,
            "material": {"kind": om.kind, "ior": float(om.ior), "tint": list(map(float, om.tint)),
                         "base_color": list(map(float, om.base_color)),
                         "diffuse": float(om.diffuse), "specular": float(om.specular),
                         "shininess": float(om.shininess)},
            "patches": [_patch_dict(p) for p in obj.patches]}


def scene_to_dict(scene: Scene) -> dict:
    """The canonical JSON-ready dict of ``scene`` (every field written; images by path only):
    one specular object as ``object``, several as the list ``objects``."""
    objects = [_object_dict(o) for o in scene.objects]
    return {
        "format": FORMAT, "version": VERSION, "name": scene.name,
        "render": {"width": int(scene.render.width), "height": int(scene.render.height),
                   "max_events": int(scene.render.max_events)},
        **({"object": objects[0]} if len(objects) == 1 else {"objects": objects}),
        "environment": {"meshes": [_mesh_dict(m) for m in scene.meshes]},
        "materials": [_material_dict(m) for m in scene.materials.values()],
        "lights": [_light_dict(li) for li in scene.lights],
        "world": _world_dict(scene.world),
        "cameras": [_camera_dict(c) for c in scene.cameras],
    }
