"""Colour of rays leaving the specular object (environment shading) and the object's own local
illumination.

Environment materials: "emission" radiance = texture * strength (lights ignored); "diffuse"
radiance = albedo / pi * (world.ambient + sum of light irradiances); "nodes" radiance = the
graph's emission + its albedo / pi * (the same), both from trace/nodes.py; with
point light  E = color * power / (4 pi r^2) * max(0, n.l)
sun          E = color * strength * max(0, n.l)
and n the shading normal turned towards the incoming ray. Shadow rays are cast only for lights
with ``shadows`` set, only from points the light faces, against the environment meshes and the
optional occluder (a tessellated proxy of the specular object); toward a point light they are
tested as segments ending at it (MeshSet.any_hit's apex: packets bounded from the light, apex
grids). Rays that hit nothing see eval_world(direction). Hit points are shaded as columns
(3, k), one material group at a time; constant colours are not evaluated per point.
"""

from __future__ import annotations

import numpy as np

from ..scene.model import Light, ObjectMaterial, Scene
from .meshes import MeshSet, RayHits
from .nodes import ShadingPoints, evaluate
from .textures import eval_texture, eval_world

SHADOW_OFFSET = 1e-7    # fraction of the scene's bounding-box diagonal (at least 1 m): shadow
                        # ray origins move this far along the facing geometric normal so that
                        # a surface does not shadow itself through rounding
APEX_PAD = 4.0          # shadow-ray offsets: a shadow ray starts one offset off its surface
                        # point and aims from that point at the light, so it passes within one
                        # offset of the light; the apex grids allow this many
SHADE_CHUNK = 8192      # rays shaded at once: bounds the per-chunk arrays (~L2 cache size)
# Radiance is clamped here so that images stay finite in float32 (max 3.4e38) after the
# renderer's factors (tint, at most the scene format's 1e12) for any valid scene; real scenes
# are many orders below it (the sun's disc is ~2e7 W/m^2/sr).
MAX_RADIANCE = 1e20


