"""Blender data -> core Scene (world space, metres, linear RGB).

    export_scene(depsgraph, target, report)   the whole scene: object(s) + environment + cameras
    specular_objects(depsgraph)               the objects rendered as specular objects
    export_object(obj, depsgraph, report)     the specular object alone (what the tree bakes)
    spline_surfaces(obj_eval)                 exact NURBS of a SURFACE object, object space
    object_fingerprint(obj, depsgraph)        hash of what a bake depends on (staleness)

The specular object:
- SURFACE objects: every NURBS surface spline exactly (``core.geometry.knots.surface_from_blender``
  reproduces Blender's knot rule from the order / cyclic / endpoint / bezier flags), transformed
  to world space (an affine map acts on the Cartesian control points; weights are unchanged).
  Splines that are curves (one row of points) are skipped with a warning.
- MESH objects, CURVE objects with extrude/bevel/fill, metaballs: the evaluated mesh as polygonal
  patches; faces are split into equivalence classes along sharp edges and around flat-shaded
  faces (one core patch per class); smooth classes carry Blender's corner normals (smooth
  shading, custom split normals).
Classes: each spline is its own class unless splines share a group (object.riray.spline_groups)
or a material with material.riray.join_class.

Everything core cannot simulate is reported (``Report``) by name with what was used instead;
objects with nothing exportable raise ``ExportError`` with a message for the user.
"""

from __future__ import annotations

import hashlib

import numpy as np

from ..core.geometry.knots import GeometryError, surface_from_blender
from ..core.geometry.primitives import transform
from ..core.rowops import unique_rows
from ..core.scene.model import (Camera, Light, Mesh, Patch, RenderSettings, Scene,
                                SpecularObject, World)
from ..core.scene.validate import degenerate_reason
from . import materials as matmap
from .nodegraph import SurfaceContext, object_random_id
from .properties import spline_group
from .report import ExportError, Report

# Object types whose evaluated mesh can be the specular object or part of the environment.
MESH_LIKE = {"MESH", "CURVE", "SURFACE", "META", "FONT"}
SPECULAR_TYPES = {"SURFACE", "MESH", "CURVE", "META"}   # object types a specular object can be
# A matrix this close to the identity counts as identity (object texture coordinates).
IDENTITY_TOL = 1e-9
# Fingerprint grid: world coordinates are hashed in units of this fraction of the object's box
# diagonal (float32 noise from editing transforms stays below it; real edits do not).
FINGERPRINT_QUANTUM = 1e-6


# --------------------------------------------------------------------------- small helpers
def matrix_np(m) -> np.ndarray:
    return np.array([list(row) for row in m], dtype=np.float64)


def _rgb(c) -> tuple[float, float, float]:
    return (float(c[0]), float(c[1]), float(c[2]))


def spline_points(spline) -> np.ndarray:
    """(count_u * count_v, 4) Cartesian xyz + weight, u fastest."""
    pts = np.empty(len(spline.points) * 4, dtype=np.float64)
    spline.points.foreach_get("co", pts)
    return pts.reshape(-1, 4)


def spline_is_surface(spline) -> bool:
    return spline.point_count_v >= 2 and spline.point_count_u >= 2 and spline.order_v >= 2


def spline_surface(spline):
    """The exact NurbsSurface of one surface spline, object space (GeometryError if Blender's
    flags give no valid surface)."""
    return surface_from_blender(
        spline_points(spline), spline.point_count_u, spline.point_count_v,
        spline.order_u, spline.order_v, spline.use_cyclic_u, spline.use_cyclic_v,
        spline.use_endpoint_u, spline.use_endpoint_v, spline.use_bezier_u, spline.use_bezier_v)


def zero_weight(spline) -> str | None:
    """'control point k (u i, v j) has weight w' for the first control point of a spline whose
    weight is not > 0 (Blender accepts 0; a rational surface cannot have it), else None."""
    w = spline_points(spline)[:, 3]
    bad = np.flatnonzero(~(w > 0))
    if not len(bad):
        return None
    k = int(bad[0])
    nu = spline.point_count_u
    return f"control point {k} (u {k % nu}, v {k // nu}) has weight {w[k]:g}"


