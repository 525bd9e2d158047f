"""The object function f: rays entering the object -> rays leaving it (paper, section 2).

A ray is followed through the chain of reflections/refractions its material calls for, up to
``max_events`` surface events; if it would still hit the object after that, f returns the
*null ray* (paper 5.2). Only the material's own effects are simulated:
  mirror      reflect at every hit; never refracts, no Fresnel
  glass       refract (IOR), total internal reflection where Snell has no solution; no Fresnel
  dielectric  at the first hit the ray splits: a reflected ray (weight = exact unpolarized
              Fresnel reflectance) and the transmitted chain, which then behaves as glass
On NURBS patches the medium is tracked by parity (the ray starts outside; each refraction
toggles inside / outside), so the result does not depend on which way the patch normals point.
A mesh patch says itself which side a ray is on: it enters the object through the front of a
triangle (its winding normal facing the ray) and leaves through the back, whatever it crossed
before (open meshes, as Blender's renderers treat them). On smooth meshes events use the
shading normal as ``eventnormal`` makes it sound.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scene.model import ObjectMaterial
from .eventnormal import event_normal, oriented, reflect, refract
from .patches import PatchHit, PatchTracer

# Secondary rays start on the surface (to ~1e-11 of the object size after Newton); hits nearer
# than this fraction of the object diagonal are the start point itself, not a new event.
SECONDARY_T_MIN_REL = 1e-7
# The ray-tree hash of a path (32 bits, FNV-1a style): from the seed, each event folds in the
# code 4 * patch + 4 + kind (kind 1: reflection or TIR, 2: refraction).
TREE_HASH_SEED = 2166136261
TREE_HASH_PRIME = 16777619
REFLECT, REFRACT = 1, 2
# Events after the first whose hits a path record keeps (EventRecord): the RI-Tree's samples
# carry them as seeds for solving a query ray exactly along a sample's path; 7 covers every
# path of the default max_events (8), trapped ones included.
RECORDED_EVENTS = 7


def tree_hash_step(h, patch, kind):
    """The running ray-tree hash ``h`` (uint64 array, 32-bit values) after an event of kind
    ``kind`` on patches ``patch`` (>= 0)."""
    code = np.asarray(patch).astype(np.uint64) * np.uint64(4) + np.uint64(4) \
        + np.asarray(kind).astype(np.uint64)
    return ((h ^ code) * np.uint64(TREE_HASH_PRIME)) & np.uint64(0xFFFFFFFF)


def one_reflection_hash(patch) -> np.ndarray:
    """(N,) uint32: the ray-tree hash of a path that reflects once off ``patch`` and leaves
    (negative patches: a value of no path that matters; callers mask misses)."""
    p = np.maximum(np.asarray(patch, np.int64), 0)
    return tree_hash_step(np.full(p.shape, TREE_HASH_SEED, np.uint64), p,
                          REFLECT).astype(np.uint32)


@dataclass
class ObjectRays:
    """f's outputs for N input rays. Miss: ``hit`` False, output = input ray, patch/cls -1.
    Null: ``null`` True, ``out_dir`` zero. ``normal`` is the unit first-hit normal flipped to
    face the incoming ray. ``refl_dir``/``fresnel`` are set only for dielectric objects
    (zero / 0 otherwise). ``t_first`` is the distance to the first hit (inf on a miss);
    ``uv`` its patch parameters normalized to the patch's domain [0, 1]^2 (barycentric on a
    mesh patch; zero on a miss, and where an RI-Tree interpolated the hit instead of finding
    it exactly)."""

    hit: np.ndarray
    null: np.ndarray
    out_origin: np.ndarray
    out_dir: np.ndarray
    t_first: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    patch: np.ndarray
    cls: np.ndarray
    events: np.ndarray
    refl_dir: np.ndarray
    fresnel: np.ndarray
    tree: np.ndarray
    uv: np.ndarray

    def take(self, idx) -> "ObjectRays":
        """The rows ``idx`` of every array."""
        return ObjectRays(**{k: v[idx] for k, v in self.__dict__.items()})


def fresnel_dielectric(cos_i, eta):
    """Exact unpolarized Fresnel reflectance, cos_i >= 0 the incidence cosine, eta = n1/n2."""
    sin_t2 = eta * eta * (1.0 - cos_i * cos_i)
    cos_t = np.sqrt(np.maximum(1.0 - sin_t2, 0.0))
    rs = (eta * cos_i - cos_t) / np.maximum(eta * cos_i + cos_t, 1e-300)
    rp = (cos_i - eta * cos_t) / np.maximum(cos_i + eta * cos_t, 1e-300)
    return np.where(sin_t2 >= 1.0, 1.0, 0.5 * (rs * rs + rp * rp))


@dataclass
class EventRecord:
    """The hits of events 1..RECORDED_EVENTS (after the first) of N traced rays: the patch
    (-1: no such event) and the normalized patch parameters (N, K, 2) in [0, 1]^2."""

    patch: np.ndarray
    uv: np.ndarray

    @classmethod
    def empty(cls, n: int) -> "EventRecord":
        return cls(patch=np.full((n, RECORDED_EVENTS), -1, np.int32),
                   uv=np.zeros((n, RECORDED_EVENTS, 2)))


def _first_hits(tracer, o, d, tmax, known):
    """tracer.intersect(o, d, tmax=tmax), reusing the hits ``known`` = (rows, PatchHit)."""
    if known is None or len(known[0]) == 0:
        return tracer.intersect(o, d, tmax=tmax)
    rows, hits = known
    rest = np.ones(len(o), bool)
    rest[rows] = False
    rest = np.flatnonzero(rest)
    tm = None if tmax is None else np.asarray(tmax, np.float64)[rest]
    found = tracer.intersect(o[rest], d[rest], tmax=tm)
    out = PatchHit(**{k: np.empty((len(o),) + v.shape[1:], v.dtype)
                      for k, v in found.__dict__.items()})
    out.put(rest, found)
    out.put(rows, hits)
    return out


def trace_object(tracer: PatchTracer, material: ObjectMaterial, origins, dirs,
                 max_events: int = 8, tmax=None, inside=None, first=None,
                 record: EventRecord | None = None) -> ObjectRays:
    """Apply f to N rays (origins (N,3), unit dirs (N,3)); ``tmax`` limits the first segment
    (something in the environment in front of the object). ``inside`` (N,) bool marks rays that
    start inside a refractive object (default: all start outside). ``first``: optional
    (rows, PatchHit), the first hits of rays ``rows`` already found by ``tracer.intersect``
    with the same tmax and every patch (the RI-Tree query's first-hit stage); the other rays'
    first hits are found here. ``record``: an EventRecord.empty(N) to fill with the hits of
    the events after the first."""
    o = np.array(origins, dtype=np.float64)
    d = np.array(dirs, dtype=np.float64)
    n = len(o)
    first = _first_hits(tracer, o, d, tmax, first)
    res = ObjectRays(hit=first.hit.copy(), null=np.zeros(n, bool), out_origin=o.copy(),
                     out_dir=d.copy(), t_first=first.t.copy(), point=first.point.copy(),
                     normal=first.normal.copy(), patch=first.patch.copy(), cls=first.cls.copy(),
                     events=np.zeros(n, np.int64), refl_dir=np.zeros((n, 3)), fresnel=np.zeros(n),
                     tree=np.zeros(n, np.uint32),
                     uv=tracer.normalized_uv(first.patch, first.u, first.v))
    res.normal, _, _ = oriented(d, first.normal, first.geo_normal)

    act = np.flatnonzero(first.hit)
    cur_o, cur_d = o[act], d[act]
    pts, patch = first.point[act], first.patch[act]
    nrm, geo, back = oriented(cur_d, first.normal[act], first.geo_normal[act])
    tree = np.full(len(act), TREE_HASH_SEED, dtype=np.uint64)   # the running ray-tree hash
    inside = np.zeros(len(act), bool) if inside is None else np.asarray(inside, bool)[act].copy()
    ior = float(material.ior)
    t_min2 = SECONDARY_T_MIN_REL * tracer.diag
    for event in range(max_events):
        res.events[act] += 1
        if material.kind == "mirror":
            new_d = reflect(cur_d, event_normal(cur_d, nrm, geo))
        else:
            on_mesh = tracer.is_mesh[patch]
            inside = np.where(on_mesh, back, inside)
            eta = np.where(inside, ior, 1.0 / ior)
            new_d, tir = refract(cur_d, event_normal(cur_d, nrm, geo, eta), eta)
            if event == 0 and material.kind == "dielectric":
                cos_i = -np.einsum("ij,ij->i", cur_d, nrm)
                res.fresnel[act] = fresnel_dielectric(cos_i, eta)
                res.refl_dir[act] = reflect(cur_d, event_normal(cur_d, nrm, geo))
            inside ^= ~tir
        kind = REFLECT if material.kind == "mirror" else np.where(tir, REFLECT, REFRACT)
        tree = tree_hash_step(tree, patch, kind)
        cur_o = pts
        cur_d = new_d
        nxt = tracer.intersect(cur_o, cur_d, tmin=np.full(len(act), t_min2))
        esc = ~nxt.hit
        res.out_origin[act[esc]] = cur_o[esc]
        res.out_dir[act[esc]] = cur_d[esc]
        res.tree[act[esc]] = tree[esc]
        keep = ~esc
        act, cur_o, cur_d, inside, tree = act[keep], cur_o[keep], cur_d[keep], inside[keep], tree[keep]
        pts, patch = nxt.point[keep], nxt.patch[keep]
        if record is not None and event < min(RECORDED_EVENTS, max_events - 1):
            record.patch[act, event] = patch
            record.uv[act, event] = tracer.normalized_uv(patch, nxt.u[keep], nxt.v[keep])
        nrm, geo, back = oriented(cur_d, nxt.normal[keep], nxt.geo_normal[keep])
        if len(act) == 0:
            break
    # still hitting after max_events: trapped -> null ray
    res.null[act] = True
    res.tree[act] = tree
    res.out_origin[act] = pts
    res.out_dir[act] = 0.0
    return res