class Environment:
    """Everything an output ray can see: the scene's meshes, their materials, lights, world,
    and an optional extra shadow-casting MeshSet ``occluder``.

    ``stats`` accumulates {"env_rays": rays shaded, "shadow_rays": shadow rays cast}."""

    def __init__(self, scene: Scene, occluder: MeshSet | None = None):
        self.meshes = MeshSet(scene.meshes)
        self.occluder = occluder if occluder is not None and occluder.num_triangles else None
        self.lights = list(scene.lights)
        self.world = scene.world
        self.materials = []                      # per mesh
        for m in scene.meshes:
            if m.material not in scene.materials:
                raise ValueError(f"mesh {m.name!r}: material {m.material!r} is not in "
                                 f"scene.materials ({sorted(scene.materials)})")
            mat = scene.materials[m.material]
            if mat.kind not in ("diffuse", "emission", "nodes"):
                raise ValueError(f"material {mat.name!r}: kind must be 'diffuse', 'emission' "
                                 f"or 'nodes', got {mat.kind!r}")
            if mat.kind == "nodes" and mat.graph is None:
                raise ValueError(f"material {mat.name!r}: kind 'nodes' needs a graph")
            tex = mat.color
            if mat.kind != "nodes" and tex.kind != "constant" and tex.coords == "uv" \
                    and m.uvs is None:
                raise ValueError(f"mesh {m.name!r}: material {mat.name!r} has a uv-mapped "
                                 f"texture but the mesh has no uvs")
            self.materials.append(mat)
        # one shading group per distinct material, per triangle
        names = list(dict.fromkeys(m.material for m in scene.meshes))
        self._materials = [scene.materials[k] for k in names]
        mesh_group = np.array([names.index(m.material) for m in scene.meshes], dtype=np.int64)
        self._tri_material = mesh_group[self.meshes.tri_mesh]
        for light in self.lights:
            if light.kind not in ("point", "sun"):
                raise ValueError(f"light {light.name!r}: kind must be 'point' or 'sun', "
                                 f"got {light.kind!r}")
        pts = [self.meshes.vertices] + ([self.occluder.vertices] if self.occluder else [])
        pts = np.concatenate(pts)
        diag = float(np.linalg.norm(pts.max(0) - pts.min(0))) if len(pts) else 0.0
        self.offset = SHADOW_OFFSET * max(diag, 1.0)
        self.stats = {"env_rays": 0, "shadow_rays": 0}
        for light in self.lights:             # built here, before a render forks its workers
            if light.kind == "point" and light.shadows:
                for ms in (self.meshes, self.occluder):
                    if ms is not None:
                        ms.prepare_apex(light.position, APEX_PAD * self.offset)

    def closest(self, origins, dirs, tmin=None, tmax=None) -> RayHits:
        """The closest environment hit of each ray in [tmin, tmax] (defaults 0, inf), a hit
        record ``shade_rays`` can take; not counted."""
        return self.meshes.closest(origins, dirs, tmin, tmax)

    def hit_distance(self, origins, dirs, tmin=None, tmax=None) -> np.ndarray:
        """(N,) distance to the closest environment mesh (inf on a miss); not counted."""
        return self.closest(origins, dirs, tmin, tmax).t

    def shade_rays(self, origins, dirs, tmin=None, hits: RayHits | None = None) -> np.ndarray:
        """(N, 3) radiance seen along rays (unit dirs) from t >= tmin (default 0). ``hits``:
        the rays' closest hits (``closest`` with the same tmin), found here when None."""
        origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        n = len(origins)
        tmin = np.broadcast_to(np.asarray(0.0 if tmin is None else tmin, np.float64), (n,))
        out = np.zeros((n, 3))
        for c0 in range(0, n, SHADE_CHUNK):
            sl = slice(c0, min(n, c0 + SHADE_CHUNK))
            h = (self.meshes.closest(origins[sl], dirs[sl], tmin[sl]) if hits is None
                 else hits.take(sl))
            out[sl] = self._shade_chunk(dirs[sl], h)
        self.stats["env_rays"] += n
        return np.clip(out, -MAX_RADIANCE, MAX_RADIANCE)

    def _shade_chunk(self, dirs, hits: RayHits):
        """Radiance along rays ``dirs`` with closest hits ``hits``: the world where they miss;
        emission + albedo / pi * (ambient + irradiance) where they hit, the irradiance (and
        its shadow rays) found once for every point with an albedo, whatever its material.
        Hit points are worked on as columns (3, k): per-point arithmetic runs over rows."""
        n = len(dirs)
        out = np.empty((3, n))
        hit = hits.tri >= 0
        idx = np.flatnonzero(hit)
        if len(idx) < n:
            miss = np.flatnonzero(~hit)
            _put(out, miss, eval_world(self.world, dirs[miss]).T)
        if len(idx) == 0:
            return out.T
        if len(idx) == n:                               # all hit: no gathers
            tri, b1, b2, d = hits.tri, hits.b1, hits.b2, np.ascontiguousarray(dirs.T)
        else:
            tri, b1, b2 = hits.tri[idx], hits.b1[idx], hits.b2[idx]
            d = np.ascontiguousarray(dirs[idx].T)
        point, geo, normal = self.meshes.surface(tri, b1, b2)
        # normals turned towards the incoming ray (the geometric side decides)
        back = geo[0] * d[0] + geo[1] * d[1] + geo[2] * d[2] > 0
        flip = np.where(back, -1.0, 1.0)
        geo, normal = geo * flip, normal * flip
        k = len(idx)
        emission, albedo = np.zeros((3, k)), np.zeros((3, k))
        lit = np.zeros(k, bool)
        group = self._tri_material[tri]
        for g in np.flatnonzero(np.bincount(group, minlength=len(self._materials))):
            sel = np.flatnonzero(group == g)
            mat = self._materials[g]
            at = lambda a: a.take(sel, axis=1).T
            if mat.kind == "nodes":
                cl = evaluate(mat.graph, ShadingPoints(
                    position=at(point), normal=at(normal), true_normal=at(geo), incoming=-at(d),
                    uv=self.meshes.uv_at(tri[sel], b1[sel], b2[sel]).T, backfacing=back[sel]))
                alb = np.broadcast_to(cl.albedo, (len(sel), 3)).T
                _put(emission, sel, np.broadcast_to(cl.emission, (len(sel), 3)).T)
                _put(albedo, sel, alb)
                lit[sel] = np.any(alb != 0, axis=0)             # only these cast shadow rays
                continue
            tex = mat.color
            if tex.kind == "constant":                  # not evaluated per point
                col = np.broadcast_to(np.asarray(tex.color, dtype=np.float64)[:, None],
                                      (3, len(sel)))
            else:
                col = eval_texture(tex, at(point), self.meshes.uv_at(tri[sel], b1[sel],
                                                                     b2[sel]).T).T
            if mat.kind == "emission":
                _put(emission, sel, col * mat.strength)
            else:
                _put(albedo, sel, col)
                lit[sel] = True
        on = np.flatnonzero(lit)
        if len(on) < k:
            off = np.flatnonzero(~lit)
            _put(out, idx[off], emission.take(off, axis=1))
            point, normal, geo, emission, albedo = (a.take(on, axis=1) for a in
                                                    (point, normal, geo, emission, albedo))
            idx = idx[on]
        if len(on):
            irr = sum(self._light_cols(light, point, normal, geo, self.occluder)[0]
                      for light in self.lights)
            _put(out, idx, emission + albedo * (self.world.ambient + irr) / np.pi)
        return out.T

    def light_irradiance(self, light: Light, points, normals, offset_normals, occluder=None):
        """(E (N, 3), l (N, 3)): the irradiance from one light (cosine and shadow included)
        and the unit directions towards it."""
        cols = (np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(-1, 3).T)
                for a in (points, normals, offset_normals))
        e, l = self._light_cols(light, *cols, occluder)
        return e.T, l.T

    def _light_cols(self, light: Light, p, nrm, off_nrm, occluder):
        """``light_irradiance`` on columns: points, normals, offset normals (3, k) each."""
        if light.kind == "point":
            pos = np.asarray(light.position, dtype=np.float64)
            to = pos[:, None] - p
            r2 = to[0] * to[0] + to[1] * to[1] + to[2] * to[2]
            r = np.sqrt(r2)
            l = to / np.where(r > 0, r, 1.0)
            # a light nearer than the shadow offset is on the surface: 1/r^2 stops growing
            # there (finite, so colour components of 0 give 0, not NaN)
            scale = light.power / (4.0 * np.pi * np.maximum(r2, self.offset ** 2))
        else:
            d = np.asarray(light.direction, dtype=np.float64)
            l = np.broadcast_to((-d / np.linalg.norm(d))[:, None], p.shape)
            scale = float(light.strength)
        cos = np.maximum(nrm[0] * l[0] + nrm[1] * l[1] + nrm[2] * l[2], 0.0)
        lit = cos > 0
        if light.shadows and lit.any():
            idx = np.flatnonzero(lit)
            l_on = l
            if len(idx) < len(lit):
                p, off_nrm, l_on = (a.take(idx, axis=1) for a in (p, off_nrm, l))
            o = p + self.offset * off_nrm
            if light.kind == "point":
                to_o = pos[:, None] - o
                dist = np.sqrt(to_o[0] * to_o[0] + to_o[1] * to_o[1] + to_o[2] * to_o[2])
            else:
                dist = np.full(len(idx), np.inf)
            blocked = self._occluded(o.T, l_on.T, dist, occluder,
                                     pos if light.kind == "point" else None)
            lit[idx[blocked]] = False
        e = np.where(lit, scale * cos, 0.0) * np.asarray(light.color, dtype=np.float64)[:, None]
        return e, l

    def _occluded(self, origins, dirs, dist, occluder, apex):
        """(n,) bool: is each shadow segment blocked; ``apex``: the point light they end at."""
        self.stats["shadow_rays"] += len(origins)
        pad = APEX_PAD * self.offset
        blocked = self.meshes.any_hit(origins, dirs, 0.0, dist, apex, pad)
        if occluder is None or blocked.all():
            return blocked
        if not blocked.any():
            return occluder.any_hit(origins, dirs, 0.0, dist, apex, pad)
        free = np.flatnonzero(~blocked)
        blocked[free] = occluder.any_hit(origins[free], dirs[free], 0.0, dist[free], apex, pad)
        return blocked


