"""The object function f: rays entering the object -> rays leaving it (paper, section 2).

A ray is followed through the chain of reflections/refractions its material calls for, up to
``max_events`` surface events; if it would still hit the object after that, f returns the
*null ray* (paper 5.2). Only the material's own effects are simulated:
  mirror      reflect at every hit; never refracts, no Fresnel
  glass       refract (IOR), total internal reflection where Snell has no solution; no Fresnel
  dielectric  at the first hit the ray splits: a reflected ray (weight = exact unpolarized
              Fresnel reflectance) and the transmitted chain, which then behaves as glass.
              Traced with a ``shade`` (the renderers' exact tracing), every later crossing
              splits too, as Blender's renderers weigh reflection and refraction at each one:
              the refracted (or totally reflected) chain stays f's one output ray, carrying
              ``out_weight`` of the light that entered, and the reflections it leaves behind
              are followed as a full Fresnel tree, bounded by FRESNEL_MIN_WEIGHT and
              ``max_events``, whose leaving rays' colour is summed into ``branch_color``
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
# A recorded hit on a mesh patch keeps its triangle t as its two normalized parameters
# (t mod TRI_BASE, t div TRI_BASE) / TRI_LEVELS: exact through the cache's 16-bit parameter
# codes (ritree.codec), and what solving along the path starts from (trace.meshwalk).
TRI_BASE = 1 << 16
TRI_LEVELS = TRI_BASE - 1
# A dielectric's Fresnel tree follows a branch while it carries at least this fraction of the
# light that entered the object (the weight of the chain after the first refraction): on
# smooth glass Suzanne 1e-2 renders within 0.05 dB of 1e-4's tree with half its rays.
FRESNEL_MIN_WEIGHT = 1e-2


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
    it exactly). A dielectric traced with its Fresnel tree: ``out_weight`` the share of the
    light past the first refraction that the output ray carries, ``branch_color`` (N, 3) the
    colour the tree's other leaving rays carry on the same scale; elsewhere 1 and 0 (the
    output ray carries all of it)."""

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
    out_weight: np.ndarray
    branch_color: np.ndarray

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


