"""Colour of rays leaving the specular object (environment shading) and the object's own local
illumination.

Environment materials: "emission" radiance = texture * strength (lights ignored); "diffuse"
radiance = albedo / pi * (world.ambient + E_sky + sum of light irradiances); "nodes" radiance =
the graph's emission + its albedo / pi * (the same), both from trace/nodes.py; with
point light  E = color * power / (4 pi r^2) * max(0, n.l)
sun          E = color * strength * max(0, n.l)
area light   E = L * F * V: L = color * power / (pi * area) (Cycles' convention), F the
             closed-form form factor of the light's polygon (an ellipse: a 32-gon of its area)
             where the whole light is above the horizon, else estimated from the samples; V the
             share of the samples' contribution cos cos' / r^2 unshadowed (16 stratified points
             on the light, each a shadow ray): soft shadows, exact where nothing occludes
sky          E_sky = pi * mean of the world's radiance along 16 stratified cosine-weighted
             rays, 0 for those that meet the environment or the occluder (only when
             world.sky is set: the world lights the scene)
and n the shading normal turned towards the incoming ray. Sample sets are stratified grids
shifted per point by a hash of its coordinates (trace/lights.py): deterministic, and noise
rather than bands where they do not converge. A "diffuse" material with metallic m adds
m * colour * (its reflection + the lights' highlight): a mirror ray into the environment for
roughness <= 0.1 (it sees the area lights), else 9 stratified rays in a Blinn-Phong lobe of
exponent 2 / roughness^4 - 2 plus that lobe's highlight from each light; reflected rays are
shaded without further metal reflection. Rays that meet an area light's lit face before any
surface add its radiance L. Shadow rays are cast only for lights with ``shadows`` set, only
from points the light faces, against the environment meshes and the optional occluder (a
tessellated proxy of the specular object); toward a point light they are tested as segments
ending at it (MeshSet.any_hit's apex: packets bounded from the light, apex grids). Rays that
hit nothing see eval_world(direction). Hit points are shaded as columns (3, k), one material
group at a time; constant colours are not evaluated per point. None of the sampled terms
costs anything in a scene without area lights, sky lighting or metals.
"""

from __future__ import annotations

import numpy as np

from ..scene.model import Light, ObjectMaterial, Scene
from .lights import (AreaLight, cosine_directions, lobe_directions, point_offsets,
                     sphere_directions)
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
SKY_SIDE = 4            # the sky term: SKY_SIDE^2 stratified cosine-weighted occlusion rays
# The sky term is cast only where the world can be seen at all: SKY_PROBE_SIDE^3 points at the
# cell centres of a grid over the environment's box each look along SKY_PROBE_DIRS directions
# spread over the sphere; where none of those rays leaves the environment (a closed room) the
# term is off: a point could then see the world only through an opening narrower than the
# probes resolve (below about 1/SKY_PROBE_DIRS of the sphere), whose light is that small.
SKY_PROBE_SIDE = 8
SKY_PROBE_DIRS = 64
AREA_SIDE = 4           # an area light: AREA_SIDE^2 stratified shadow rays to points on it
GLOSSY_SIDE = 3         # a rough metal: GLOSSY_SIDE^2 stratified reflection rays in its lobe
ROUGH_SHARP = 0.1       # Blender roughness up to which a metal reflects as a mirror (its lobe,
                        # exponent 2e4 at 0.1, is narrower than a pixel's footprint there)
SALT_SKY, SALT_AREA, SALT_GLOSSY = 1, 2, 3      # independent sample offsets per term