def spline_surfaces(obj, report: Report | None = None) -> list[tuple[int, object]]:
    """[(spline index, NurbsSurface in object space)] for the surface splines of ``obj``."""
    out = []
    for i, sp in enumerate(obj.data.splines):
        if not spline_is_surface(sp):
            if report is not None:
                report.warning(f"{obj.name}: spline {i} is a curve ({sp.point_count_u} x "
                               f"{sp.point_count_v} points), not a surface; skipped")
            continue
        bad = zero_weight(sp)
        if bad is not None:
            if report is not None:
                report.warning(f"{obj.name}: spline {i} skipped: {bad}; weights must be > 0")
            continue
        try:
            out.append((i, spline_surface(sp)))
        except GeometryError as exc:
            if report is not None:
                report.warning(f"{obj.name}: spline {i} skipped: {exc}")
    return out


def blender_sample_params(spline, surf) -> tuple[np.ndarray, np.ndarray]:
    """The (u, v) parameter values at which Blender's evaluated mesh samples a surface spline:
    count * resolution values per direction, uniform over the domain, the end included unless
    the direction is cyclic. Vertex k of the spline's block is (u[k // nv], v[k % nv])."""
    u0, u1, v0, v1 = surf.domain
    nu = spline.point_count_u * spline.resolution_u
    nv = spline.point_count_v * spline.resolution_v
    u = np.linspace(u0, u1, nu, endpoint=not spline.use_cyclic_u)
    v = np.linspace(v0, v1, nv, endpoint=not spline.use_cyclic_v)
    return u, v


