"""Writing interpolated answers into the batch's result: the hidden rule (something in front of
the interpolated hit), the normal facing the ray, mirror rays answered from the hit
(QueryOptions.mirror_rays), a dielectric's reflected ray and Fresnel weight."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from ...trace.objectfn import fresnel_dielectric, reflect
from ...trace.patches import T_MIN_REL, PatchHit
from ...trace.polish import Seeds, keep_near, polish_hits
from ..answers import MISS
from .options import MIRROR_BLEND, MIRROR_NEWTON

# The Newton hit is kept only near the interpolated one: within this distance (relative to the
# object's box diagonal; interpolated hits where the tolerance answers are ~1e-4 off) and with
# a normal within this angle of the interpolated normal (a grazing ray's second root, where it
# leaves the surface, has a normal facing the other way); otherwise the ray keeps the
# interpolated normal's answer.
NEWTON_MAX_MOVE_REL = 1e-2
NEWTON_MAX_TURN_DEG = 10.0


@dataclass
class Blended:
    """Interpolated answers of query rays ``rows`` (n): output ray (oo, od unit), first hit pt
    and unit normal nm (object space), class and representative patch."""

    rows: np.ndarray                   # (n,) query rays
    oo: np.ndarray                     # (n, 3)
    od: np.ndarray                     # (n, 3)
    pt: np.ndarray                     # (n, 3)
    nm: np.ndarray                     # (n, 3)
    cls: np.ndarray                    # (n,)
    patch: np.ndarray                  # (n,)
    null: bool = False                 # answered null (trapped)
    mirror: np.ndarray | None = None   # (n,) MIRROR_*: how mirror rays are answered
    uvn: np.ndarray | None = None      # (n, 2) interpolated normalized patch parameters
    alt_uvn: np.ndarray | None = None  # (n, 2) those of the heaviest sample

    def take(self, k) -> "Blended":
        """The rows ``k`` of every per-ray field."""
        per_ray = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "null"}
        return Blended(null=self.null,
                       **{n: None if v is None else v[k] for n, v in per_ray.items()})


def patch_of(q, ids, weights) -> np.ndarray:
    """The patch of the heaviest interpolant (a representative patch id); ``ids`` (n, K)
    the sample ids the (n, K) weights refer to."""
    best = np.argmax(np.abs(weights), axis=1)
    return q.table.patch[ids[np.arange(len(ids)), best]].astype(np.int64)


def fill(q, b, bl: Blended) -> None:
    """Write the interpolated answers ``bl`` into ``b.res``. Mirror rays whose samples all
    reflect once (``bl.mirror``) are answered as the tracer answers such a ray from its hit -
    leaving from pt along the query direction reflected about nm - instead of by the blended
    output ray; with MIRROR_NEWTON the hit and normal are first replaced by exact ones on
    ``bl.patch`` (``exact_hits``, where kept)."""
    dd = b.d[bl.rows]
    t_first = np.einsum("ij,ij->i", bl.pt - b.o[bl.rows], dd)
    # the environment is in front of the interpolated hit: the object is not seen
    hidden = t_first >= b.tmax[bl.rows]
    if hidden.any():
        b.ans[bl.rows[hidden]] = MISS
        k = ~hidden
        bl, dd, t_first = bl.take(k), dd[k], t_first[k]
    flip = np.einsum("ij,ij->i", bl.nm, dd) > 0
    bl.nm = np.where(flip[:, None], -bl.nm, bl.nm)
    if bl.mirror is not None and bl.mirror.any():
        t_first = mirror_answers(q, b, bl, dd, t_first)
    res, rows = b.res, bl.rows
    res.hit[rows] = True
    res.null[rows] = bl.null
    res.out_origin[rows] = bl.oo
    res.out_dir[rows] = bl.od
    res.point[rows] = bl.pt
    res.normal[rows] = bl.nm
    res.t_first[rows] = t_first
    res.cls[rows] = bl.cls
    res.patch[rows] = bl.patch
    if q.material.kind == "dielectric":
        cos_i = -np.einsum("ij,ij->i", dd, bl.nm)
        res.fresnel[rows] = fresnel_dielectric(cos_i, np.full(len(rows), 1.0 / q.material.ior))
        res.refl_dir[rows] = reflect(dd, bl.nm)


def mirror_answers(q, b, bl: Blended, dd, t_first) -> np.ndarray:
    """Answer the mirror rays of ``bl`` (directions ``dd``, first-hit distances ``t_first``)
    from their hit: Newton's exact one where MIRROR_NEWTON finds it. Returns t_first."""
    newton = np.flatnonzero(bl.mirror == MIRROR_NEWTON)
    if len(newton):
        rows = bl.rows
        bl.pt, bl.nm, t_first = bl.pt.copy(), bl.nm.copy(), t_first.copy()
        with b.clock("newton"):
            h = exact_hits(q, b, rows[newton], dd[newton],
                           Seeds(bl.patch[newton], bl.uvn[newton], bl.pt[newton],
                                 bl.nm[newton], bl.alt_uvn[newton]))
        k = newton[h.hit]
        n_new = h.normal[h.hit]
        bl.pt[k], t_first[k] = h.point[h.hit], h.t[h.hit]
        bl.nm[k] = np.where((np.einsum("ij,ij->i", n_new, dd[k]) > 0)[:, None], -n_new, n_new)
        b.exact_mirror_hits += len(k)
        b.newton_ok[rows[k]] = True
        b.res.uv[rows[k]] = q.st.tracer.normalized_uv(h.patch[h.hit], h.u[h.hit], h.v[h.hit])
    m = bl.mirror != MIRROR_BLEND
    bl.od = np.where(m[:, None], reflect(dd, bl.nm), bl.od)
    bl.oo = np.where(m[:, None], bl.pt, bl.oo)
    return t_first


def exact_hits(q, b, rows, d, seeds: Seeds) -> PatchHit:
    """Exact hits of query rays ``rows`` (directions ``d``) on their seeds' patches near the
    seeds (NEWTON_MAX_MOVE_REL, NEWTON_MAX_TURN_DEG): where the query found the ray's exact
    first hit already, that hit if it is on the seed's patch (none if on another), else
    Newton's from the seeds."""
    lim = NEWTON_MAX_MOVE_REL * q.tree.diag, np.cos(np.radians(NEWTON_MAX_TURN_DEG))
    h = PatchHit.misses(len(rows))
    got = b.known.of(rows)
    rest = np.ones(len(rows), bool)
    if got is not None:
        k, kh = got
        rest[k] = False
        same = kh.hit & (kh.patch == seeds.patch[k])
        h.put(k[same], kh.take(np.flatnonzero(same)))
        keep_near(h, d, seeds, *lim)
    r = np.flatnonzero(rest)
    if len(r):
        sub = Seeds(*(None if x is None else x[r] for x in
                      (seeds.patch, seeds.uvn, seeds.point, seeds.normal, seeds.alt_uvn)))
        floor = T_MIN_REL * q.st.tracer.diag
        h.put(r, polish_hits(q.st.tracer, b.o[rows[r]], d[r], sub, *lim,
                             np.full(len(r), floor), b.tmax[rows[r]]))
    return h