def roughness_shininess(roughness: float) -> float:
    """The Blinn-Phong exponent of a microfacet lobe of Blender ``roughness`` (alpha =
    roughness^2; the Beckmann-equivalent exponent 2 / alpha^2 - 2), at least 1."""
    alpha = max(float(roughness), 1e-3) ** 2
    return max(2.0 / (alpha * alpha) - 2.0, 1.0)


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
            if light.kind not in ("point", "sun", "area"):
                raise ValueError(f"light {light.name!r}: kind must be 'point', 'sun' or "
                                 f"'area', got {light.kind!r}")
        self._areas = {id(li): AreaLight(li) for li in self.lights if li.kind == "area"}
        self._glossy = any(m.kind != "emission" and (m.metallic > 0 or m.specular > 0)
                           for m in self._materials)
        w = self.world
        dark = w.strength == 0 or (w.kind == "color" and max(w.color) == 0)
        pts = [self.meshes.vertices] + ([self.occluder.vertices] if self.occluder else [])
        pts = np.concatenate(pts)
        diag = float(np.linalg.norm(pts.max(0) - pts.min(0))) if len(pts) else 0.0
        self.offset = SHADOW_OFFSET * max(diag, 1.0)
        # the sky term is on (off for a black world, or one no probe ray reaches)
        self.sky = bool(w.sky) and not dark and self._world_reachable()
        self.stats = {"env_rays": 0, "shadow_rays": 0}
        for light in self.lights:             # built here, before a render forks its workers
            if light.kind == "point" and light.shadows:
                for ms in (self.meshes, self.occluder):
                    if ms is not None:
                        ms.prepare_apex(light.position, APEX_PAD * self.offset)

    def _world_reachable(self) -> bool:
        """Whether any of SKY_PROBE_SIDE^3 points spread through the environment's box sees
        the world along one of SKY_PROBE_DIRS directions from beyond the shadow offset (a probe
        on a floor plane sees past it; no environment: yes)."""
        v = self.meshes.vertices
        if len(v) == 0:
            return True
        lo, hi = v.min(axis=0), v.max(axis=0)
        f = (np.arange(SKY_PROBE_SIDE) + 0.5) / SKY_PROBE_SIDE
        grid = np.stack(np.meshgrid(f, f, f, indexing="ij"), axis=-1).reshape(-1, 3)
        points = lo + grid * (hi - lo)
        dirs = sphere_directions(SKY_PROBE_DIRS)
        o = np.repeat(points, len(dirs), axis=0)
        d = np.tile(dirs, (len(points), 1))
        return not bool(np.all(self.meshes.any_hit(o, d, np.full(len(o), self.offset))))

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
        return self._shade_rays(origins, dirs, tmin, hits, bounce=0, see_lights=True)

    def _shade_rays(self, origins, dirs, tmin, hits, bounce: int, see_lights: bool):
        """``shade_rays`` at reflection depth ``bounce`` (metals reflect at depth 0 only);
        ``see_lights``: add the radiance of the area lights the rays meet first."""
        origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        n = len(origins)
        tmin = np.broadcast_to(np.asarray(0.0 if tmin is None else tmin, np.float64), (n,))
        out = np.zeros((n, 3))
        for c0 in range(0, n, SHADE_CHUNK):
            sl = slice(c0, min(n, c0 + SHADE_CHUNK))
            h = (self.meshes.closest(origins[sl], dirs[sl], tmin[sl]) if hits is None
                 else hits.take(sl))
            out[sl] = self._shade_chunk(dirs[sl], h, bounce)
            if see_lights and self._areas:
                out[sl] += self._lights_seen(origins[sl], dirs[sl], tmin[sl], h.t)
        self.stats["env_rays"] += n
        return np.clip(out, -MAX_RADIANCE, MAX_RADIANCE)

    def _lights_seen(self, origins, dirs, tmin, tmax) -> np.ndarray:
        """(n, 3) radiance of the area lights' lit faces met by the rays within (tmin, tmax)
        (lights are not opaque: what lies behind one is seen too, as in Cycles)."""
        out = np.zeros((len(origins), 3))
        o = origins + dirs * tmin[:, None]
        for area in self._areas.values():
            t = area.hit_distance(o, dirs) + tmin
            out[t < tmax] += area.radiance
        return out

    def _shade_chunk(self, dirs, hits: RayHits, bounce: int = 0):
        """Radiance along rays ``dirs`` with closest hits ``hits``: the world where they miss;
        emission + albedo / pi * (ambient + irradiance) + metal reflection where they hit,
        the irradiance (and its shadow rays) found once for every point with an albedo or a
        metal, whatever its material. Hit points are worked on as columns (3, k): per-point
        arithmetic runs over rows."""
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
        # glossy layers (depth 0 only): their material group, -1 elsewhere; the metal's tint
        # and the dielectric coat's Fresnel weight
        glossy = np.full(k, -1, np.int64) if self._glossy and bounce == 0 else None
        tint, coat = (np.zeros((3, k)), np.zeros(k)) if glossy is not None else (None, None)
        group = self._tri_material[tri]
        for g in np.flatnonzero(np.bincount(group, minlength=len(self._materials))):
            sel = np.flatnonzero(group == g)
            mat = self._materials[g]
            at = lambda a: a.take(sel, axis=1).T
            if mat.kind == "nodes":
                cl = evaluate(mat.graph, ShadingPoints(
                    position=at(point), normal=at(normal), true_normal=at(geo), incoming=-at(d),
                    uv=self.meshes.uv_at(tri[sel], b1[sel], b2[sel]).T, backfacing=back[sel]))
                col = np.broadcast_to(cl.albedo, (len(sel), 3)).T
                _put(emission, sel, np.broadcast_to(cl.emission, (len(sel), 3)).T)
                lit[sel] = np.any(col != 0, axis=0)             # only these cast shadow rays
            else:
                tex = mat.color
                if tex.kind == "constant":                  # not evaluated per point
                    col = np.broadcast_to(np.asarray(tex.color, dtype=np.float64)[:, None],
                                          (3, len(sel)))
                else:
                    col = eval_texture(tex, at(point), self.meshes.uv_at(tri[sel], b1[sel],
                                                                         b2[sel]).T).T
                if mat.kind == "emission":
                    _put(emission, sel, col * mat.strength)
                    continue
                lit[sel] = True
            if glossy is not None and (mat.metallic > 0 or mat.specular > 0):
                glossy[sel] = g
                lit[sel] = True
                _put(tint, sel, col * mat.metallic)
                fr = _fresnel(mat, -np.sum(d[:, sel] * normal[:, sel], axis=0))
                coat[sel] = (1.0 - mat.metallic) * fr
                col = col * ((1.0 - mat.metallic) * (1.0 - fr))
            _put(albedo, sel, col)
        on = np.flatnonzero(lit)
        if len(on) < k:
            off = np.flatnonzero(~lit)
            _put(out, idx[off], emission.take(off, axis=1))
            point, normal, geo, emission, albedo, d = (
                a.take(on, axis=1) for a in (point, normal, geo, emission, albedo, d))
            idx = idx[on]
            if glossy is not None:
                glossy, tint, coat = glossy[on], tint.take(on, axis=1), coat[on]
        if len(on) == 0:
            return out.T
        if glossy is not None and not np.any(glossy >= 0):
            glossy = None
        irr = np.zeros_like(albedo)
        shine = np.zeros_like(albedo) if glossy is not None else None
        for light in self.lights:
            e, l = self._light_cols(light, point, normal, geo, self.occluder)
            irr += e
            if shine is not None:
                shine += self._highlights(e, l, normal, d, glossy)
        sky = self.sky_irradiance(point, normal, geo, self.occluder) if self.sky else 0.0
        col = emission + albedo * (self.world.ambient + irr + sky) / np.pi
        if glossy is not None:
            col += (tint + coat) * shine + coat * (sky / np.pi) + tint * self._metal_reflection(
                point, normal, geo, d, glossy)
        _put(out, idx, col)
        return out.T

    def _group_rows(self, glossy, metals_only=False):
        """(material, row indices) of the glossy points, one material at a time."""
        for g in np.unique(glossy[glossy >= 0]):
            if not metals_only or self._materials[g].metallic > 0:
                yield self._materials[g], np.flatnonzero(glossy == g)

    def _highlights(self, e, l, normal, d, glossy):
        """(3, k) the lights' Blinn-Phong highlight of rough glossy layers (per unit weight):
        e * the lobe (s + 8) / (8 pi) (n.h)^s, s from the roughness; 0 for sharp layers and
        others (a sharp metal's reflection rays see the area lights themselves)."""
        out = np.zeros_like(e)
        h = l - d
        h = h / np.maximum(np.linalg.norm(h, axis=0), 1e-300)
        nh = np.maximum(np.sum(normal * h, axis=0), 0.0)
        for mat, rows in self._group_rows(glossy):
            if mat.roughness <= ROUGH_SHARP:
                continue
            s = roughness_shininess(mat.roughness)
            _put(out, rows, e[:, rows] * ((s + 8.0) / (8.0 * np.pi) * nh[rows] ** s))
        return out

    def _metal_reflection(self, point, normal, geo, d, glossy):
        """(3, k) radiance the metal points reflect (per unit tint): one reflection bounce
        into the environment, a mirror ray for sharp metals, GLOSSY_SIDE^2 stratified rays in
        the roughness lobe otherwise (area lights are then left to ``_highlights``)."""
        out = np.zeros_like(point)
        r = d - 2.0 * np.sum(d * normal, axis=0) * normal
        for mat, rows in self._group_rows(glossy, metals_only=True):
            o = (point[:, rows] + self.offset * geo[:, rows])
            if mat.roughness <= ROUGH_SHARP:
                rad = self._shade_rays(o.T, r[:, rows].T, None, None, 1, True)
                _put(out, rows, rad.T)
                continue
            dirs = lobe_directions(r[:, rows], roughness_shininess(mat.roughness), GLOSSY_SIDE,
                                   point_offsets(point[:, rows], SALT_GLOSSY))
            m = dirs.shape[2]
            below = np.einsum("ik,ikm->km", geo[:, rows], dirs) <= 0
            dirs = np.where(below[None], r[:, rows, None], dirs)       # the mirror ray instead
            rad = self._shade_rays(np.repeat(o.T, m, axis=0), dirs.reshape(3, -1).T, None,
                                   None, 1, False)
            _put(out, rows, rad.reshape(len(rows), m, 3).mean(axis=1).T)
        return out

    def sky_irradiance(self, p, nrm, off_nrm, occluder):
        """(3, k) irradiance from the world at points ``p`` with normals ``nrm`` (offset
        normals ``off_nrm``), columns: pi * the mean world radiance along SKY_SIDE^2
        stratified cosine-weighted rays, 0 for those that meet the environment or
        ``occluder`` (or point below the surface)."""
        dirs = cosine_directions(nrm, SKY_SIDE, point_offsets(p, SALT_SKY))
        m = dirs.shape[2]
        up = np.einsum("ik,ikm->km", off_nrm, dirs) > 0
        flat = dirs.reshape(3, -1)
        free = up.ravel().copy()
        on = np.flatnonzero(free)
        o = np.repeat(p + self.offset * off_nrm, m, axis=1)
        free[on] = ~self._occluded(o[:, on].T, flat[:, on].T, np.full(len(on), np.inf),
                                   occluder, None)
        rad = np.zeros((len(free), 3))
        seen = np.flatnonzero(free)
        rad[seen] = eval_world(self.world, flat[:, seen].T)
        return np.pi * rad.reshape(-1, m, 3).mean(axis=1).T

    def light_irradiance(self, light: Light, points, normals, offset_normals, occluder=None):
        """(E (N, 3), l (N, 3)): the irradiance from one light (cosine and shadow included)
        and the unit directions towards it."""
        cols = (np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(-1, 3).T)
                for a in (points, normals, offset_normals))
        e, l = self._light_cols(light, *cols, occluder)
        return e.T, l.T

    def _light_cols(self, light: Light, p, nrm, off_nrm, occluder):
        """``light_irradiance`` on columns: points, normals, offset normals (3, k) each."""
        if light.kind == "area":
            return self._area_cols(self._areas[id(light)], p, nrm, off_nrm, occluder)
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

    def _area_cols(self, area: AreaLight, p, nrm, off_nrm, occluder):
        """(E, l) (3, k) each of an area light: radiance * the closed-form form factor where
        the whole light is above a point's horizon (else the AREA_SIDE^2 stratified samples'
        estimate), times the share of the samples' contribution cos cos' / r^2 that reaches
        the point unshadowed; l towards the light's centre."""
        k = p.shape[1]
        to_c = area.centre[:, None] - p
        l = to_c / np.maximum(np.linalg.norm(to_c, axis=0), 1e-300)
        e = np.zeros((3, k))
        front = np.flatnonzero(area.in_front(p))
        if len(front) == 0:
            return e, l
        p, nrm, off_nrm = (a.take(front, axis=1) for a in (p, nrm, off_nrm))
        q = area.sample_points(AREA_SIDE, point_offsets(p, SALT_AREA))     # (3, f, m)
        w = q - p[:, :, None]
        r2 = np.maximum(np.einsum("ikm,ikm->km", w, w), self.offset ** 2)
        r = np.sqrt(r2)
        cos_p = np.maximum(np.einsum("ik,ikm->km", nrm, w), 0.0) / r
        cos_l = np.maximum(-np.einsum("i,ikm->km", area.normal, w), 0.0) / r
        f = cos_p * cos_l / r2
        total = f.sum(axis=1)
        seen = f.copy()
        if area.light.shadows:
            on = np.flatnonzero(f.ravel() > 0)
            o = np.repeat(p + self.offset * off_nrm, f.shape[1], axis=1)[:, on]
            to = q.reshape(3, -1)[:, on] - o
            dist = np.linalg.norm(to, axis=0)
            blocked = self._occluded(o.T, (to / np.maximum(dist, 1e-300)).T, dist, occluder,
                                     None)
            seen.ravel()[on[blocked]] = 0.0
        ff, whole = area.form_factor(p, nrm)
        ff = np.where(whole, ff, total * area.area / f.shape[1])
        share = seen.sum(axis=1) / np.where(total > 0, total, 1.0)
        _put(e, front, area.radiance[:, None] * (ff * share))
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