# --------------------------------------------------------------------------- evaluated meshes
class EvaluatedMesh:
    """World-space triangles of an object's evaluated mesh (context manager: frees the mesh)."""

    def __init__(self, obj, depsgraph, matrix=None):
        self.obj = obj
        self.obj_eval = obj.evaluated_get(depsgraph)
        self.matrix = matrix_np(matrix if matrix is not None else self.obj_eval.matrix_world)
        self.mesh = None

    def __enter__(self):
        try:
            self.mesh = self.obj_eval.to_mesh()
        except RuntimeError:
            self.mesh = None
        return self

    def __exit__(self, *exc):
        if self.mesh is not None:
            self.obj_eval.to_mesh_clear()
        self.mesh = None

    @property
    def has_faces(self) -> bool:
        return self.mesh is not None and len(self.mesh.polygons) > 0

    def arrays(self, with_uvs: bool = True) -> dict:
        """vertices (n,3) world, tris (m,3) into them, tri_poly (m,), poly_material (P,),
        poly_smooth (P,), corner uvs (m,3,2) or None."""
        me = self.mesh
        me.calc_loop_triangles()
        nv, nt, npoly = len(me.vertices), len(me.loop_triangles), len(me.polygons)
        co = np.empty(nv * 3)
        me.vertices.foreach_get("co", co)
        m = self.matrix
        verts = co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3]
        tris = np.empty(nt * 3, dtype=np.int64)
        me.loop_triangles.foreach_get("vertices", tris)
        loops = np.empty(nt * 3, dtype=np.int64)
        me.loop_triangles.foreach_get("loops", loops)
        tri_poly = np.empty(nt, dtype=np.int64)
        me.loop_triangles.foreach_get("polygon_index", tri_poly)
        pmat = np.empty(npoly, dtype=np.int64)
        me.polygons.foreach_get("material_index", pmat)
        psmooth = np.empty(npoly, dtype=bool)
        me.polygons.foreach_get("use_smooth", psmooth)
        uvs = None
        layer = me.uv_layers.active if with_uvs else None
        if layer is not None and len(me.loops):
            luv = np.empty(len(me.loops) * 2)
            layer.data.foreach_get("uv", luv)
            uvs = luv.reshape(-1, 2)[loops].reshape(nt, 3, 2)
        if np.linalg.det(m[:3, :3]) < 0:          # mirrored transform: keep winding outward
            tris = tris.reshape(-1, 3)[:, ::-1].ravel()
            if uvs is not None:
                uvs = uvs[:, ::-1]
        return {"vertices": verts, "tris": tris.reshape(-1, 3), "tri_poly": tri_poly,
                "poly_material": pmat, "poly_smooth": psmooth, "uvs": uvs}

    def corner_normals(self) -> np.ndarray | None:
        """(m, 3, 3) unit world-space normals at the corners of the loop triangles, in the
        order and winding of ``arrays``' tris: Blender's shading normals (interpolated vertex
        normals, sharp edges and flat faces split, custom split normals); None where every
        face is flat (the triangles' own normals)."""
        me = self.mesh
        if me.normals_domain == "FACE":
            return None
        me.calc_loop_triangles()
        nt = len(me.loop_triangles)
        loops = np.empty(nt * 3, dtype=np.int64)
        me.loop_triangles.foreach_get("loops", loops)
        local = np.empty(len(me.loops) * 3)
        me.corner_normals.foreach_get("vector", local)
        # normals map by the inverse transpose of the linear part (rows: n @ inv(M))
        n = local.reshape(-1, 3)[loops] @ np.linalg.inv(self.matrix[:3, :3])
        n /= np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None]
        n = n.reshape(nt, 3, 3)
        return n[:, ::-1] if np.linalg.det(self.matrix[:3, :3]) < 0 else n

    def smooth_classes(self) -> np.ndarray:
        """(P,) class label per polygon: polygons joined across edges that are not sharp and
        whose two faces are both smooth-shaded (labels 0..k-1 in order of first polygon)."""
        me = self.mesh
        npoly = len(me.polygons)
        totals = np.empty(npoly, dtype=np.int64)
        me.polygons.foreach_get("loop_total", totals)
        starts = np.empty(npoly, dtype=np.int64)
        me.polygons.foreach_get("loop_start", starts)
        loop_edge = np.empty(len(me.loops), dtype=np.int64)
        me.loops.foreach_get("edge_index", loop_edge)
        poly_of_loop = np.zeros(len(me.loops), dtype=np.int64)
        poly_of_loop[np.repeat(starts, totals) + _ramp(totals)] = np.repeat(np.arange(npoly),
                                                                             totals)
        sharp = np.zeros(len(me.edges), dtype=bool)
        if len(me.edges):
            me.edges.foreach_get("use_edge_sharp", sharp)
        smooth = np.empty(npoly, dtype=bool)
        me.polygons.foreach_get("use_smooth", smooth)
        # pairs of polygons sharing an edge, consecutive after sorting loops by edge
        srt = np.argsort(loop_edge, kind="stable")
        e_sorted = loop_edge[srt]
        p_sorted = poly_of_loop[srt]
        same = e_sorted[1:] == e_sorted[:-1]
        a, b, e = p_sorted[:-1][same], p_sorted[1:][same], e_sorted[1:][same]
        join = ~sharp[e] & smooth[a] & smooth[b]
        return _components(npoly, a[join], b[join])


def _ramp(totals: np.ndarray) -> np.ndarray:
    """0..t-1 for each t in totals, concatenated."""
    if totals.size == 0:
        return np.zeros(0, dtype=np.int64)
    offsets = np.repeat(np.cumsum(totals) - totals, totals)
    return np.arange(int(totals.sum())) - offsets


