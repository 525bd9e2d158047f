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
from .meshes import MeshSet, RayHits
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
        its shadow rays) found once for every point with an albedo, whatever its material."""
        hit = self.meshes.record(hits)
        n = len(dirs)
        out = np.zeros((n, 3))
        miss = ~hit.hit
        if miss.any():
            out[miss] = eval_world(self.world, dirs[miss])
        idx = np.flatnonzero(hit.hit)
        if len(idx) == 0:
            return out
        # normals turned towards the incoming ray (the geometric side decides)
        d = dirs[idx]
        back = np.einsum("ij,ij->i", hit.geo_normal[idx], d) > 0
        flip = np.where(back, -1.0, 1.0)[:, None]
        normal, geo, point = hit.normal[idx] * flip, hit.geo_normal[idx] * flip, hit.point[idx]
        emission = np.zeros((len(idx), 3))
        albedo = np.zeros((len(idx), 3))
        lit = np.zeros(len(idx), bool)
        mesh = hit.mesh[idx]
        order = np.argsort(mesh, kind="stable")
        starts = np.flatnonzero(np.r_[True, mesh[order][1:] != mesh[order][:-1]])
        for sel in np.split(order, starts[1:]):        # one group per mesh, rays in order
            mat = self.materials[int(mesh[sel[0]])]
            if mat.kind == "nodes":
                cl = evaluate(mat.graph, ShadingPoints(
                    position=point[sel], normal=normal[sel], true_normal=geo[sel],
                    incoming=-d[sel], uv=hit.uv[idx[sel]], backfacing=back[sel]))
                emission[sel], albedo[sel] = cl.emission, cl.albedo
                lit[sel] = np.any(cl.albedo != 0, axis=1)   # only these cast shadow rays
                continue
            tex = mat.color
            if mat.kind == "emission":
                if tex.kind == "constant":
                    emission[sel] = np.asarray(tex.color, dtype=np.float64) * mat.strength
                else:
                    emission[sel] = eval_texture(tex, point[sel], hit.uv[idx[sel]]) * mat.strength
                continue
            albedo[sel] = (tex.color if tex.kind == "constant"
                           else eval_texture(tex, point[sel], hit.uv[idx[sel]]))
            lit[sel] = True
        on = np.flatnonzero(lit)
        off = np.flatnonzero(~lit)
        out[idx[off]] = emission[off]
        if len(on):
            irr = self.irradiance(point[on], normal[on], geo[on], self.occluder)
            out[idx[on]] = emission[on] + albedo[on] * (self.world.ambient + irr) / np.pi
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