def _fresnel(mat, cos) -> np.ndarray:
    """(k,) reflectance of a dielectric layer of normal reflectance ``mat.specular`` seen at
    cosines ``cos``: Schlick's with the grazing limit lowered by the roughness (a rough
    layer reflects less at grazing angles)."""
    f0 = float(mat.specular)
    edge = max(1.0 - float(mat.roughness), f0)
    return f0 + (edge - f0) * (1.0 - np.clip(cos, 0.0, 1.0)) ** 5


def _put(out, idx, values):
    """out[:, idx] = values, row by row (a fancy assignment along the second axis is slower)."""
    for row, v in zip(out, values):
        row[idx] = v


def local_illumination(points, normals, view_dirs, material: ObjectMaterial,
                       env: Environment) -> np.ndarray:
    """(N, 3) local shading of the specular object at ``points`` with unit ``normals``, seen
    along ``view_dirs`` (unit, viewer -> point; normals are flipped to face the viewer):

        diffuse * base_color / pi * (ambient + E_sky + sum_l E_l)
      + specular * sum_l E_l * (s + 8) / (8 pi) * max(0, n.h)^s

    (energy-normalised Blinn-Phong, s = shininess, h the half vector towards the light or an
    area light's centre; E_sky when the world lights the scene). Shadow rays test the
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
    if material.diffuse and env.sky:
        cols = [np.ascontiguousarray(a.T) for a in (points, n)]
        out += base * env.sky_irradiance(cols[0], cols[1], cols[1], None).T
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
