"""The scene as the tracer sees it: the object's exact patch tracer and the environment (meshes,
lights, world), built once and shared by every renderer, the RI-Tree bake and its query; with
the box-entry and camera-inside tests every frame needs.
"""

from __future__ import annotations

import numpy as np

from ..geometry.tessellate import tessellate
from ..scene.model import Mesh, Scene
from .boxes import slab_intervals
from .meshes import MeshSet
from .objectfn import SECONDARY_T_MIN_REL, ObjectRays, trace_object
from .patches import PatchTracer
from .shading import Environment

# Grid resolution of the shadow proxy per NURBS patch (triangles are only shadow casters).
PROXY_GRID = 16


def build_environment(scene: Scene) -> Environment:
    """The scene's environment (meshes, lights, world), with every specular object's
    tessellated proxy as shadow caster when some light casts shadows."""
    occluder = None
    if any(light.shadows for light in scene.lights):
        occluder = MeshSet([_proxy_mesh(p) for obj in scene.objects for p in obj.patches])
    return Environment(scene, occluder=occluder)


class SceneTracer:
    """A scene of one specular object with its acceleration structures built once: the
    object's patch tracer and the environment (``build_environment``). A scene of several
    has one per object (``object_tracers``).

    ``tracer`` / ``env``: parts already built for this scene (a PatchTracer of an object with
    the same patches; an Environment of the same environment, lights and object), e.g. kept
    from the previous frame of an animation; built here when None."""

    def __init__(self, scene: Scene, tracer: PatchTracer | None = None,
                 env: Environment | None = None):
        self.scene = scene
        self.tracer = tracer if tracer is not None else PatchTracer(scene.object)
        self.env = env if env is not None else build_environment(scene)
        self.box_lo = self.tracer.lo - 1e-6 * self.tracer.diag
        self.box_hi = self.tracer.hi + 1e-6 * self.tracer.diag

    def object_function(self, origins, dirs, tmax=None, first=None,
                        record=None, fresnel_tree: bool = False) -> ObjectRays:
        """f of the rays (trace_object; ``first``: first hits already found, ``record``: an
        EventRecord to fill, see there); ``fresnel_tree``: a dielectric's Fresnel tree
        followed too, its other branches shaded by the environment (rendering, not baking)."""
        return trace_object(self.tracer, self.scene.object.material, origins, dirs,
                            self.scene.render.max_events, tmax=tmax, first=first,
                            record=record,
                            shade=self.env.shade_rays if fresnel_tree else None)

    def box_entry(self, origins, dirs):
        """Distance at which each ray enters the object's bounding box (inf if it misses)."""
        return slab_entry(origins, dirs, self.box_lo, self.box_hi)


def object_tracers(scene: Scene, env: Environment | None = None) -> list[SceneTracer]:
    """One SceneTracer per specular object of ``scene`` (its ``view``), sharing one
    environment (``env``, built here when None) whose shadows every object casts."""
    env = env if env is not None else build_environment(scene)
    return [SceneTracer(scene.view(i), env=env) for i in range(len(scene.objects))]


def slab_entry(o, d, lo, hi):
    """Entry distance (>= 0) of rays into the box [lo, hi]; inf where they miss it."""
    tnear, tfar = slab_intervals(o, d, lo, hi)
    tn = np.maximum(tnear.max(axis=1), 0.0)
    tf = tfar.min(axis=1)
    return np.where(tn <= tf, tn, np.inf)


# Camera-inside test: rays from the camera position in these fixed directions (unit after
# normalization; generic, so they avoid the axes, poles and seams of revolved samples) count
# their crossings of the object until they escape; an odd count for the majority means inside.
INSIDE_DIRS = np.array([[0.267, 0.534, 0.802], [-0.713, 0.297, -0.635], [0.439, -0.818, 0.371],
                        [-0.182, -0.391, -0.902], [0.858, 0.137, -0.495], [-0.577, 0.761, 0.296],
                        [0.093, -0.274, 0.957]])
INSIDE_DIRS = INSIDE_DIRS / np.linalg.norm(INSIDE_DIRS, axis=1)[:, None]
INSIDE_MAX_CROSSINGS = 64   # a direction still hitting after this many is left out of the vote


def point_inside(st: SceneTracer, p) -> bool:
    """Whether ``p`` lies inside the object (crossing parity along INSIDE_DIRS, majority vote);
    False without tracing when ``p`` is outside the object's bounding box."""
    p = np.asarray(p, dtype=np.float64)
    if np.any(p < st.box_lo) or np.any(p > st.box_hi):
        return False
    k = len(INSIDE_DIRS)
    o, d = np.tile(p, (k, 1)), INSIDE_DIRS.copy()
    crossings = np.zeros(k, np.int64)
    live = np.arange(k)
    tmin = SECONDARY_T_MIN_REL * st.tracer.diag
    for _ in range(INSIDE_MAX_CROSSINGS):
        h = st.tracer.intersect(o[live], d[live], tmin=np.full(len(live), tmin))
        live = live[h.hit]
        if len(live) == 0:
            break
        crossings[live] += 1
        o[live] = h.point[h.hit]
    decided = np.ones(k, bool)
    decided[live] = False
    return int((crossings[decided] % 2 == 1).sum()) * 2 > int(decided.sum())


def check_camera_outside(st: SceneTracer, cam) -> None:
    """ValueError when camera ``cam`` stands inside the object (no view is rendered from there;
    ``render`` and ``validate`` both refuse it)."""
    if point_inside(st, np.asarray(cam.matrix_world, dtype=np.float64)[:3, 3]):
        raise ValueError(f"camera {cam.name!r} is inside the object "
                         f"{st.scene.object.name!r}")


def _proxy_mesh(patch) -> Mesh:
    if patch.surface is None:
        return Mesh(name=patch.name, vertices=patch.vertices, triangles=patch.triangles, material="")
    v, t = tessellate(patch.surface, PROXY_GRID, PROXY_GRID)
    return Mesh(name=patch.name, vertices=v, triangles=t, material="")
