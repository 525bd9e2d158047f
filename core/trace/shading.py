"""Colour of rays leaving the specular object (environment shading) and the object's own local
illumination.

Environment materials: "emission" radiance = texture * strength (lights ignored); "diffuse"
radiance = albedo / pi * (world.ambient + sum of light irradiances); "nodes" radiance = the
graph's emission + its albedo / pi * (the same), both from trace/nodes.py; with
point light  E = color * power / (4 pi r^2) * max(0, n.l)
sun          E = color * strength * max(0, n.l)
and n the shading normal turned towards the incoming ray. Shadow rays are cast only for lights
with ``shadows`` set, only from points the light faces, against the environment meshes and the
optional occluder (a tessellated proxy of the specular object). Rays that hit nothing see
eval_world(direction).
"""

from __future__ import annotations

import numpy as np

from ..scene.model import Light, ObjectMaterial, Scene
from .meshes import MeshSet
from .nodes import ShadingPoints, evaluate
from .textures import eval_texture, eval_world

SHADOW_OFFSET = 1e-7    # fraction of the scene's bounding-box diagonal (at least 1 m): shadow
                        # ray origins move this far along the facing geometric normal so that
                        # a surface does not shadow itself through rounding
SHADE_CHUNK = 65536     # rays shaded at once: bounds the per-chunk hit records
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
        for light in self.lights:
            if light.kind not in ("point", "sun"):
                raise ValueError(f"light {light.name!r}: kind must be 'point' or 'sun', "
                                 f"got {light.kind!r}")
        pts = [self.meshes.vertices] + ([self.occluder.vertices] if self.occluder else [])
        pts = np.concatenate(pts)
        diag = float(np.linalg.norm(pts.max(0) - pts.min(0))) if len(pts) else 0.0
        self.offset = SHADOW_OFFSET * max(diag, 1.0)
        self.stats = {"env_rays": 0, "shadow_rays": 0}

    def hit_distance(self, origins, dirs, tmin=None, tmax=None) -> np.ndarray:
        """(N,) distance to the closest environment mesh (inf on a miss); not counted."""
        return self.meshes.closest_t(origins, dirs, tmin, tmax)[0]

    def shade_rays(self, origins, dirs, tmin=None) -> np.ndarray:
        """(N, 3) radiance seen along rays (unit dirs) from t >= tmin (default 0)."""
        origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        n = len(origins)
        tmin = np.broadcast_to(np.asarray(0.0 if tmin is None else tmin, np.float64), (n,))
        out = np.zeros((n, 3))
        for c0 in range(0, n, SHADE_CHUNK):
            sl = slice(c0, min(n, c0 + SHADE_CHUNK))
            out[sl] = self._shade_chunk(origins[sl], dirs[sl], tmin[sl])
        self.stats["env_rays"] += n
        return np.clip(out, -MAX_RADIANCE, MAX_RADIANCE)

    def _shade_chunk(self, origins, dirs, tmin):
        hit = self.meshes.closest_hit(origins, dirs, tmin)
        out = np.zeros((len(origins), 3))
        miss = ~hit.hit
        if miss.any():
            out[miss] = eval_world(self.world, dirs[miss])
        for k in np.unique(hit.mesh[hit.hit]):
            sel = np.flatnonzero(hit.mesh == k)
            mat = self.materials[k]
            # normals turned towards the incoming ray (the geometric side decides)
            back = np.einsum("ij,ij->i", hit.geo_normal[sel], dirs[sel]) > 0
            flip = np.where(back, -1.0, 1.0)[:, None]
            normal, geo = hit.normal[sel] * flip, hit.geo_normal[sel] * flip
            if mat.kind == "nodes":
                cl = evaluate(mat.graph, ShadingPoints(
                    position=hit.point[sel], normal=normal, true_normal=geo,
                    incoming=-dirs[sel], uv=hit.uv[sel], backfacing=back))
                lit = np.any(cl.albedo != 0, axis=1)
                if lit.all():
                    irr = self.irradiance(hit.point[sel], normal, geo, self.occluder)
                    out[sel] = cl.emission + cl.albedo * (self.world.ambient + irr) / np.pi
                    continue
                out[sel] = cl.emission
                if lit.any():       # only points with an albedo cast shadow rays
                    lit = np.flatnonzero(lit)
                    irr = self.irradiance(hit.point[sel[lit]], normal[lit], geo[lit],
                                          self.occluder)
                    out[sel[lit]] += cl.albedo[lit] * (self.world.ambient + irr) / np.pi
                continue
            tex = mat.color
            if tex.kind == "constant":
                albedo = np.broadcast_to(np.asarray(tex.color, dtype=np.float64), (len(sel), 3))
            else:
                albedo = eval_texture(tex, hit.point[sel], hit.uv[sel])
            if mat.kind == "emission":
                out[sel] = albedo * mat.strength
                continue
            irr = self.irradiance(hit.point[sel], normal, geo, self.occluder)
            out[sel] = albedo * (self.world.ambient + irr) / np.pi
        return out

    def irradiance(self, points, normals, offset_normals, occluder=None) -> np.ndarray:
        """(N, 3) direct irradiance sum_l E_l from the scene's lights at ``points`` with unit
        ``normals``; shadow rays start ``self.offset`` along ``offset_normals`` and test the
        environment meshes and ``occluder``."""
        out = np.zeros((len(points), 3))
        for light in self.lights:
            out += self.light_irradiance(light, points, normals, offset_normals, occluder)[0]
        return out

    def light_irradiance(self, light: Light, points, normals, offset_normals, occluder=None):
        """(E (N, 3), l (N, 3)): the irradiance from one light (cosine and shadow included)
        and the unit directions towards it."""
        if light.kind == "point":
            to = np.asarray(light.position, dtype=np.float64) - points
            r2 = np.einsum("ij,ij->i", to, to)
            r = np.sqrt(r2)
            l = to / np.where(r > 0, r, 1.0)[:, None]
            # a light nearer than the shadow offset is on the surface: 1/r^2 stops growing
            # there (finite, so colour components of 0 give 0, not NaN)
            scale = light.power / (4.0 * np.pi * np.maximum(r2, self.offset ** 2))
        else:
            d = np.asarray(light.direction, dtype=np.float64)
            l = np.broadcast_to(-d / np.linalg.norm(d), points.shape)
            r = np.full(len(points), np.inf)
            scale = np.full(len(points), float(light.strength))
        cos = np.maximum(np.einsum("ij,ij->i", normals, l), 0.0)
        lit = cos > 0
        if light.shadows and lit.any():
            idx = np.flatnonzero(lit)
            o = points[idx] + self.offset * offset_normals[idx]
            dist = (np.linalg.norm(np.asarray(light.position, dtype=np.float64) - o, axis=1)
                    if light.kind == "point" else r[idx])
            blocked = self._occluded(o, l[idx], dist, occluder)
            lit[idx[blocked]] = False
        e = np.where(lit, scale * cos, 0.0)[:, None] * np.asarray(light.color, dtype=np.float64)
        return e, l

    def _occluded(self, origins, dirs, dist, occluder):
        self.stats["shadow_rays"] += len(origins)
        blocked = self.meshes.any_hit(origins, dirs, 0.0, dist)
        if occluder is not None and not blocked.all():
            free = np.flatnonzero(~blocked)
            blocked[free] = occluder.any_hit(origins[free], dirs[free], 0.0, dist[free])
        return blocked


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
