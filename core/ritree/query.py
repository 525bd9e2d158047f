"""Answering rays through the RI-Tree (paper 4.1, 4.2, 4.3, 5.1-5.4).

For each query ray that enters the padded box: its entry point Q and face give the viewpoint
cell (four viewpoints, bilinear weights); its direction gives the hemicube slot and (u, v);
the four direction trees give four leaf cells (DQs), 16 samples in all. Then
- policy "ri" (the paper): the two-patch condition over the 16 class ids; with two classes
  the exact first hit against only the <= 16 candidate patches picks the class; usable samples
  are those of that class that are not null; each DQ interpolates bilinearly (4 usable),
  barycentrically (3) or from its extra samples (one/two-interpolant cells); the QNode level
  combines the DQs the same way; extrapolation and the pairwise angle/distance thresholds
  apply; anything short of three interpolants at either level is traced exactly - except
  where counting the null samples of the class as usable gives an interpolation whose
  interpolants are all null: that ray may be answered null (``null_interp``; off by default,
  as in the paper: a trapped region can hide an exit no sample shows, see QueryOptions).
- policy "raytree" (Bala et al., for comparison): interpolate only when all 16 samples have
  identical ray trees; trace otherwise.
Interpolated first-hit points and normals feed local illumination; a dielectric's reflected
ray and Fresnel weight come from the interpolated normal. A mirror ray whose usable samples
all reflect once is answered as the exact tracer answers it from its hit: the query direction
reflected about its normal (``mirror_rays``; the paper blends the output rays). By default
("newton"), where those samples share one NURBS patch, the hit and normal are the exact ones
Newton's method finds on it from the interpolated patch parameters (trace.polish), and such a
ray outside the tolerance is answered so too where the bake saw no path change there;
"reflect" uses the interpolated hit and normal.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, replace

import numpy as np

from ..rowops import all_last, any_last, norm3
from ..trace.objectfn import ObjectRays, fresnel_dielectric, reflect
from ..trace.patches import T_MIN_REL, PatchHit
from ..trace.polish import Seeds, keep_near, polish_hits
from .extras import extra_weights
from .interp import (BILINEAR, EXTRA, EXTRAPOLATED, FAIL, TRIANGLE, UNIT_CORNERS,
                     bilinear_weights, cell_weights, drop_outlier, drop_outlier_units, far_pairs,
                     may_have_far_pairs)
from .locate import Located, locate
from .tree import BOUNDARY, PATH_CHANGE

# Rays per block of the blend stage: bounds its (rays, 24, 14) float32 sample gather to 44 MB.
BLEND_BLOCK = 1 << 15
# Interpolated unit vectors shorter than this before normalization (opposed samples) are not
# trusted: the ray is traced.
MIN_BLEND_NORM = 1e-3
# How a mirror ray is answered (QueryOptions.mirror_rays "interpolate", "reflect", "newton"): the
# blended output ray (the paper);
# the query direction reflected about the interpolated normal at the interpolated hit, for
# units whose usable samples all reflect once; and, where those samples also share one NURBS
# patch, reflected at the exact hit that Newton finds from the interpolated patch parameters.
MIRROR_BLEND, MIRROR_NORMAL, MIRROR_NEWTON = 0, 1, 2
MIRROR_RAYS = ("newton", "reflect", "interpolate")
# The Newton hit is kept only near the interpolated one: within this distance (relative to the
# object's box diagonal; interpolated hits where the tolerance answers are ~1e-4 off) and with
# a normal within this angle of the interpolated normal (a grazing ray's second root, where it
# leaves the surface, has a normal facing the other way); otherwise the ray keeps the
# interpolated normal's answer.
NEWTON_MAX_MOVE_REL = 1e-2
NEWTON_MAX_TURN_DEG = 10.0

# Answer codes: how each ray was answered.
# FULL..EXTRAPOLATED_S interpolate an output ray; NULL_S answers the null ray (trapped: every
# interpolant of the query's class is null).
MISS, FULL, REDUCED, EXTRA_S, EXTRAPOLATED_S, TRACED, OUTSIDE, NULL_S = 0, 1, 2, 3, 4, 5, 6, 7
ANSWER_NAMES = ("miss", "interpolated_16", "interpolated_reduced", "interpolated_extra",
                "interpolated_extrapolated", "traced", "traced_outside_tree", "interpolated_null")
# Why a ray was traced.
WHY_CLASSES, WHY_USABLE, WHY_THRESHOLD, WHY_RAYTREE, WHY_BLEND = 1, 2, 3, 4, 5
WHY_TOLERANCE, WHY_UNSAMPLED, WHY_PATH = 6, 7, 8
WHY_NAMES = ("", "more_than_two_classes", "too_few_usable", "threshold", "raytree_mismatch",
             "degenerate_blend", "tolerance", "unsampled_hit", "path_change")


# The default render-time tolerance (degrees): on the sample scenes' close views it keeps p99
# errors under 1.4 degrees and maxima under 2.6, and is faster than the paper's 20-degree angle
# threshold, the previous default, on four of the five (vase_glass: 1.83x against 1.86x, for a
# p99 of 1.06 instead of 5.75 degrees; docs/benchmarks.md, the Pareto plots).
DEFAULT_MAX_ERROR_DEG = 2.0


@dataclass
class QueryOptions:
    """Render-time choices (no re-bake needed). Angles in degrees, distances relative to the
    object's box diagonal; None switches a rule off. The default is the baked-error tolerance;
    the paper's thresholds are options."""

    policy: str = "ri"                 # "ri" (the paper) or "raytree" (Bala et al.)
    extrapolation: float | None = None  # allowed barycentric distance below 0 (None: off)
    angle_deg: float | None = None     # pairwise angle threshold between interpolants
    distance: float | None = None      # pairwise distance threshold between output origins
    threshold_on: str = "samples"      # compare all interpolated samples (the paper), or the
                                       # four viewpoints' "intermediate" rays f*(R_VP)
    threshold_leaves: str = "all"      # samples mode: compare the samples of "all" direction
                                       # leaves, or of the "unverified" ones only (at the maximum
                                       # depth: a shallower leaf passed the bake's midpoint test)
    null_interp: bool = False          # True: a ray whose interpolants (class rules, null
                                       # rays counted) are all null is null; False: traced (the
                                       # paper). Off by default: on vase_glass close 2 of 281
                                       # such rays leave after 7 events between 16 samples,
                                       # leaves and test rays all trapped along one path
    max_error_deg: float | None = DEFAULT_MAX_ERROR_DEG  # degrees ("ri" policy): interpolate
                                       # only where the errors the bake measured in the ray's
                                       # four leaves and its viewpoint cell are within it, else
                                       # trace (None: off)
    fallback_angle_deg: float | None = 20.0  # a tree whose bake measured no viewpoint cell
                                       # (--full, or a cell-list region) cannot bound its error:
                                       # there the tolerance gives way to the paper's rules with
                                       # this angle threshold (unless angle_deg is set; None:
                                       # keep the tolerance, which then traces every ray)
    path_identity: bool = False        # trace rays whose usable samples differ in ray-tree hash
                                       # or whose leaves / cell the bake saw change path
    mirror_rays: str = "newton"        # mirrors ("ri" policy), a ray whose usable samples all
                                       # reflect once: "reflect" leaves along the query
                                       # direction reflected about the interpolated normal,
                                       # from the interpolated hit point; "newton" (where those
                                       # samples share one NURBS patch) the same at the exact
                                       # hit Newton finds from the interpolated patch
                                       # parameters; "interpolate": the blended output ray (paper)

    def validate(self) -> "QueryOptions":
        if self.policy not in ("ri", "raytree"):
            raise ValueError(f"policy must be 'ri' or 'raytree', got {self.policy!r}")
        if self.threshold_on not in ("intermediate", "samples"):
            raise ValueError("threshold_on must be 'intermediate' or 'samples', "
                             f"got {self.threshold_on!r}")
        if self.threshold_leaves not in ("unverified", "all"):
            raise ValueError("threshold_leaves must be 'unverified' or 'all', "
                             f"got {self.threshold_leaves!r}")
        if self.mirror_rays not in MIRROR_RAYS:
            raise ValueError(f"mirror_rays must be one of {MIRROR_RAYS}, got {self.mirror_rays!r}")
        for name in ("extrapolation", "angle_deg", "distance", "max_error_deg",
                     "fallback_angle_deg"):
            val = getattr(self, name)
            if val is not None and not (np.isfinite(val) and val >= 0):
                raise ValueError(f"{name} must be None or a finite number >= 0, got {val!r}")
        return self