def _put(out, idx, values):
    """out[:, idx] = values, row by row (a fancy assignment along the second axis is slower)."""
    for row, v in zip(out, values):
        row[idx] = v


def local_illumination(points, normals, view_dirs, material: ObjectMaterial,
                       env: Environment) -> np.ndarray:
    """(N, 3) local shading of the specular object at ``points`` with unit ``normals``, seen
    along ``view_dirs`` (unit, viewer -> point; normals are flipped to face the viewer):

        diffuse * base_color / pi * (ambient + sum_l E_l)
      + specular * sum_l color_l * scale_l * cos_l * (s + 8) / (8 pi) * max(0, n.h)^s

    (energy-normalised Blinn-Phong, s = shininess, h the half vector). Shadow rays test the
    environment meshes only: the object casts no shadow on itself (its tessellated proxy,
    ``env.occluder``, would shadow the exact surface it approximates)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    view_dirs = np.asarray(view_dirs, dtype=np.float64).reshape(-1, 3)
    out = np.zeros((len(points), 3))
    if len(points) == 0 or (material.diffuse == 0 and material.specular == 0):
        return out
    n = normals * np.where(np.einsum("ij,ij->i", normals, view_dirs) > 0, -1.0, 1.0)[:, None]
    base = material.diffuse * np.asarray(material.base_color, dtype=np.float64) / np.pi
    out += base * env.world.ambient
    s = float(material.shininess)
    for light in env.lights:
        e, l = env.light_irradiance(light, points, n, n)
        if material.diffuse:
            out += base * e
        if material.specular:
            h = l - view_dirs
            hn = np.linalg.norm(h, axis=1)
            h /= np.where(hn > 0, hn, 1.0)[:, None]
            nh = np.maximum(np.einsum("ij,ij->i", n, h), 0.0)
            out += (material.specular * (s + 8.0) / (8.0 * np.pi)) * e * (nh ** s)[:, None]
    return np.minimum(out, MAX_RADIANCE)