def tri_params(tri) -> np.ndarray:
    """(N, 2) the normalized parameters a recorded mesh hit on triangles ``tri`` (N,) keeps."""
    t = np.asarray(tri, np.int64)
    return np.stack([t % TRI_BASE, t // TRI_BASE], axis=1) / TRI_LEVELS


def params_tri(uv) -> np.ndarray:
    """(N,) int64 the triangles of recorded mesh hits' normalized parameters ``uv`` (N, 2)."""
    k = np.rint(np.asarray(uv, np.float64) * TRI_LEVELS).astype(np.int64)
    return k[:, 0] + TRI_BASE * k[:, 1]


def recorded_params(tracer, patch, hit) -> np.ndarray:
    """(N, 2) what a path record keeps of hits ``hit`` (PatchHit) on patches ``patch``: the
    normalized patch parameters on NURBS, the triangle (``tri_params``) on meshes."""
    uv = tracer.normalized_uv(patch, hit.u, hit.v)
    mesh = np.flatnonzero((patch >= 0) & tracer.is_mesh[np.maximum(patch, 0)])
    uv[mesh] = tri_params(hit.tri[mesh])
    return uv


@dataclass
class EventRecord:
    """The hits of events 1..RECORDED_EVENTS (after the first) of N traced rays: the patch
    (-1: no such event) and its ``recorded_params`` (N, K, 2) in [0, 1]^2; and those of the
    first hit (``first_uv`` (N, 2), zero on a miss)."""

    patch: np.ndarray
    uv: np.ndarray
    first_uv: np.ndarray

    @classmethod
    def empty(cls, n: int) -> "EventRecord":
        return cls(patch=np.full((n, RECORDED_EVENTS), -1, np.int32),
                   uv=np.zeros((n, RECORDED_EVENTS, 2)), first_uv=np.zeros((n, 2)))


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
                 record: EventRecord | None = None, shade=None) -> ObjectRays:
    """Apply f to N rays (origins (N,3), unit dirs (N,3)); ``tmax`` limits the first segment
    (something in the environment in front of the object). ``inside`` (N,) bool marks rays that
    start inside a refractive object (default: all start outside). ``first``: optional
    (rows, PatchHit), the first hits of rays ``rows`` already found by ``tracer.intersect``
    with the same tmax and every patch (the RI-Tree query's first-hit stage); the other rays'
    first hits are found here. ``record``: an EventRecord.empty(N) to fill with the hits of
    the events after the first. ``shade``: (origins, dirs) -> (M, 3) colour of rays leaving
    the object; given, a dielectric's Fresnel tree is followed (module docstring)."""
    o = np.array(origins, dtype=np.float64)
    d = np.array(dirs, dtype=np.float64)
    n = len(o)
    first = _first_hits(tracer, o, d, tmax, first)
    res = ObjectRays(hit=first.hit.copy(), null=np.zeros(n, bool), out_origin=o.copy(),
                     out_dir=d.copy(), t_first=first.t.copy(), point=first.point.copy(),
                     normal=first.normal.copy(), patch=first.patch.copy(), cls=first.cls.copy(),
                     events=np.zeros(n, np.int64), refl_dir=np.zeros((n, 3)), fresnel=np.zeros(n),
                     tree=np.zeros(n, np.uint32),
                     uv=tracer.normalized_uv(first.patch, first.u, first.v),
                     out_weight=np.ones(n), branch_color=np.zeros((n, 3)))
    split = shade is not None and material.kind == "dielectric"
    branches = FresnelBranches()
    res.normal, _, _ = oriented(d, first.normal, first.geo_normal)
    if record is not None:
        record.first_uv[:] = recorded_params(tracer, first.patch, first)

    act = np.flatnonzero(first.hit)
    cur_o, cur_d = o[act], d[act]
    pts, patch = first.point[act], first.patch[act]
    nrm, geo, back = oriented(cur_d, first.normal[act], first.geo_normal[act])
    tree = np.full(len(act), TREE_HASH_SEED, dtype=np.uint64)   # the running ray-tree hash
    inside = np.zeros(len(act), bool) if inside is None else np.asarray(inside, bool)[act].copy()
    t_min2 = SECONDARY_T_MIN_REL * tracer.diag
    for event in range(max_events):
        res.events[act] += 1
        ev = surface_event(tracer, material, cur_d, nrm, geo, back, patch, inside)
        new_d, inside = ev.out_dir, ev.inside_after
        if split and event > 0:
            branches.split(act, pts, cur_d, nrm, geo, ev.n_t, ev.eta, ev.tir, ev.inside,
                           event + 1, res.out_weight)
        if event == 0 and material.kind == "dielectric":
            cos_i = -np.einsum("ij,ij->i", cur_d, nrm)
            res.fresnel[act] = fresnel_dielectric(cos_i, ev.eta)
            res.refl_dir[act] = reflect(cur_d, event_normal(cur_d, nrm, geo))
        tree = tree_hash_step(tree, patch, ev.kind)
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
            record.uv[act, event] = recorded_params(tracer, patch, nxt.take(keep))
        nrm, geo, back = oriented(cur_d, nxt.normal[keep], nxt.geo_normal[keep])
        if len(act) == 0:
            break
    # still hitting after max_events: trapped -> null ray
    res.null[act] = True
    res.tree[act] = tree
    res.out_origin[act] = pts
    res.out_dir[act] = 0.0
    if split:
        res.branch_color = branches.trace(tracer, material, shade, n, max_events)
    return res


@dataclass
class SurfaceEvent:
    """One reflection or refraction of N rays: the direction leaving, the event kind (REFLECT
    or REFRACT), whether it was a total internal reflection, the side the ray met (``inside``:
    in the glass) and the side it leaves on (``inside_after``), the refraction normal ``n_t``
    and ``eta`` = n_from / n_to (glass and dielectric; None on a mirror)."""

    out_dir: np.ndarray
    kind: np.ndarray
    tir: np.ndarray
    inside: np.ndarray
    inside_after: np.ndarray
    n_t: np.ndarray | None
    eta: np.ndarray | None


def surface_event(tracer, material: ObjectMaterial, d, nrm, geo, back, patch,
                  inside) -> SurfaceEvent:
    """The event of rays ``d`` (N, 3) meeting patches ``patch`` with ``oriented`` shading
    ``nrm`` and geometric ``geo`` normals (``back``: met from behind): a mirror reflects; glass
    refracts (total internal reflection past the critical angle), in the glass where the ray
    met a mesh's back (whatever it crossed before) or, on NURBS, by the parity ``inside``."""
    n = len(d)
    if material.kind == "mirror":
        none = np.zeros(n, bool)
        return SurfaceEvent(reflect(d, event_normal(d, nrm, geo)), np.full(n, REFLECT), none,
                            inside, inside, None, None)
    inside = np.where(tracer.is_mesh[patch], back, inside)
    eta = np.where(inside, float(material.ior), 1.0 / float(material.ior))
    n_t = event_normal(d, nrm, geo, eta)
    out, tir = refract(d, n_t, eta)
    return SurfaceEvent(out, np.where(tir, REFLECT, REFRACT), tir, inside, inside ^ ~tir, n_t,
                        eta)


class FresnelBranches:
    """The reflections a dielectric's output chain leaves behind at its crossings after the
    first, and the Fresnel tree that follows them (trace_object, and the RI-Tree query's
    chains solved along a sample's path)."""

    def __init__(self):
        self.parts = []

    def split(self, rows, pts, d, nrm, geo, n_t, eta, tir, inside, used, out_weight):
        """At the crossing ``pts`` of the chains of rays ``rows`` (arriving along ``d``,
        oriented normals ``nrm`` / ``geo``, refraction normal ``n_t``, ``eta``, ``tir``, on the
        side ``inside``, after ``used`` events): the chain keeps 1 - F of its weight
        (``out_weight``, in place), a reflection of weight F is kept where it carries at least
        FRESNEL_MIN_WEIGHT. Total internal reflection is the chain itself (F = 1)."""
        f = np.where(tir, 0.0, fresnel_dielectric(-np.einsum("ij,ij->i", d, n_t), eta))
        w = out_weight[rows] * f
        out_weight[rows] -= w
        k = np.flatnonzero(w >= FRESNEL_MIN_WEIGHT)
        if len(k):
            self.parts.append((rows[k], pts[k], reflect(d[k], event_normal(d[k], nrm[k], geo[k])),
                               w[k], inside[k], np.full(len(k), used)))

    def trace(self, tracer, material, shade, n: int, max_events: int,
              keep=None) -> np.ndarray:
        """(n, 3): the colour the branches' leaving rays carry, summed per input ray (only
        those ``keep`` (n,) bool marks, if given): at each crossing a branch splits into a
        reflection (weight F) and a refraction (1 - F; none past the critical angle), each
        followed while its weight is at least FRESNEL_MIN_WEIGHT; a branch still hitting after
        ``max_events`` events is trapped and carries nothing."""
        color = np.zeros((n, 3))
        if not self.parts:
            return color
        rows, o, d, w, inside, used = (np.concatenate(x) for x in zip(*self.parts))
        if keep is not None:
            k = np.flatnonzero(keep[rows])
            rows, o, d, w, inside, used = rows[k], o[k], d[k], w[k], inside[k], used[k]
        ior, t_min2 = float(material.ior), SECONDARY_T_MIN_REL * tracer.diag
        while len(rows):
            h = tracer.intersect(o, d, tmin=np.full(len(o), t_min2))
            esc = np.flatnonzero(~h.hit)
            np.add.at(color, rows[esc], w[esc, None] * shade(o[esc], d[esc]))
            k = np.flatnonzero(h.hit & (used < max_events))
            rows, d, w, inside, used = rows[k], d[k], w[k], inside[k], used[k] + 1
            o, h = h.point[k], h.take(k)
            nrm, geo, back = oriented(d, h.normal, h.geo_normal)
            inside = np.where(tracer.is_mesh[h.patch], back, inside)
            eta = np.where(inside, ior, 1.0 / ior)
            n_t = event_normal(d, nrm, geo, eta)
            t_d, tir = refract(d, n_t, eta)
            f = np.where(tir, 1.0, fresnel_dielectric(-np.einsum("ij,ij->i", d, n_t), eta))
            r_d = np.where(tir[:, None], t_d, reflect(d, event_normal(d, nrm, geo)))
            kr = np.flatnonzero(w * f >= FRESNEL_MIN_WEIGHT)
            kt = np.flatnonzero(~tir & (w * (1.0 - f) >= FRESNEL_MIN_WEIGHT))
            rows = np.concatenate([rows[kr], rows[kt]])
            o = np.concatenate([o[kr], o[kt]])
            d = np.concatenate([r_d[kr], t_d[kt]])
            w = np.concatenate([(w * f)[kr], (w * (1.0 - f))[kt]])
            inside = np.concatenate([inside[kr], ~inside[kt]])
            used = np.concatenate([used[kr], used[kt]])
        return color