class StageClock:
    """CPU seconds (this process's CPU clock) spent per named stage of a query. A stage run
    inside another is that stage's time only, not the outer one's."""

    def __init__(self):
        self.cpu: dict[str, float] = {}
        self._inner: list[float] = []      # per open stage: the time of stages run inside it

    @contextmanager
    def __call__(self, name: str):
        t0 = time.process_time()
        self._inner.append(0.0)
        try:
            yield
        finally:
            spent = time.process_time() - t0
            inner = self._inner.pop()
            self.cpu[name] = self.cpu.get(name, 0.0) + spent - inner
            if self._inner:
                self._inner[-1] += spent


class KnownHits:
    """Exact first hits (against every patch, within the ray's tmax) the query found for some
    of its N rays, so that nothing searches them again."""

    def __init__(self, n: int):
        self.pos = np.full(n, -1, np.int64)       # row of each ray in the hits, -1: none
        self.pieces: list[PatchHit] = []

    def add(self, rays, hit: PatchHit) -> None:
        """Record the hits of rays ``rays`` (none recorded yet)."""
        self.pos[rays] = self._count() + np.arange(len(rays))
        self.pieces.append(hit)

    def _count(self) -> int:
        return sum(len(h.t) for h in self.pieces)

    def _all(self) -> PatchHit:
        if len(self.pieces) > 1:
            self.pieces = [PatchHit(**{f: np.concatenate([getattr(h, f) for h in self.pieces])
                                       for f in self.pieces[0].__dict__})]
        return self.pieces[0]

    def hit(self, rays) -> np.ndarray:
        """Whether each of ``rays`` (all recorded) hits the object."""
        return self._all().hit[self.pos[rays]]

    def of(self, rays):
        """(positions within ``rays`` that have a recorded hit, their PatchHit), or None."""
        p = self.pos[rays]
        k = np.flatnonzero(p >= 0)
        return (k, self._all().take(p[k])) if len(k) else None


# Stages whose time is exact tracing the query calls (the rest is the query's own work):
# "newton" is the tracer's Newton step on known patches (mirror_rays "newton").
TRACING_STAGES = ("first_hits", "trace", "newton")


def group_rows(keys: np.ndarray):
    """Group the rows of an (m, k) integer array: (group id of each row (m,), index of the
    first row of each group (G,)); groups are numbered in sorted key order. Runs of equal
    consecutive rows (neighbouring pixels share their sample set) are sorted as one."""
    m = len(keys)
    if m == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    head = np.ones(m, bool)
    head[1:] = any_last(keys[1:] != keys[:-1])
    heads = np.flatnonzero(head)
    run_of = np.cumsum(head) - 1
    hk = keys[heads]
    sk, k = hk, hk.shape[1]
    if k > 1 and hk.min() >= 0 and hk.max() < 1 << 31:
        # pairs of columns as one int64 (order-preserving): half the sort keys
        h = hk.astype(np.int64)
        sk = np.concatenate([(h[:, 0:k - 1:2] << 32) | h[:, 1:k:2], h[:, k - k % 2:]], axis=1)
    order = np.argsort(sk[:, 0], kind="stable") if sk.shape[1] == 1 else np.lexsort(sk.T[::-1])
    sk = sk[order]
    new = np.ones(len(heads), bool)
    new[1:] = any_last(sk[1:] != sk[:-1])
    group = np.empty(len(heads), np.int64)
    group[order] = np.cumsum(new) - 1
    return group[run_of], heads[order[new]]


def blend(vals, rows, w) -> np.ndarray:
    """Weighted sums ``w`` (n, K) of the items ``vals[rows]`` (rows (n,) into vals (G, K, C))
    -> (n, C) float64, in blocks of BLEND_BLOCK rays (float32 gather and sums)."""
    n = len(rows)
    out = np.empty((n, vals.shape[-1]))
    for a in range(0, n, BLEND_BLOCK):
        b = min(a + BLEND_BLOCK, n)
        out[a:b] = np.matmul(w[a:b, None, :].astype(np.float32, copy=False),
                             vals.take(rows[a:b], axis=0))[:, 0]
    return out


def far_bits(far) -> np.ndarray:
    """Far-pair matrices (F, 32, 32) bool as bit rows (F, 32) uint32: bit j of row i."""
    return np.packbits(far, axis=2, bitorder="little").view("<u4")[..., 0].astype(np.uint32)


# Item of each (DQ k, slot j) of a ray by default: the DQ's corners 4k + j, and for slots 4, 5
# the DQ's first two extras 16 + 4k, 16 + 4k + 1 (weight 0 unless the DQ uses its extras, which
# then name the two they use). The items of one ray are distinct.
DEFAULT_ITEMS = np.array([[4 * k + j for j in range(4)] + [16 + 4 * k, 16 + 4 * k + 1]
                          for k in range(4)])