def _components(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Connected-component labels of n nodes with edges (a, b), numbered by first node."""
    parent = np.arange(n)
    a, b = a.copy(), b.copy()
    while a.size:
        ra, rb = parent[a], parent[b]
        lo, hi = np.minimum(ra, rb), np.maximum(ra, rb)
        np.minimum.at(parent, hi, lo)
        while True:                                  # pointer jumping to the roots
            nxt = parent[parent]
            if np.array_equal(nxt, parent):
                break
            parent = nxt
        keep = parent[a] != parent[b]
        a, b = a[keep], b[keep]
    _, first, labels = np.unique(parent, return_index=True, return_inverse=True)
    rank = np.argsort(np.argsort(first))            # number classes by first polygon
    return rank[labels]


# --------------------------------------------------------------------------- the specular object
def _material_slots(obj) -> list:
    return [slot.material for slot in obj.material_slots]


def _class_ids(keys: list) -> list[int]:
    """Class id per patch from grouping keys: ("group", g) keeps g, anything else gets the next
    free id in order of first appearance."""
    used = {k[1] for k in keys if k[0] == "group"}
    nxt = 0
    ids, seen = [], {}
    for k in keys:
        if k[0] == "group":
            ids.append(int(k[1]))
            continue
        if k not in seen:
            while nxt in used:
                nxt += 1
            seen[k] = nxt
            used.add(nxt)
        ids.append(seen[k])
    return ids


def _surface_patches(obj, obj_eval, report: Report) -> tuple[list[Patch], list]:
    m = matrix_np(obj_eval.matrix_world)
    surfaces = spline_surfaces(obj_eval, report)
    slots = _material_slots(obj)
    keys, used_mats, patches = [], [], []
    for i, surf in surfaces:
        sp = obj_eval.data.splines[i]
        mat = slots[sp.material_index] if sp.material_index < len(slots) else None
        used_mats.append(mat)
        g = spline_group(obj, i)
        if g >= 0:
            keys.append(("group", g))
        elif mat is not None and mat.riray.join_class:
            keys.append(("material", mat.name))
        else:
            keys.append(("spline", i))
        patches.append(Patch(name=f"{obj.name}.spline{i:03d}", class_id=-1,
                             surface=transform(surf, m)))
    for p, cid in zip(patches, _class_ids(keys)):
        p.class_id = cid
    live = [md.name for md in obj.modifiers if md.show_render]
    if live:
        report.warning(f"{obj.name}: modifiers {', '.join(live)} are ignored; the exact "
                       "NURBS splines are used")
    return patches, used_mats


def _mesh_patches(obj, depsgraph, report: Report) -> tuple[list[Patch], list]:
    with EvaluatedMesh(obj, depsgraph) as em:
        if not em.has_faces:
            what = {"MESH": "the mesh has no faces",
                    "CURVE": "the curve has no surface (give it an Extrude, Bevel or Fill)",
                    "META": "the metaball has no surface"}.get(obj.type, "no faces")
            raise ExportError(f"{obj.name}: nothing to export: {what}")
        arr = em.arrays(with_uvs=False)
        labels = em.smooth_classes()
        normals = em.corner_normals()
    slots = _material_slots(obj)
    pmat = arr["poly_material"]
    # material join: all faces of a joining material form one class
    keys = []
    for lab in range(int(labels.max()) + 1):
        first = int(np.argmax(labels == lab))
        mi = int(pmat[first])
        mat = slots[mi] if mi < len(slots) else None
        keys.append(("material", mat.name) if mat is not None and mat.riray.join_class
                    else ("region", lab))
    cls_of_label = np.array(_class_ids(keys))
    tri_cls = cls_of_label[labels[arr["tri_poly"]]]
    patches, used_mats = [], []
    for cid in range(int(tri_cls.max()) + 1):
        sel = tri_cls == cid
        if not np.any(sel):
            continue
        tris = arr["tris"][sel]
        vid, inv = np.unique(tris.ravel(), return_inverse=True)
        patches.append(Patch(name=f"{obj.name}.class{cid:03d}", class_id=cid,
                             vertices=arr["vertices"][vid].copy(),
                             triangles=inv.reshape(-1, 3).astype(np.int64),
                             normals=_class_normals(normals, sel, arr)))
        mi = int(pmat[arr["tri_poly"][sel][0]])
        used_mats.append(slots[mi] if mi < len(slots) else None)
    return patches, used_mats


def _class_normals(normals, sel, arr) -> np.ndarray | None:
    """The corner normals of the triangles ``sel`` of one class, None for a class of flat
    faces (or a mesh without smooth shading)."""
    if normals is None or not np.any(arr["poly_smooth"][arr["tri_poly"][sel]]):
        return None
    return normals[sel].copy()


def export_object(obj, depsgraph, report: Report | None = None) -> SpecularObject:
    """The specular object in world space. Raises ExportError when nothing can be exported."""
    report = report if report is not None else Report()
    if obj is None:
        raise ExportError("no object: select a NURBS surface, mesh or curve object")
    if obj.type == "FONT":
        raise ExportError(f"{obj.name}: text objects cannot be the specular object; convert "
                          "it to a mesh or curve first (Object > Convert)")
    if obj.type not in SPECULAR_TYPES:
        kind = obj.type.lower().replace("_", " ")
        article = "an" if kind[0] in "aeiou" else "a"
        raise ExportError(f"{obj.name}: {article} {kind} object has no surface to export; "
                          "select a NURBS surface, mesh or curve object")
    obj_eval = obj.evaluated_get(depsgraph)
    if obj.type == "SURFACE":
        patches, used = _surface_patches(obj, obj_eval, report)
        if not patches:
            weights = [(i, zero_weight(sp)) for i, sp in enumerate(obj_eval.data.splines)
                       if spline_is_surface(sp)]
            weights = [(i, w) for i, w in weights if w is not None]
            if weights:
                i, bad = weights[0]
                raise ExportError(f"{obj.name}: nothing to export: in spline {i}, {bad}; NURBS "
                                  "weights must be > 0")
            raise ExportError(f"{obj.name}: nothing to export: the surface has no NURBS surface "
                              "splines (only curves or invalid splines)")
    else:
        patches, used = _mesh_patches(obj, depsgraph, report)
    _check_shape(obj.name, patches)
    distinct = []
    for m in used:
        if m not in distinct:
            distinct.append(m)
    mat = max(distinct, key=lambda m: sum(u is m for u in used))
    if len(distinct) > 1:
        others = ", ".join(m.name if m else "(none)" for m in distinct if m is not mat)
        report.warning(f"{obj.name}: the object uses several materials; core simulates one, "
                       f"{mat.name if mat else '(none)'!r}, also for {others}")
    return SpecularObject(name=obj.name, patches=patches,
                          material=matmap.object_material(mat, report, obj.name))


def _check_shape(name: str, patches) -> None:
    """ExportError for a degenerate object: its control points or vertices all in one place or
    on one line (core's scene validation, in the object's name)."""
    reason = degenerate_reason(patches)
    if reason:
        raise ExportError(f"{name}: the object is degenerate ({reason}): there is no surface to "
                          "render or bake")


# --------------------------------------------------------------------------- environment
def _hidden(obj) -> bool:
    """Hidden for rendering (the object or, for instances, its original)."""
    orig = getattr(obj, "original", obj) or obj
    return bool(orig.hide_render)


def _surface_context(obj, matrix: np.ndarray, random_id: int) -> SurfaceContext:
    """The object data node graphs read (texture space, Object Info), Cycles' conventions:
    Random = random_id / (2^32 - 1)."""
    data = getattr(obj, "data", None)
    loc = tuple(getattr(data, "texspace_location", (0.0, 0.0, 0.0)))
    size = tuple(getattr(data, "texspace_size", (1.0, 1.0, 1.0)))
    return SurfaceContext(matrix=matrix, texspace_location=loc, texspace_size=size,
                          color=tuple(obj.color), pass_index=int(obj.pass_index),
                          random=(random_id & 0xFFFFFFFF) / float(0xFFFFFFFF))


def _env_meshes(obj, depsgraph, materials: dict, cache: "matmap.EnvironmentMaterials",
                matrix=None, name: str | None = None, random_id: int = 0) -> list[Mesh]:
    with EvaluatedMesh(obj, depsgraph, matrix) as em:
        if not em.has_faces:
            return []
        arr = em.arrays(with_uvs=True)
        world_matrix = em.matrix
    slots = _material_slots(obj)
    out = []
    pmat = arr["poly_material"][arr["tri_poly"]]
    psmooth = arr["poly_smooth"][arr["tri_poly"]]
    for mi in np.unique(pmat):
        for smooth in (False, True):
            sel = (pmat == mi) & (psmooth == smooth)
            if not np.any(sel):
                continue
            mat = slots[mi] if mi < len(slots) else None
            base = name or obj.name
            surface = _surface_context(obj, world_matrix, random_id)
            if mat is not None:
                surface.material_index = int(mat.pass_index)
            core_mat = cache.get(mat, obj, base, arr["uvs"] is not None, surface)
            materials[core_mat.name] = core_mat
            tris = arr["tris"][sel]
            if arr["uvs"] is not None:
                # vertices carry one uv each: split where a vertex has several uvs
                uv = arr["uvs"][sel].reshape(-1, 2)
                key_arr = np.concatenate([tris.reshape(-1, 1).astype(np.float64), uv], axis=1)
                uniq, inv = unique_rows(key_arr)
                verts = arr["vertices"][uniq[:, 0].astype(np.int64)]
                uvs = uniq[:, 1:].copy()
                tri = inv.reshape(-1, 3).astype(np.int64)
            else:
                vid, inv = np.unique(tris.ravel(), return_inverse=True)
                verts, uvs, tri = arr["vertices"][vid], None, inv.reshape(-1, 3).astype(np.int64)
            name_k = base if len(out) == 0 else f"{base}.{len(out)}"
            out.append(Mesh(name=name_k, vertices=verts, triangles=tri, material=core_mat.name,
                            uvs=uvs, smooth=bool(smooth)))
    return out


def export_light(obj, report: Report, matrix=None, name: str | None = None) -> Light | None:
    li = obj.data
    m = matrix_np(matrix if matrix is not None else obj.matrix_world)
    name = name or obj.name
    color = _rgb(np.multiply(li.color, li.temperature_color) if getattr(li, "use_temperature",
                                                                          False) else li.color)
    energy = float(li.energy) * 2.0 ** float(getattr(li, "exposure", 0.0))
    shadows = bool(getattr(li, "use_shadow", True))
    if li.type == "SUN":
        d = -m[:3, 2]
        d = d / np.linalg.norm(d)
        return Light(name=name, kind="sun", color=color, strength=energy,
                     direction=tuple(float(x) for x in d), shadows=shadows)
    if li.type == "AREA":
        return _area_light(li, m, name, color, energy, shadows, report)
    if li.type != "POINT":
        report.warning(f"light {name}: {li.type.lower()} lights are rendered as point lights "
                       "of the same power")
    elif getattr(li, "shadow_soft_size", 0.0) > 0.0:
        report.warning(f"light {name}: radius {li.shadow_soft_size:g} m ignored (hard "
                       "shadows from the centre)")
    return Light(name=name, kind="point", color=color, power=energy,
                 position=tuple(float(x) for x in m[:3, 3]), shadows=shadows)


def _area_light(li, m, name, color, energy, shadows, report: Report) -> Light:
    """An area light as Cycles sees it: the object's X and Y columns (scale included) times
    Size / Size Y span it, it faces along -Z, one-sided; its power in W."""
    x, y, z = m[:3, 0], m[:3, 1], m[:3, 2]
    d = -z / np.linalg.norm(z)
    axis = x - (x @ d) * d
    axis /= np.linalg.norm(axis)
    square = li.shape in ("SQUARE", "DISK")
    size = (float(li.size) * float(np.linalg.norm(x)),
            float(li.size if square else li.size_y) * float(np.linalg.norm(y)))
    spread = float(getattr(li, "spread", np.pi))
    if spread < np.pi - 1e-6:
        report.warning(f"light {name}: spread {np.degrees(spread):.0f} deg ignored (emits "
                       "over the whole hemisphere)")
    if not min(size) > 0:
        report.warning(f"light {name}: an area light of zero size is rendered as a point light")
        return Light(name=name, kind="point", color=color, power=energy,
                     position=tuple(float(v) for v in m[:3, 3]), shadows=shadows)
    return Light(name=name, kind="area", color=color, power=energy,
                 position=tuple(float(v) for v in m[:3, 3]), direction=tuple(float(v) for v in d),
                 axis=tuple(float(v) for v in axis), size=size,
                 shape="ellipse" if li.shape in ("DISK", "ELLIPSE") else "rectangle",
                 shadows=shadows)


def export_camera(obj, scene, report: Report | None = None) -> Camera:
    """A Blender camera object with the scene's render settings (sensor fit, shift)."""
    report = report if report is not None else Report()
    cam = obj.data
    m = matrix_np(obj.matrix_world)
    kind = "perspective"
    if cam.type == "ORTHO":
        kind = "orthographic"
    elif cam.type != "PERSP":
        report.warning(f"camera {obj.name}: {cam.type.lower()} cameras are not supported; "
                       "rendered as a perspective camera")
    r = scene.render
    if abs(r.pixel_aspect_x - r.pixel_aspect_y) > 1e-9:
        report.warning("non-square pixel aspect is ignored (square pixels)")
    return Camera(name=obj.name, matrix_world=m, kind=kind, lens=float(cam.lens),
                  sensor_width=float(cam.sensor_width), sensor_height=float(cam.sensor_height),
                  sensor_fit=str(cam.sensor_fit), shift_x=float(cam.shift_x),
                  shift_y=float(cam.shift_y), ortho_scale=float(cam.ortho_scale),
                  clip_start=float(cam.clip_start), clip_end=float(cam.clip_end))


def render_size(scene) -> tuple[int, int]:
    r = scene.render
    pct = r.resolution_percentage / 100.0
    return max(1, int(r.resolution_x * pct)), max(1, int(r.resolution_y * pct))


def export_environment(depsgraph, exclude, report: Report):
    """(meshes, materials, lights, world) of everything the depsgraph renders but ``exclude``
    (an object or a list of them): objects in enabled collections, not hidden for rendering,
    and their instances (collection instances, particles, geometry-node instances), each with
    its own world matrix."""
    cam = depsgraph.scene.camera
    cam_matrix = matrix_np(cam.evaluated_get(depsgraph).matrix_world) if cam is not None \
        else None
    meshes, materials, lights = [], {}, []
    cache = matmap.EnvironmentMaterials(report, cam_matrix)
    excluded = {o.name for o in _as_list(exclude)}
    counts: dict[str, int] = {}
    for inst in depsgraph.object_instances:
        obj = inst.object
        orig = obj.original
        if inst.is_instance:
            parent = inst.parent.original if inst.parent is not None else None
            if parent is not None and (parent.name in excluded or parent.hide_render):
                continue
        elif orig.name in excluded:
            continue
        if _hidden(obj):
            continue
        k = counts[orig.name] = counts.get(orig.name, 0) + 1
        name = orig.name if k == 1 else f"{orig.name}.inst{k - 1}"
        matrix = inst.matrix_world.copy()
        if obj.type in MESH_LIKE:
            rid = int(inst.random_id) if inst.is_instance else object_random_id(orig.name)
            meshes.extend(_env_meshes(obj, depsgraph, materials, cache, matrix, name, rid))
        elif obj.type == "LIGHT":
            light = export_light(obj, report, matrix, name)
            if light is not None:
                lights.append(light)
        elif obj.type not in {"CAMERA", "EMPTY", "LIGHT_PROBE", "ARMATURE", "SPEAKER"}:
            report.warning(f"{orig.name}: {obj.type.lower()} objects are not part of the "
                           "environment")
    world = matmap.export_world(depsgraph.scene.world, report, cam_matrix)
    return meshes, materials, lights, world


def _as_list(objs) -> list:
    """``objs`` as a list: a list or tuple of objects, one object, or None (none)."""
    return list(objs) if isinstance(objs, (list, tuple)) else [] if objs is None else [objs]


def specular_objects(depsgraph) -> list:
    """The objects the depsgraph renders as specular objects, by name: surface, mesh, curve
    and metaball objects marked RI-Tree Object in their panel, or with a sharp glass or mirror
    material in a slot (materials.is_sharp_specular), and the one object older files named in
    scene.riray.target."""
    legacy = depsgraph.scene.riray.target
    out = []
    for obj in depsgraph.objects:
        orig = obj.original
        if orig.type not in SPECULAR_TYPES or orig.hide_render:
            continue
        if orig.riray.specular or orig == legacy or any(
                matmap.is_sharp_specular(slot.material) for slot in orig.material_slots):
            out.append(orig)
    return sorted(out, key=lambda o: o.name)


def export_scene(depsgraph, target, report: Report | None = None, cameras: str = "ALL",
                 environment: bool = True) -> Scene:
    """The core Scene: ``target`` (an object, or a list of objects) as the specular objects,
    every other visible object as the environment, the scene camera first among the cameras
    (``cameras``: "ALL", "ACTIVE" or "NONE"), the render size with the resolution
    percentage."""
    report = report if report is not None else Report()
    scene = depsgraph.scene
    objs = [export_object(t, depsgraph, report) for t in _as_list(target)]
    if environment:
        meshes, materials, lights, world = export_environment(depsgraph, target, report)
    else:
        meshes, materials, lights, world = [], {}, [], World()
    cams = []
    if cameras != "NONE":
        cam_objs = []
        if scene.camera is not None:
            cam_objs.append(scene.camera)
        if cameras == "ALL":
            cam_objs += [o for o in scene.objects if o.type == "CAMERA" and o is not scene.camera]
        names = set()
        for c in cam_objs:
            if c.name in names:
                continue
            names.add(c.name)
            cams.append(export_camera(c.evaluated_get(depsgraph), scene, report))
    w, h = render_size(scene)
    return Scene(objects=objs, meshes=meshes, materials=materials, lights=lights, world=world,
                 cameras=cams, render=RenderSettings(width=w, height=h,
                                                     max_events=int(scene.riray.max_events)),
                 name=scene.name)


# --------------------------------------------------------------------------- staleness
def object_fingerprint(obj, depsgraph) -> str:
    """SHA-1 of everything the RI-Tree depends on: the exported patches (world space, so the
    transform is included), class ids and the object material. '' when nothing exports."""
    try:
        so = export_object(obj, depsgraph, Report())
    except (ExportError, GeometryError):
        return ""
    return specular_fingerprint(so)


def specular_fingerprint(so) -> str:
    """``object_fingerprint`` of an exported specular object (core SpecularObject)."""
    pts = [p.surface.points.reshape(-1, 3) if p.surface is not None else p.vertices
           for p in so.patches]
    allp = np.concatenate(pts)
    # world coordinates quantized to FINGERPRINT_QUANTUM of the object's size, so float32
    # round trips of a transform (x + 0.1 - 0.1) do not count as a change
    q = FINGERPRINT_QUANTUM * max(float(np.linalg.norm(allp.max(0) - allp.min(0))), 1e-12)
    h = hashlib.sha1()
    for p in so.patches:
        h.update(f"{p.class_id}|".encode())
        if p.surface is not None:
            s = p.surface
            h.update(f"{s.degree_u},{s.degree_v}".encode())
            for a in (s.knots_u, s.knots_v, s.weights):
                h.update(np.ascontiguousarray(np.round(a, 9)).tobytes())
            h.update(np.ascontiguousarray(np.round(s.points / q).astype(np.int64)).tobytes())
        else:
            h.update(np.ascontiguousarray(np.round(p.vertices / q).astype(np.int64)).tobytes())
            h.update(np.ascontiguousarray(p.triangles).tobytes())
            if p.normals is not None:
                h.update(np.ascontiguousarray(np.round(p.normals, 6)).tobytes())
    m = so.material
    h.update(repr((m.kind, round(m.ior, 9), tuple(round(x, 9) for x in m.tint))).encode())
    return h.hexdigest()