@dataclass
class SetItems:
    """What a sample set can interpolate from: the 16 corners (item 4k + j: DQ k, corner j)
    and each leaf's four extras (item 16 + 4k + e; id 0 and unusable where the leaf has
    none). Their values are RITree.blend_vals rows (output directions times the perspective
    weight), so one weighted sum blends every column."""

    ids: np.ndarray          # (S, 32) sample ids
    corner_vals: np.ndarray  # (S, 16, 14) float32: items 0-15
    extra_vals: np.ndarray   # (S, 16, 14) float32: items 16-31
    has_extra: np.ndarray    # (S, 4) the leaf stores extras

    @classmethod
    def of(cls, tree, s_leaf, s_ids) -> "SetItems":
        s = len(s_leaf)
        ex_ids = np.zeros((s, 16), np.int64)
        has = np.zeros((s, 4), bool)
        if len(tree.ex_node):
            pos = np.minimum(np.searchsorted(tree.ex_node, s_leaf), len(tree.ex_node) - 1)
            has = tree.ex_node[pos] == s_leaf
            ex_ids = np.where(has[..., None], tree.ex_ids[pos], 0).reshape(s, 16)
        vals = tree.blend_vals
        return cls(ids=np.concatenate([s_ids, ex_ids], axis=1), corner_vals=vals[s_ids],
                   extra_vals=vals[ex_ids], has_extra=has)

    def item_vals(self, sets, item) -> np.ndarray:
        """Values (..., 14) of items ``item`` (0-31) of sets ``sets`` (broadcast together)."""
        c = self.corner_vals[sets, np.minimum(item, 15)]
        e = self.extra_vals[sets, np.maximum(item - 16, 0)]
        return np.where((item < 16)[..., None], c, e)


class TreeQuery:
    """Answers batches of rays with a baked tree, tracing exactly (``st``, a SceneTracer) where
    the tree cannot answer.

    One call runs a staged pipeline over all its rays (call it with a whole frame, or a
    worker's share of one): locate -> group rays by sample set -> exact first hits of all
    two-class rays (one tracer call) -> per (set, class) decisions -> per-ray weights ->
    blend -> exact tracing of every ray the tree cannot answer (one tracer call). Work that
    depends only on the 16 samples and the class (class counts, candidate patches, usable
    corners, whether any pairwise threshold can bite) is done once per set, not per ray."""

    def __init__(self, tree, st, options: QueryOptions | None = None):
        self.tree, self.st = tree, st
        self.opt = (options or QueryOptions()).validate()
        self.material = st.scene.object.material
        # load-time work, done once (and before any fork, so worker processes share it): a
        # loaded tree's derived hit points and normals, decoded samples and their
        # perspective-weighted copy, dense leaf tables, answerable-leaf flags
        tree.attach_geometry(st.tracer)
        self.table = tree.table
        tree.blend_vals, tree.vp_locator, tree.dir_locator
        tree.leaf_ok, tree.leaf_sampled, tree.cell_rect
        # a bake that measured no viewpoint cell (a full tree, or one whose every test ray was
        # traced) left no viewpoint-level errors to bound
        if (self.opt.max_error_deg is not None and self.opt.fallback_angle_deg is not None
                and np.isnan(tree.vp_err).all()):
            self.opt = replace(self.opt, max_error_deg=None,
                               angle_deg=self.opt.angle_deg if self.opt.angle_deg is not None
                               else self.opt.fallback_angle_deg)

    def __call__(self, o, d, tmax=None):
        """(ObjectRays, answers (N,), why (N,), stats) for rays o, d (unit). ``stats`` holds
        ``exact_first_hits`` and the CPU seconds of each stage (``query_<stage>_cpu_s``)."""
        o = np.asarray(o, np.float64)
        d = np.asarray(d, np.float64)
        n = len(o)
        tmax = np.full(n, np.inf) if tmax is None else np.asarray(tmax, np.float64)
        clock = self._clock = StageClock()
        known = self._known = KnownHits(n)
        self._exact_mirror_hits = 0   # per-call state (a TreeQuery answers one call at a time)
        self._must = np.zeros(n, bool)     # rays only Newton's hit may answer (_within_tolerance)
        self._newton_ok = np.zeros(n, bool)
        ans = np.full(n, MISS, np.int8)
        why = np.zeros(n, np.int8)
        res = _empty_result(n, o, d)
        with clock("locate"):
            loc, outside = locate(self.tree, o, d, tmax)
        ans[outside] = OUTSIDE
        n_exact = 0
        if len(loc):
            if self.opt.policy == "raytree":
                self._raytree(o, d, tmax, loc, res, ans, why, clock)
            else:
                n_exact = self._ri(o, d, tmax, loc, res, ans, why, clock, known)
        # a ray past the tolerance that Newton did not answer is traced
        lost = np.flatnonzero(self._must & ~self._newton_ok & (ans != TRACED))
        ans[lost] = TRACED
        why[lost] = WHY_TOLERANCE
        with clock("trace"):
            tr = np.flatnonzero((ans == TRACED) | (ans == OUTSIDE))
            if len(tr):
                ex = self.st.object_function(o[tr], d[tr], tmax[tr], first=known.of(tr))
                for k, val in ex.__dict__.items():
                    getattr(res, k)[tr] = val
        stats = {"exact_first_hits": n_exact, "exact_mirror_hits": self._exact_mirror_hits,
                 **{f"query_{k}_cpu_s": v for k, v in clock.cpu.items()}}
        return res, ans, why, stats

    # ------------------------------------------------------------------ sample sets
    def _sets(self, loc: Located):
        """Group located rays by their four leaves (= their 16 samples): (set of each ray,
        leaves (S, 4), sample ids (S, 16), sample classes (S, 16))."""
        set_of, first = group_rows(loc.leaf)
        s_leaf = loc.leaf[first]
        s_ids = self.tree.dir_forest.corner[s_leaf].reshape(-1, 16)
        return set_of, s_leaf, s_ids, self.table.cls[s_ids]

    # ------------------------------------------------------------------ the paper's policy
    def _ri(self, o, d, tmax, loc, res, ans, why, clock, known) -> int:
        tree, tab, opt = self.tree, self.table, self.opt
        with clock("group"):
            set_of, s_leaf, s_ids, s_cls = self._sets(loc)
            srt = np.sort(s_cls, axis=1)
            n_cls = 1 + np.sum(srt[:, 1:] != srt[:, :-1], axis=1)
            r_n = n_cls[set_of]
            rows = loc.ray
            many = r_n > 2
            ans[rows[many]] = TRACED
            why[rows[many]] = WHY_CLASSES
            pc = np.where(r_n == 1, srt[set_of, 0], -2)
            two = np.flatnonzero(r_n == 2)
        if len(two):
            with clock("first_hits"):
                pc[two] = self._first_hit_class(o, d, tmax, rows[two], set_of[two],
                                                np.flatnonzero(n_cls == 2), s_ids, known)
        ans[rows[pc == -1]] = MISS
        go = np.flatnonzero(pc >= 0)
        if opt.max_error_deg is not None:
            with clock("first_hits"):
                self._check_misses(o, d, tmax, loc, np.flatnonzero(pc == -1), set_of, s_leaf,
                                   ans, why, known)
            go = self._within_tolerance(loc, go, set_of, s_leaf, ans, why, known)
        if opt.path_identity:
            go = self._same_path(loc, go, set_of, pc, s_ids, s_leaf, ans, why)
        if len(go) == 0:
            return len(two)
        thresholds = opt.angle_deg is not None or opt.distance is not None
        ang = None if opt.angle_deg is None else np.radians(opt.angle_deg)
        dist = None if opt.distance is None else opt.distance * tree.diag
        per_sample = thresholds and opt.threshold_on == "samples"
        with clock("decide"):
            set_of, pc = set_of[go], pc[go]
            m = len(go)            # the rays left: loc's rows ``go`` (taken in "weights")
            # only the sets these rays use (all-miss sets hold many rays, answered already)
            keep = np.zeros(len(s_leaf), bool)
            keep[set_of] = True
            set_of = (np.cumsum(keep) - 1)[set_of]
            s_leaf, s_ids, s_cls = (a[keep] for a in (s_leaf, s_ids, s_cls))
            items = SetItems.of(tree, s_leaf, s_ids)
            unit_of, ufirst = group_rows(np.stack([set_of, pc], axis=1))
            u_set, u_pc = set_of[ufirst], pc[ufirst]
            u_ok = (tab.cls[items.ids[u_set]] == u_pc[:, None]) & ~tab.null[items.ids[u_set]]
            u_ok[:, 16:] &= np.repeat(items.has_extra[u_set], 4, axis=1)      # (U, 32) usable
            # units whose usable samples all reflect once: answered from the normal (and,
            # where they share one patch, from Newton's hit on it)
            u_mirror = None
            if opt.mirror_rays != "interpolate" and self.material.kind == "mirror":
                once = np.all(tab.once[items.ids[u_set]] | ~u_ok, axis=1)
                u_mirror = np.where(once, MIRROR_NORMAL, MIRROR_BLEND).astype(np.int8)
                if opt.mirror_rays == "newton":
                    pid = tab.patch[items.ids[u_set]]
                    top = np.where(u_ok, pid, -1).max(axis=1)
                    one = (top == np.where(u_ok, pid, np.iinfo(np.int32).max).min(axis=1)) \
                        & (self.st.tracer.piece_base[np.maximum(top, 0)] >= 0)   # one NURBS patch
                    u_mirror[once & one] = MIRROR_NEWTON
                # rays past the tolerance that Newton cannot answer are traced
                lost = self._must[loc.ray[go]] & (u_mirror[unit_of] != MIRROR_NEWTON)
                if lost.any():
                    ans[loc.ray[go[lost]]] = TRACED
                    why[loc.ray[go[lost]]] = WHY_TOLERANCE
                    k = ~lost
                    go, set_of, pc, unit_of = go[k], set_of[k], pc[k], unit_of[k]
                    m = len(go)
            # the DQs whose samples the thresholds compare: all, or those the bake could not
            # verify (split to the maximum depth: a shallower leaf's midpoint matched)
            u_checked = np.ones((len(u_set), 4), bool)
            if per_sample and opt.threshold_leaves == "unverified":
                u_checked = tree.dir_forest.level[s_leaf[u_set]] >= tree.params.direction_depth
            u_far = np.zeros(len(u_set), bool)      # units where some threshold may bite
            if per_sample:
                # far_pairs' pretest on everything a ray of the unit can use: a unit that
                # passes has no far pair among any ray's interpolants
                used = u_ok & np.tile(np.repeat(u_checked, 4, axis=1), 2)
                v = tab.vals[items.ids[u_set]].astype(np.float64)
                u_far = may_have_far_pairs(v[..., 3:6], v[..., 0:3], used, ang, dist)
                far, far_of = self._unit_far_pairs(u_far, items.ids[u_set], u_ok, u_checked,
                                                   ang, dist)
                u_far = far.any(axis=(1, 2))[far_of]          # units with a real far pair
        if per_sample or not thresholds:
            # units whose 16 corners are all usable and pass the thresholds: every ray of
            # them blends its 16 corners bilinearly at both levels, wherever it falls
            easy = (all_last(u_ok[:, :16].reshape(-1, 2, 8)).all(axis=1) & ~u_far)[unit_of]
            if easy.any():
                e, h = np.flatnonzero(easy), np.flatnonzero(~easy)
                with clock("blend"):
                    self._blend_bilinear(loc.take(go[e]), items, set_of[e], pc[e], o, d, tmax,
                                         res, ans, why,
                                         None if u_mirror is None else u_mirror[unit_of[e]])
                go, set_of, pc, unit_of = go[h], set_of[h], pc[h], unit_of[h]
                m = len(go)
        with clock("weights"):
            loc = loc.take(go)
            usable = u_ok[unit_of, :16].reshape(m, 4, 4)
            checked = u_checked[unit_of]
            thr_hit = np.zeros((m, 4), bool)            # DQs whose corners the thresholds cut
            fr = np.flatnonzero(u_far[unit_of])         # rays that need the pairwise tests
            if len(fr):
                fr_row = far_of[unit_of[fr]]             # their units' rows of ``far``
                self._direction_thresholds(fr, far, fr_row, u_ok[:, :16], unit_of, loc,
                                           usable, thr_hit)
            # per DQ: 4 corners + up to 2 extras; every DQ of every ray in one call, rows
            # 4 * ray + DQ
            w = np.zeros((m, 4, 6))
            wk, dq_st = cell_weights(usable.reshape(-1, 4), loc.lx.ravel(), loc.ly.ravel(),
                                     opt.extrapolation)
            w[:, :, :4] = wk.reshape(m, 4, 4)
            dq_st = dq_st.reshape(m, 4)
            item = np.broadcast_to(DEFAULT_ITEMS, (m, 4, 6))
            fail = np.flatnonzero(dq_st.ravel() == FAIL)
            if len(fail):
                ea = extra_weights(tree, tab, loc.leaf.ravel()[fail], loc.lx.ravel()[fail],
                                   loc.ly.ravel()[fail], usable.reshape(-1, 4)[fail],
                                   pc[fail // 4], opt.extrapolation)
                r, k = np.divmod(fail[ea.rows], 4)
                if len(r):
                    item = item.copy()
                    w[r, k] = ea.w
                    item[r, k, 4:] = 16 + 4 * k[:, None] + ea.extra
                    dq_st[r, k] = np.where(ea.extrapolated, EXTRAPOLATED, EXTRA)
            is_extra = (dq_st == EXTRA) | (dq_st == EXTRAPOLATED)
            # viewpoint level
            dq_ok = dq_st != FAIL
            thr_q = np.zeros(m, bool)
            if per_sample and len(fr):
                self._viewpoint_thresholds(fr, far_bits(far)[fr_row], item, usable, w, is_extra,
                                           dq_ok, checked, loc, thr_hit, thr_q)
            elif thresholds and not per_sample:
                # the intermediate rays f*(R_VP): parallel query rays from the four viewpoints
                inter = np.einsum("nkj,nkjc->nkc", w.astype(np.float32),
                                  items.item_vals(set_of[:, None, None], item)).astype(np.float64)
                idir = inter[:, :, 3:6] / np.maximum(
                    np.linalg.norm(inter[:, :, 3:6], axis=2), 1e-300)[:, :, None]
                r2, blocks = far_pairs(idir, inter[:, :, 0:3], dq_ok, ang, dist)
                dq_ok[r2], thr_q[r2] = drop_outlier(blocks, dq_ok[r2], UNIT_CORNERS,
                                                    np.stack([loc.alpha[r2], loc.beta[r2]], 1))
            W, qst = cell_weights(dq_ok, loc.alpha, loc.beta, opt.extrapolation)
            few = qst == FAIL
            # too few interpolants because the thresholds cut them: traced "by the threshold"
            thr = ~(few & (thr_q | np.any(thr_hit & ~dq_ok, axis=1)))
            few &= thr
        with clock("blend"):
            cand = np.flatnonzero(~few & thr)
            out, best = self._blend(items, set_of, cand, W, w, item, is_extra)
            od, nm = out[:, 3:6], out[:, 9:12]
            lod, lnm = norm3(od), norm3(nm)
            blend_ok = np.ones(m, bool)
            blend_ok[cand] = (lod > MIN_BLEND_NORM) & (lnm > MIN_BLEND_NORM)
            good = ~few & thr & blend_ok
            kind = np.maximum(dq_st.max(axis=1, where=dq_ok, initial=BILINEAR), qst)
            code = np.select([kind == BILINEAR, kind == TRIANGLE, kind == EXTRA,
                              kind == EXTRAPOLATED], [FULL, REDUCED, EXTRA_S, EXTRAPOLATED_S],
                             TRACED)
            rows = loc.ray
            ans[rows] = np.where(good, code, TRACED)
            why[rows] = np.select([few, ~thr, ~blend_ok], [WHY_USABLE, WHY_THRESHOLD, WHY_BLEND], 0)
            gc = good[cand]
            g = cand[gc]
            self._fill(res, ans, rows[g], o, d, tmax, out[gc, 0:3], od[gc] / lod[gc, None],
                       out[gc, 6:9], nm[gc] / lnm[gc, None], pc[g],
                       tab.patch[items.ids[set_of[g], best[gc]]].astype(np.int64),
                       mirror=None if u_mirror is None else u_mirror[unit_of[g]],
                       uv=(out[gc, 12:14], tab.vals[items.ids[set_of[g], best[gc]], 12:14]))
            if opt.null_interp:
                # units holding a null sample of their class: their failed rays may be null
                u_null = np.any(tab.null[s_ids[u_set]] & (s_cls[u_set] == u_pc[:, None]), axis=1)
                r = np.flatnonzero(few & u_null[unit_of])
                if len(r):
                    self._null(loc.take(r), s_ids[set_of[r]], pc[r], o, d, tmax, res, ans, why)
        return len(two)

    def _blend_bilinear(self, loc, items, set_of, pc, o, d, tmax, res, ans, why, mirror=None):
        """Rays ``loc`` (of sets ``set_of``, classes ``pc``) whose 16 corners are all usable:
        bilinear weights at both levels, one blend (the general path's answers, without its
        per-ray rules; the weights are formed in float32, the blend's precision, so the
        representative patch of two weights equal to float32 rounding may be the other's).
        ``mirror``: how mirror rays are answered (MIRROR_*, see ``_fill``)."""
        W = bilinear_weights(loc.alpha, loc.beta)                            # (n, 4)
        # W_k times DQ k's bilinear weights, float32 (the blend's precision)
        wr = np.empty((len(loc), 4, 4), np.float32)
        for j, wy in ((0, W * (1 - loc.ly)), (2, W * loc.ly)):
            wr[:, :, j] = wy * (1 - loc.lx)
            wr[:, :, j + 1] = wy * loc.lx
        wr = wr.reshape(len(loc), 16)
        out = blend(items.corner_vals, set_of, wr)
        best = np.argmax(wr, axis=1)                     # bilinear weights are >= 0
        od, nm = out[:, 3:6], out[:, 9:12]
        lod, lnm = norm3(od), norm3(nm)
        ok = (lod > MIN_BLEND_NORM) & (lnm > MIN_BLEND_NORM)
        rows = loc.ray
        ans[rows] = np.where(ok, FULL, TRACED)
        why[rows] = np.where(ok, 0, WHY_BLEND)
        g = np.flatnonzero(ok)
        self._fill(res, ans, rows[g], o, d, tmax, out[g, 0:3], od[g] / lod[g, None],
                   out[g, 6:9], nm[g] / lnm[g, None], pc[g],
                   self.table.patch[items.ids[set_of[g], best[g]]].astype(np.int64),
                   mirror=None if mirror is None else mirror[g],
                   uv=(out[g, 12:14], self.table.vals[items.ids[set_of[g], best[g]], 12:14]))

    def _blend(self, items, set_of, cand, W, w, item, is_extra):
        """Blend rays ``cand`` (of sets ``set_of``) with viewpoint weights W (m, 4) and per-DQ
        slot weights w (m, 4, 6) over items ``item`` (m, 4, 6); rays without extras blend their
        16 corners only. Returns (values (c, 14), the heaviest item of each ray (c,))."""
        out = np.empty((len(cand), items.corner_vals.shape[-1]))
        best = np.empty(len(cand), np.int64)
        ex = is_extra[cand].any(axis=1)
        k = np.flatnonzero(~ex)
        r = cand[k]
        wr = (W[r, :, None] * w[r, :, :4]).reshape(len(r), 16)
        out[k] = blend(items.corner_vals, set_of[r], wr)
        best[k] = np.argmax(np.abs(wr), axis=1)
        k = np.flatnonzero(ex)
        if len(k):
            r = cand[k]
            wr = np.zeros((len(r), 32))
            np.put_along_axis(wr, item[r].reshape(len(r), 24),
                              (W[r, :, None] * w[r]).reshape(len(r), 24), axis=1)
            out[k] = blend(items.corner_vals, set_of[r], wr[:, :16]) \
                + blend(items.extra_vals, set_of[r], wr[:, 16:])
            best[k] = np.argmax(np.abs(wr), axis=1)
        return out, best

    def _within_tolerance(self, loc, go, set_of, s_leaf, ans, why, known):
        """Of the located rays ``go``, those whose four leaves (decided once per set) and
        viewpoint cell the bake measured within ``max_error_deg`` (an unmeasured NaN is not);
        the others are traced (WHY_TOLERANCE). With mirror_rays "newton", a mirror ray outside
        the tolerance whose leaves and cell the bake did not see change path goes on as one
        that only an exact hit may answer (``_must``): the bake's errors are the blend's, which
        that hit replaces. Where the object's outline crosses them (BOUNDARY), only if the ray's
        exact first hit is known (a two-class ray): hit or miss is then not a guess. A leaf or
        cell the bake saw answered wrongly (inf) proves nothing: the ray is traced; one it did
        not measure (NaN: its midpoint changed class at the maximum depth, or no test ray was
        interpolated) is traced too, unless the exact first hit is known: its flags, which the
        bake sets from the traced corners and test rays whether or not it could measure, are
        then all the evidence the exact hit needs."""
        tol, tree = self.opt.max_error_deg, self.tree
        s_ok = np.all(tree.dir_err[s_leaf] <= tol, axis=1)
        ok = s_ok[set_of[go]] & (tree.vp_err[loc.vnode[go]] <= tol)
        if self.opt.mirror_rays == "newton" and self.material.kind == "mirror":
            flags = np.bitwise_or.reduce(tree.dir_flags[s_leaf], axis=1)[set_of[go]] \
                | tree.vp_flags[loc.vnode[go]]
            exact = known.pos[loc.ray[go]] >= 0
            s_err, c_err = tree.dir_err[s_leaf], tree.vp_err[loc.vnode[go]]
            measured = np.all(np.isfinite(s_err), axis=1)[set_of[go]] & np.isfinite(c_err)
            seen_wrong = np.any(np.isinf(s_err), axis=1)[set_of[go]] | np.isinf(c_err)
            calm = ~ok & (measured | (exact & ~seen_wrong)) & (flags & PATH_CHANGE == 0) \
                & ((flags & BOUNDARY == 0) | exact)
            self._must[loc.ray[go[calm]]] = True
            ok |= calm
        bad = loc.ray[go[~ok]]
        ans[bad] = TRACED
        why[bad] = WHY_TOLERANCE
        return go[ok]

    def _same_path(self, loc, go, set_of, pc, s_ids, s_leaf, ans, why):
        """Of the located rays ``go`` (classes ``pc``), those whose usable samples (their set's
        corners of their class, not null) share one ray-tree hash and whose leaves and cell
        the bake did not see change path (PATH_CHANGE); decided once per (set, class) unit.
        The others are traced (WHY_PATH)."""
        tab, tree = self.table, self.tree
        unit_of, first = group_rows(np.stack([set_of[go], pc[go]], axis=1))
        u_set = set_of[go][first]
        ids = s_ids[u_set]
        use = (tab.cls[ids] == pc[go][first][:, None]) & ~tab.null[ids]
        h = tab.tree[ids].astype(np.int64)
        top = np.where(use, h, -1).max(axis=1)
        same = top <= np.where(use, h, np.iinfo(np.int64).max).min(axis=1)
        u_ok = same & ~np.any(tree.dir_flags[s_leaf[u_set]] & PATH_CHANGE, axis=1)
        ok = u_ok[unit_of] & (tree.vp_flags[loc.vnode[go]] & PATH_CHANGE == 0)
        bad = loc.ray[go[~ok]]
        ans[bad] = TRACED
        why[bad] = WHY_PATH
        return go[ok]

    def _check_misses(self, o, d, tmax, loc, miss, set_of, s_leaf, ans, why, known):
        """Tolerance mode, the rays ``miss`` the samples answer MISS (all 16 miss, or the exact
        first hit against the candidate patches missed): the miss is trusted where the bake
        verified it (within the tolerance, no object/miss boundary in the four leaves or the
        cell); elsewhere the exact first hit against every patch decides, and a ray that hits
        is traced (WHY_UNSAMPLED: paper Fig. 9(b), or a patch none of its samples hit)."""
        tree, tol = self.tree, self.opt.max_error_deg
        s_ok = np.all((tree.dir_err[s_leaf] <= tol) & (tree.dir_flags[s_leaf] & BOUNDARY == 0),
                      axis=1)
        c = loc.vnode[miss]
        ok = s_ok[set_of[miss]] & (tree.vp_err[c] <= tol) & (tree.vp_flags[c] & BOUNDARY == 0)
        r = loc.ray[miss[~ok]]
        if len(r):
            new = r[known.pos[r] < 0]        # the others' first hit stage searched every patch
            if len(new):
                known.add(new, self.st.tracer.intersect(o[new], d[new], tmax=tmax[new]))
            r = r[known.hit(r)]
            ans[r] = TRACED
            why[r] = WHY_UNSAMPLED

    def _first_hit_class(self, o, d, tmax, rows, set_of, two_sets, s_ids, known) -> np.ndarray:
        """Class of the exact first hit (-1: miss) of rays ``rows`` against only the distinct
        patches of their two-class sets. One tracer call against every patch finds it where
        the nearest hit is a candidate's or there is none (it is kept in ``known`` for the
        trace stage); the few rays whose nearest hit is another patch's are searched again
        against their candidates only."""
        pat = np.sort(self.table.patch[s_ids[two_sets]].astype(np.int64), axis=1)
        dup = np.zeros_like(pat, bool)
        dup[:, 1:] = pat[:, 1:] == pat[:, :-1]
        cand = np.where(dup | (pat < 0), -1, pat)
        cand = cand[np.searchsorted(two_sets, set_of)]
        hit = self.st.tracer.intersect(o[rows], d[rows], tmax=tmax[rows])
        known.add(rows, hit)
        cls = np.where(hit.hit, hit.cls, -1)
        other = np.flatnonzero(hit.hit & ~np.any(cand == hit.patch[:, None], axis=1))
        if len(other):
            r = rows[other]
            h2 = self.st.tracer.intersect(o[r], d[r], tmax=tmax[r], patches=cand[other])
            cls[other] = np.where(h2.hit, h2.cls, -1)
        return cls

    def _unit_far_pairs(self, u_far, u_ids, u_ok, u_checked, ang, dist):
        """Paper 5.3's far pairs among the 32 items (usable, checked) of the units ``u_far``,
        once per unit: (far (F, 32, 32), row of each unit in it (U,), -1 where not tested)."""
        fu = np.flatnonzero(u_far)
        used = u_ok[fu] & np.tile(np.repeat(u_checked[fu], 4, axis=1), 2)
        full = np.zeros((len(fu) + 1, 32, 32), bool)          # the last row: no far pair
        # units without usable extras compare their 16 corners only (a quarter of the pairs)
        ext = any_last(used[:, 16:].reshape(-1, 2, 8)).any(axis=1)
        for sel, k in ((np.flatnonzero(~ext), 16), (np.flatnonzero(ext), 32)):
            if len(sel):
                v = self.table.vals[u_ids[fu[sel], :k]].astype(np.float64)
                rws, far = far_pairs(v[..., 3:6], v[..., 0:3], used[sel, :k], ang, dist)
                full[sel[rws], :k, :k] = far
        far_of = np.full(len(u_far), len(fu))
        far_of[fu] = np.arange(len(fu))
        return full, far_of

    @staticmethod
    def _direction_thresholds(fr, far, fr_row, u_used, unit_of, loc, usable, thr_hit):
        """Paper 5.3 at the direction level for rays ``fr`` (``fr_row``: their units' rows of
        the far pairs ``far`` (F, 32, 32); ``u_used`` (U, 16) the units' usable corners): far
        corners of a DQ are not usable (an outlier is dropped, which one depends on where the
        ray falls in the cell). Degrees and leftovers are found per unit, not per ray."""
        rows, pos = np.unique(fr_row, return_inverse=True)
        first = np.zeros(len(rows), np.int64)
        first[pos] = np.arange(len(fr))          # a ray of each unit (all share its usable)
        used = u_used[unit_of[fr[first]]].reshape(-1, 4, 4)
        f = far[rows, :16, :16].reshape(-1, 4, 4, 4, 4)
        for k in range(4):
            usable[fr, k], thr_hit[fr, k] = drop_outlier_units(
                f[:, k, :, k], used[:, k], pos, UNIT_CORNERS,
                np.stack([loc.lx[fr, k], loc.ly[fr, k]], 1))

    @staticmethod
    def _viewpoint_thresholds(fr, bits, item, usable, w, is_extra, dq_ok, checked, loc, thr_hit,
                              thr_q):
        """Paper 5.3 at the viewpoint level for rays ``fr`` (``bits`` (R, 32): their units'
        far pairs as bit rows, bit j of row i set where items i and j are far; their items
        ``item[fr]``): DQs are far apart when any of their interpolants are (an extra-sample
        triangle's samples for extras); a DQ with a far pair inside is unusable, then an
        outlying DQ is dropped."""
        n = len(fr)
        member = np.concatenate([usable[fr], np.zeros((n, 4, 2), bool)], axis=2)
        member = np.where(is_extra[fr, :, None], w[fr] != 0, member)
        member = member & dq_ok[fr, :, None] & checked[fr, :, None]            # (n, 4, 6)
        it = item[fr]
        # each DQ's member items as a bit set (a ray's items are distinct: sum = or), and
        # the items far from any of them
        mask = np.where(member, np.left_shift(np.uint32(1), it.astype(np.uint32)),
                        np.uint32(0)).sum(axis=2, dtype=np.uint32)             # (n, 4)
        far_of_items = np.take_along_axis(bits, it.reshape(n, 24), axis=1).reshape(n, 4, 6)
        reach = np.bitwise_or.reduce(np.where(member, far_of_items, np.uint32(0)), axis=2)
        blocks = (reach[:, :, None] & mask[:, None, :]) != 0                   # (n, 4, 4)
        r = np.flatnonzero(blocks.any(axis=(1, 2)))
        blocks = blocks[r]
        inner = np.diagonal(blocks, axis1=1, axis2=2)                           # (R, 4)
        r = fr[r]
        thr_hit[r] |= inner
        dq_ok[r] &= ~inner
        dq_ok[r], thr_q[r] = drop_outlier(blocks, dq_ok[r], UNIT_CORNERS,
                                          np.stack([loc.alpha[r], loc.beta[r]], 1))

    def _null(self, loc, flat, pc, o, d, tmax, res, ans, why):
        """Rays (``loc``, their 16 sample ids ``flat``) that had too few usable interpolants:
        the same interpolation with the null samples of the query's class as the usable ones
        (null as a state of its own, like a class: four null corners, or three with the query
        inside their triangle, at both levels). Where it succeeds the query ray is answered
        null (trapped), with the interpolated first-hit point and normal for its local
        illumination."""
        tab = self.table
        m = len(loc)
        use = ((tab.cls[flat] == pc[:, None]) & tab.null[flat]).reshape(m, 4, 4)
        w = np.zeros((m, 4, 4))
        st = np.zeros((m, 4), np.int8)
        for k in range(4):
            w[:, k], st[:, k] = cell_weights(use[:, k], loc.lx[:, k], loc.ly[:, k])
        W, qst = cell_weights(st != FAIL, loc.alpha, loc.beta)
        weights = (W[:, :, None] * w).reshape(m, 16)
        ok = np.flatnonzero(qst != FAIL)
        if len(ok) == 0:
            return
        out = blend(tab.vals[flat[ok]], np.arange(len(ok)), weights[ok])
        pt, nm = out[:, 6:9], out[:, 9:12]
        ln = np.linalg.norm(nm, axis=1)
        keep = ln > MIN_BLEND_NORM
        ok, pt, nm, ln = ok[keep], pt[keep], nm[keep], ln[keep]
        rows = loc.ray[ok]
        ans[rows] = NULL_S
        why[rows] = 0
        self._fill(res, ans, rows, o, d, tmax, pt, np.zeros_like(pt), pt, nm / ln[:, None],
                   pc[ok], self._patch_of(flat[ok], weights[ok]), null=True)

    # ------------------------------------------------------------------ Bala et al.'s policy
    def _raytree(self, o, d, tmax, loc, res, ans, why, clock):
        """Interpolate (16 samples, bilinear at both levels) only where all 16 samples share
        one ray tree and class and none is null; trace otherwise. Decided once per set."""
        tab = self.table
        with clock("group"):
            set_of, s_leaf, s_ids, s_cls = self._sets(loc)
            th = tab.tree[s_ids]
            same = np.all(th == th[:, :1], axis=1) & np.all(s_cls == s_cls[:, :1], axis=1) \
                & ~np.any(tab.null[s_ids], axis=1)
            r_same = same[set_of]
            rows = loc.ray
            ans[rows[r_same & (s_cls[set_of, 0] == -1)]] = MISS
            ans[rows[~r_same]] = TRACED
            why[rows[~r_same]] = WHY_RAYTREE
        with clock("blend"):
            g = np.flatnonzero(r_same & (s_cls[set_of, 0] != -1))
            if len(g) == 0:
                return
            wq = bilinear_weights(loc.alpha[g], loc.beta[g])
            wdq = bilinear_weights(loc.lx[g], loc.ly[g])                    # (g, 4, 4)
            weights = (wq[:, :, None] * wdq).reshape(len(g), 16)
            sg = set_of[g]
            items = SetItems.of(self.tree, s_leaf, s_ids)
            out = blend(items.corner_vals, sg, weights)
            od, nm = out[:, 3:6], out[:, 9:12]
            lod, lnm = np.linalg.norm(od, axis=1), np.linalg.norm(nm, axis=1)
            ok = (lod > MIN_BLEND_NORM) & (lnm > MIN_BLEND_NORM)      # opposed samples: traced
            ans[rows[g[~ok]]] = TRACED
            why[rows[g[~ok]]] = WHY_BLEND
            g, sg, out, od, nm, lod, lnm = (a[ok] for a in (g, sg, out, od, nm, lod, lnm))
            ans[rows[g]] = FULL
            self._fill(res, ans, rows[g], o, d, tmax, out[:, 0:3], od / lod[:, None],
                       out[:, 6:9], nm / lnm[:, None], s_cls[sg, 0].astype(np.int64),
                       tab.patch[s_ids[sg, 0]].astype(np.int64))

    # ------------------------------------------------------------------ results
    def _patch_of(self, ids, weights):
        """The patch of the heaviest interpolant (a representative patch id); ``ids`` (n, K)
        the sample ids the (n, K) weights refer to."""
        best = np.argmax(np.abs(weights), axis=1)
        return self.table.patch[ids[np.arange(len(ids)), best]].astype(np.int64)

    def _exact_hits(self, rows, o, d, tmax, seeds: Seeds) -> PatchHit:
        """Exact hits of rays ``rows`` (directions ``d``) on their seeds' patches near the
        seeds (NEWTON_MAX_MOVE_REL, NEWTON_MAX_TURN_DEG): where the query found the ray's
        exact first hit already, that hit if it is on the seed's patch (none if on another),
        else Newton's from the seeds."""
        lim = NEWTON_MAX_MOVE_REL * self.tree.diag, np.cos(np.radians(NEWTON_MAX_TURN_DEG))
        h = PatchHit.misses(len(rows))
        got = self._known.of(rows)
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
            floor = T_MIN_REL * self.st.tracer.diag
            h.put(r, polish_hits(self.st.tracer, o[rows[r]], d[r], sub, *lim,
                                 np.full(len(r), floor), tmax[rows[r]]))
        return h

    def _fill(self, res, ans, rows, o, d, tmax, oo, od, pt, nm, cls, patch, null=False,
              mirror=None, uv=None):
        """Write interpolated answers (output ray oo, od; first hit pt, unit normal nm) into
        ``res``. ``mirror`` (MIRROR_* per row): mirror rays whose samples all reflect once are
        answered as the tracer answers such a ray from its hit - leaving from pt along the
        query direction reflected about nm - instead of by the blended output ray; with
        MIRROR_NEWTON the hit and normal are first replaced by exact ones on ``patch``
        (``_exact_hits``, where kept); ``uv``: (the interpolated normalized parameters, those
        of the heaviest sample) to start Newton from."""
        dd = d[rows]
        t_first = np.einsum("ij,ij->i", pt - o[rows], dd)
        # the environment is in front of the interpolated hit: the object is not seen
        hidden = t_first >= tmax[rows]
        if hidden.any():
            ans[rows[hidden]] = MISS
            k = ~hidden
            rows, oo, od, pt, nm, cls, patch, dd, t_first = (
                a[k] for a in (rows, oo, od, pt, nm, cls, patch, dd, t_first))
            mirror = None if mirror is None else mirror[k]
            uv = None if uv is None else (uv[0][k], uv[1][k])
        flip = np.einsum("ij,ij->i", nm, dd) > 0
        nm = np.where(flip[:, None], -nm, nm)
        if mirror is not None and mirror.any():
            newton = np.flatnonzero(mirror == MIRROR_NEWTON)
            if len(newton):
                pt, nm, t_first = pt.copy(), nm.copy(), t_first.copy()
                with self._clock("newton"):
                    h = self._exact_hits(rows[newton], o, dd[newton], tmax,
                                         Seeds(patch[newton], uv[0][newton], pt[newton],
                                               nm[newton], uv[1][newton]))
                k = newton[h.hit]
                n_new = h.normal[h.hit]
                pt[k], t_first[k] = h.point[h.hit], h.t[h.hit]
                nm[k] = np.where((np.einsum("ij,ij->i", n_new, dd[k]) > 0)[:, None], -n_new, n_new)
                self._exact_mirror_hits += len(k)
                self._newton_ok[rows[k]] = True
                res.uv[rows[k]] = self.st.tracer.normalized_uv(h.patch[h.hit], h.u[h.hit],
                                                               h.v[h.hit])
            m = mirror != MIRROR_BLEND
            od = np.where(m[:, None], reflect(dd, nm), od)
            oo = np.where(m[:, None], pt, oo)
        res.hit[rows] = True
        res.null[rows] = null
        res.out_origin[rows] = oo
        res.out_dir[rows] = od
        res.point[rows] = pt
        res.normal[rows] = nm
        res.t_first[rows] = t_first
        res.cls[rows] = cls
        res.patch[rows] = patch
        if self.material.kind == "dielectric":
            cos_i = -np.einsum("ij,ij->i", dd, nm)
            res.fresnel[rows] = fresnel_dielectric(cos_i, np.full(len(rows), 1.0 / self.material.ior))
            res.refl_dir[rows] = reflect(dd, nm)


def _empty_result(n, o, d) -> ObjectRays:
    """Misses for every ray (output = input ray), to be filled in by the stages."""
    return ObjectRays(hit=np.zeros(n, bool), null=np.zeros(n, bool), out_origin=o.copy(),
                      out_dir=d.copy(), t_first=np.full(n, np.inf), point=np.zeros((n, 3)),
                      normal=np.zeros((n, 3)), patch=np.full(n, -1, np.int64),
                      cls=np.full(n, -1, np.int64), events=np.zeros(n, np.int64),
                      refl_dir=np.zeros((n, 3)), fresnel=np.zeros(n),
                      tree=np.zeros(n, np.uint32), uv=np.zeros((n, 2)))
