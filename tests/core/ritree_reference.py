"""A plain per-ray reference of the RI-Tree query rules (``riray.ritree.query.TreeQuery``).

Helper module for tests/core/test_ritree_reference.py (not collected: no ``test_`` prefix). It
restates the rules of TreeQuery as it stood at commit 3bb980a (``core/ritree/query.py`` and
``core/ritree/interp.py`` before the staged rewrite, now ``core/ritree/query/``) as a Python loop
over rays, with plain scalar / tiny-array code, so a fast pipeline can be checked against it ray by ray.

What it takes from core, and why that is not a rule:
- ``entry_points``, ``Forest.locate``, ``dir_to_cube``, ``SLOT``: where a ray enters the padded
  box, its viewpoint cell and the four direction leaves (location, not a decision);
- the sample table (decoded once) and the tree's arrays (ex_*, dir_rect, forests' cells);
- ``st.tracer.intersect(..., patches=cand)``: the exact first hit of a query ray against only
  its candidate patches. The candidates are chosen here, ray by ray; the tracer call is batched
  over all two-class rays because each call has a large fixed cost, and its answer for one ray
  does not depend on the other rays of the batch.
Everything after location - the two-patch rule, usable samples, thresholds and outlier drops,
bilinear / barycentric / extra-sample weights, extrapolation, perspective weighting, the
viewpoint-level combination, null interpolation, the hidden rule and the answer / why codes -
is written out below without core's interpolation helpers.

Rules (policy "ri"; paper sections 4.1-4.3, 5.1-5.4), per ray:
1.  Rays not entering the padded box before ``tmax`` are MISS; rays starting inside it, and
    rays whose viewpoint cell, hemicube slot, direction leaves, baked (u, v) rectangles or
    corner samples are missing, are OUTSIDE (traced).
2.  Two-patch rule: > 2 classes among the 16 samples -> TRACED (more_than_two_classes) with
    ``many_classes="trace"``; with "first_hit", the exact first hit against all patches gives
    the class (no hit -> MISS; a class none of the 16 samples has -> TRACED, unsampled_hit). One
    class: that class (the miss class -1 -> MISS). Two classes: the exact first hit against the
    distinct patches of the 16 samples gives the class; no hit -> MISS.
2b. Tolerance (``max_error_deg`` set): a ray of a class (>= 0) whose four leaves'
    or viewpoint cell's baked error (``dir_err``, ``vp_err``) exceeds it, or was not measured,
    is TRACED (tolerance).
2c. Misses under a tolerance: a ray rule 2 answers MISS is traced (unsampled_hit) when its
    exact first hit against all patches hits and its leaves or cell are not within the
    tolerance or carry the BOUNDARY flag (an object/miss boundary the bake saw).
2d. Path identity (``path_identity``), after 2b: a ray of a class whose usable corners (its
    class, not null) hold more than one ray-tree hash, or whose leaves or cell carry the
    PATH_CHANGE flag, is TRACED (path_change).
2e. One path per blend (``max_error_deg`` set, ``one_path`` on, ``path_identity`` off), after
    2b: a ray of a class whose usable corners hold more than one path is TRACED (path_change);
    on a mirror a path is the sequence of classes of the patches it meets, else the ray-tree
    hash.
3.  Usable: the query's class and not null.
4.  Per-sample thresholds (``threshold_on="samples"``; angle = chord of the output directions,
    distance = of the output origins, |a - b|^2 > limit^2): pairs among the usable samples of
    the checked leaves (all, or with ``threshold_leaves="unverified"`` only leaves at the
    maximum direction depth). Per leaf: the corner in most far pairs is dropped (ties: the one
    farthest from the query's cell-local point, then the lowest corner index); a leaf still
    holding a far pair loses all its corners.
5.  Per leaf: 4 usable -> bilinear; 3 -> barycentric on their triangle (inside down to
    -INSIDE_SLACK; else extrapolated down to -extrapolation; else fail); fewer -> the leaf's
    extra samples (one-interpolant: triangle (L, v1, v2); two-interpolant: the usable side's
    pair (c1, c2) with its two extras: T1 = (c1, c2, e1), T2 = (c2, e1, e2); the first
    triangle containing the point, else extrapolation over the last valid one); else fail.
6.  Intermediate rays: each leaf's weighted sum of its samples, output directions weighted by
    the length |(1, u, v)| of their direction-cube points (perspective-correct).
7.  Viewpoint level, samples mode: the members of a leaf are its usable corners, or the
    nonzero-weight vertices of its extra-sample triangle. A leaf with a far pair among its own
    members fails; then leaves are far when any of their members are, and one outlier leaf is
    dropped by the rule of 4 (query point (alpha, beta)). Intermediate mode: the four
    intermediate rays (normalized direction, origin) are compared instead.
8.  The surviving leaves combine bilinearly (4) or barycentrically (3) in (alpha, beta), with
    the extrapolation rule; else traced: "threshold" if a threshold cut a leaf or the viewpoint
    level, else "too_few_usable". Blended direction or normal shorter than MIN_BLEND_NORM ->
    traced (degenerate_blend).
9.  Answer: the weakest kind used (bilinear < triangle < extra < extrapolated) -> FULL,
    REDUCED, EXTRA_S, EXTRAPOLATED_S.
10. Null rays (``null_interp``): a ray traced for too few usable interpolants with a null
    sample of its class among the 16 is interpolated once more with the null samples of its
    class as the usable ones (bilinear / barycentric only, no extrapolation, no thresholds,
    no extra samples); success -> NULL_S with the interpolated hit point and normal.
11. Hidden: an interpolated (or null) first hit at t >= tmax along the query ray -> MISS.
    Normals are turned to face the query ray.
12. Mirror normal (``mirror_rays`` "reflect" or "newton", after the rules of the paper, since
    commit 65bd543): on a mirror, an interpolated ray (rules 5-9) whose usable samples - corners and
    the four leaves' extra samples of its class, not null - all left the object at their
    first hit leaves from its interpolated hit point along the query direction mirrored about
    its interpolated normal.
13. Mirror Newton hit (``mirror_rays`` "newton", with rule 12): where those usable samples also all
    share one NURBS patch, the ray's nearest hit on that patch (the exact tracer restricted to
    it; for a two-class ray, its exact first hit against every patch, if on that patch, else
    none) replaces the interpolated hit point and normal - where it lies within
    NEWTON_MAX_MOVE_REL of the box diagonal of the interpolated point and its normal, turned
    to face the ray, within NEWTON_MAX_TURN_DEG of the interpolated one - and the ray leaves
    from it, mirrored about its normal. With the tolerance (rule 2b), a mirror ray outside it
    whose leaves and cell carry no PATH_CHANGE, and no BOUNDARY unless it is a two-class ray
    (its exact first hit known), and have finite measured errors - or, for a two-class ray,
    errors none of which is inf (NaN: not measured) - is not traced there: it is
    answered only by this rule's exact hit - traced (tolerance) where rules 12-13 do not
    apply or find no such hit; traced for its own reason where a later rule traces it.

Policy "raytree": OUTSIDE / MISS as above; all 16 samples with the same ray-tree hash, the same
class and none null -> bilinear at both levels (perspective-weighted) -> FULL, or MISS for the
miss class, or TRACED (degenerate_blend) for a blended direction or normal shorter than
MIN_BLEND_NORM; otherwise TRACED (raytree_mismatch).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from riray.ritree.dircube import SLOT, dir_to_cube
from riray.ritree.query import (EXTRA_S, EXTRAPOLATED_S, FULL, MISS, NULL_S, OUTSIDE, REDUCED,
                                TRACED, WHY_BLEND, WHY_CLASSES, WHY_RAYTREE, WHY_THRESHOLD,
                                WHY_PATH, WHY_TOLERANCE, WHY_UNSAMPLED, WHY_USABLE)
from riray.ritree.tree import BOUNDARY, PATH_CHANGE

try:                                   # the staged query (adab97b) moved it to ritree.locate
    from riray.ritree.locate import entry_points
except ImportError:                    # 3bb980a
    from riray.ritree.query import entry_points

# The rules' constants as they were at 3bb980a (restated, not imported: the reference must not
# follow a change in core).
INSIDE_SLACK = 1e-12       # barycentric coordinates down to -this count as inside
DEGENERATE_AREA = 1e-9     # |doubled triangle area| (cell units) at or below this: degenerate
MIN_BLEND_NORM = 1e-3      # shorter blended direction / normal: traced
NEWTON_MAX_MOVE_REL = 1e-2  # rule 13: farthest exact hit from the interpolated one (x diagonal)
NEWTON_MAX_TURN_DEG = 10.0  # rule 13: largest angle of its normal to the interpolated normal

# Interpolation kinds (ordered: larger = weaker answer).
FAIL, BILINEAR, TRIANGLE, EXTRA, EXTRAPOLATED = 0, 1, 2, 3, 4
KIND_CODE = {BILINEAR: FULL, TRIANGLE: REDUCED, EXTRA: EXTRA_S, EXTRAPOLATED: EXTRAPOLATED_S}

CORNERS = ((0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0))   # cell corner slots c0..c3


# --------------------------------------------------------------------------- the tree's data
class TreeData:
    """What the reference reads from a baked tree: samples decoded once (float64) and plain
    Python views of the per-leaf arrays."""

    def __init__(self, tree):
        self.tree = tree
        s = tree.samples
        n = len(s)
        self.vals = np.concatenate([np.asarray(s.gather(np.arange(n)), np.float64),
                                    np.asarray(s.uv, np.float64)], axis=1)   # (S, 14): + uv
        self.patch = np.asarray(s.patch).astype(np.int64)
        self.null = np.asarray(s.null).astype(bool)
        self.hash = np.asarray(s.tree).astype(np.int64)
        class_of = np.asarray(tree.class_of).astype(np.int64)
        self.cls = np.where(self.patch >= 0, class_of[np.maximum(self.patch, 0)], -1)
        self.class_of = class_of
        self.ev_patch = np.asarray(s.ev_patch).astype(np.int64)
        self.extra = {int(node): e for e, node in enumerate(np.asarray(tree.ex_node))}
        self.dir_depth = int(tree.params.direction_depth)
        self.diag = float(tree.diag)

    def class_path(self, s):
        """The classes of sample ``s``'s first-hit patch and recorded events' patches."""
        return (int(self.cls[s]),) + tuple(int(self.class_of[p]) for p in self.ev_patch[s]
                                           if p >= 0)

    def cube_scale(self, leaf, tree_id, lx, ly):
        """|(1, u, v)| at the cell-local point (lx, ly) of direction leaf ``leaf`` of direction
        tree ``tree_id`` (the perspective weight of a sample's output direction)."""
        f = self.tree.dir_forest
        u0, u1, v0, v1 = (float(x) for x in f.domain[tree_id])
        size = 2.0 ** -int(f.level[leaf])
        u = u0 + (u1 - u0) * (int(f.ix[leaf]) + lx) * size
        v = v0 + (v1 - v0) * (int(f.iy[leaf]) + ly) * size
        return math.sqrt(1.0 + u * u + v * v)


# --------------------------------------------------------------------------- small rules
def bilinear(lx, ly):
    return [(1 - lx) * (1 - ly), lx * (1 - ly), (1 - lx) * ly, lx * ly]


def barycentric(q, tri):
    """Barycentric coordinates of q in triangle tri (three (x, y)); None if degenerate."""
    (ax, ay), (bx, by), (cx, cy) = tri
    e1x, e1y, e2x, e2y = bx - ax, by - ay, cx - ax, cy - ay
    wx, wy = q[0] - ax, q[1] - ay
    det = e1x * e2y - e1y * e2x
    if not abs(det) > DEGENERATE_AREA:
        return None
    l1 = (wx * e2y - wy * e2x) / det
    l2 = (e1x * wy - e1y * wx) / det
    return [1 - l1 - l2, l1, l2]


def triangle_kind(lam, extrapolation):
    """TRIANGLE inside, EXTRAPOLATED outside but within the allowance, else FAIL."""
    if lam is None:
        return FAIL
    if min(lam) >= -INSIDE_SLACK:
        return TRIANGLE
    if extrapolation is not None and min(lam) >= -float(extrapolation):
        return EXTRAPOLATED
    return FAIL


def cell_weights(usable, q, extrapolation=None):
    """Weights over a cell's four corners from its usable ones, and the kind."""
    n = sum(bool(x) for x in usable)
    if n == 4:
        return bilinear(q[0], q[1]), BILINEAR
    w = [0.0] * 4
    if n == 3:
        idx = [c for c in range(4) if usable[c]]
        lam = barycentric(q, [CORNERS[c] for c in idx])
        kind = triangle_kind(lam, extrapolation)
        if kind != FAIL:
            for c, x in zip(idx, lam):
                w[c] = x
        return w, kind
    return w, FAIL


def pick_triangle(q, tris, extrapolation):
    """The first of the candidate triangles (list of 1 or 2 vertex-position triples) that
    contains q; else extrapolation over the last one. Returns (index, lam, kind)."""
    lams = [barycentric(q, t) for t in tris]
    for k, lam in enumerate(lams):
        if lam is not None and min(lam) >= -INSIDE_SLACK:
            return k, lam, TRIANGLE
    last = len(tris) - 1
    if extrapolation is not None and lams[last] is not None \
            and min(lams[last]) >= -float(extrapolation):
        return last, lams[last], EXTRAPOLATED
    return 0, None, FAIL


def far_matrix(vals, used, chord, dist):
    """Paper 5.3: K x K booleans, True for pairs of used interpolants (rows of ``vals``: out_o,
    out_d, point, normal, ...) whose output directions differ by a chord above ``chord`` or
    whose output origins lie more than ``dist`` apart (None: no limit), by |a - b|^2."""
    used = np.asarray(used, bool)
    vals = np.asarray(vals, np.float64).reshape(len(used), -1) if len(used) else np.zeros((0, 12))
    far = np.zeros((len(vals), len(vals)), bool)
    for lo, lim in ((3, chord), (0, dist)):
        if lim is not None:
            p = vals[:, lo:lo + 3]
            far |= ((p[:, None, :] - p[None, :, :]) ** 2).sum(axis=2) > lim * lim
    return far & used[:, None] & used[None, :]


def drop_outlier(far, used, pos, q):
    """far: K x K booleans; used: K booleans; pos: K (x, y); q: the query's (x, y). Returns
    (used, had_far_pair): the used one in most far pairs is dropped (ties: farthest from q,
    then lowest index); if a far pair remains, none is used."""
    K = len(used)
    pair = [[bool(far[i][j]) and used[i] and used[j] for j in range(K)] for i in range(K)]
    deg = [sum(row) for row in pair]
    if not any(deg):
        return list(used), False
    dist = [math.sqrt((p[0] - q[0]) ** 2 + (p[1] - q[1]) ** 2) for p in pos]
    best = None
    for i in range(K):
        if used[i] and (best is None or (deg[i], dist[i]) > (deg[best], dist[best])):
            best = i
    out = list(used)
    out[best] = False
    if any(pair[i][j] and out[i] and out[j] for i in range(K) for j in range(K)):
        out = [False] * K
    return out, True


# --------------------------------------------------------------------------- one ray
@dataclass
class Cell:
    """A located query ray: viewpoint cell weights, four direction leaves, 16 sample ids."""

    alpha: float
    beta: float
    vnode: int              # the viewpoint cell (a viewpoint-forest leaf)
    leaves: list            # 4 direction-forest nodes (one per viewpoint corner)
    trees: list             # their direction trees
    lq: list                # 4 cell-local query points (lx, ly)
    ids: list               # 4 x 4 sample ids


@dataclass
class Answer:
    ans: int
    why: int = 0
    out_origin: np.ndarray | None = None
    out_dir: np.ndarray | None = None
    point: np.ndarray | None = None
    normal: np.ndarray | None = None
    cls: int = -1
    info: dict = field(default_factory=dict)     # for reading a disagreement


def locate(tree, o, d, tmax):
    """Per ray: MISS, OUTSIDE or its Cell (rule 1)."""
    t_in, face, x, y, inside = entry_points(tree, o[None], d[None])
    t_in, face, x, y, inside = float(t_in[0]), int(face[0]), x[:1], y[:1], bool(inside[0])
    if inside:
        return OUTSIDE
    if not (math.isfinite(t_in) and t_in < tmax):
        return MISS
    vnode, alpha, beta = tree.vp_forest.locate(np.array([face]), x, y)
    vnode = int(vnode[0])
    if vnode < 0:
        return OUTSIDE
    vps = [int(v) for v in tree.vp_forest.corner[vnode]]
    cf, u, v = dir_to_cube(d[None])
    slot = int(SLOT[face, int(cf[0])])
    if min(vps) < 0 or slot < 0:
        return OUTSIDE
    u, v = float(u[0]), float(v[0])
    trees = [5 * vp + slot for vp in vps]
    leaf, lx, ly = tree.dir_forest.locate(np.array(trees), np.full(4, u), np.full(4, v))
    ids = []
    for k in range(4):
        if leaf[k] < 0:
            return OUTSIDE
        r0, r1, r2, r3 = (float(x) for x in tree.dir_rect[trees[k]])
        if not (r0 <= u <= r1 and r2 <= v <= r3):
            return OUTSIDE
        c = [int(s) for s in tree.dir_forest.corner[leaf[k]]]
        if min(c) < 0:
            return OUTSIDE
        ids.append(c)
    return Cell(float(alpha[0]), float(beta[0]), vnode, [int(x) for x in leaf], trees,
                [(float(lx[k]), float(ly[k])) for k in range(4)], ids)


def candidates(data, cell):
    """Two-patch rule (rule 2): ('traced' | 'one' | 'two', class or candidate patches)."""
    flat = [s for row in cell.ids for s in row]
    classes = sorted({int(data.cls[s]) for s in flat})
    if len(classes) > 2:
        return "traced", classes
    if len(classes) == 1:
        return "one", classes[0]
    return "two", sorted({int(data.patch[s]) for s in flat if data.patch[s] >= 0})


def finish(ans, o, d, tmax, oo, od, pt, nm, cls, info, once=None, exact_hit=None):
    """The hidden rule and the output of an interpolated ray (rule 11); ``once`` (rule 12, None:
    not asked): the ray leaves from its first hit pt along d mirrored in the plane normal to
    nm; ``exact_hit`` (rule 13, with once): a function (pt, nm) -> the exact (point, normal)
    replacing them, or None."""
    t_first = float(np.dot(pt - o, d))
    if t_first >= tmax:
        return Answer(MISS, 0, info={**info, "hidden": True})
    if float(np.dot(nm, d)) > 0:
        nm = -nm
    if once and exact_hit is not None:
        hit = exact_hit(pt, nm)
        if hit is not None:
            pt, nm = hit
            info = {**info, "newton": True}
    if once:
        oo, od = pt, d - 2.0 * float(np.dot(d, nm)) * nm
    if once is not None:
        info = {**info, "once": once}
    return Answer(ans, 0, oo, od, pt, nm, cls, info)


def reflects_once(data, cell, pc):
    """Rule 12's condition: the object is a mirror and every usable sample of the ray (corners
    and the four leaves' extra samples of class pc, not null) left the object where it first
    hit it (output origin = first-hit point)."""
    if not data.mirror:
        return False
    ids = [s for row in cell.ids for s in row]
    for leaf in cell.leaves:
        e = data.extra.get(int(leaf))
        if e is not None:
            ids += [int(s) for s in data.tree.ex_ids[e]]
    return all(np.linalg.norm(data.vals[s, 0:3] - data.vals[s, 6:9]) <= 1e-9 * data.diag
               for s in ids if data.cls[s] == pc and not data.null[s])


def one_patch(data, cell, pc):
    """Rule 13's condition: the usable samples of rule 12 all hit one NURBS patch: its id, or
    None."""
    ids = [s for row in cell.ids for s in row]
    for leaf in cell.leaves:
        e = data.extra.get(int(leaf))
        if e is not None:
            ids += [int(s) for s in data.tree.ex_ids[e]]
    pids = {int(data.patch[s]) for s in ids if data.cls[s] == pc and not data.null[s]}
    if len(pids) != 1:
        return None
    p = pids.pop()
    return p if data.tracer.object.patches[p].surface is not None else None


def nearest_on_patch(data, patch, o, d, tmax, first=None):
    """Rule 13's hit: a function (pt, nm) -> (point, normal facing d) of the ray's nearest hit
    on ``patch`` (the exact tracer restricted to it; ``first``: the ray's known exact first
    hit against every patch, a PatchHit of one row, used instead) where it lies near pt, nm;
    else None."""
    def hit(pt, nm):
        h = first if first is not None else data.tracer.intersect(
            o[None], d[None], tmax=np.array([tmax]), patches=np.array([[patch]]))
        if not h.hit[0] or int(h.patch[0]) != patch:
            return None
        n = h.normal[0] if float(np.dot(h.normal[0], d)) <= 0 else -h.normal[0]
        if np.linalg.norm(h.point[0] - pt) > NEWTON_MAX_MOVE_REL * data.diag \
                or float(np.dot(n, nm)) < np.cos(np.radians(NEWTON_MAX_TURN_DEG)):
            return None
        return h.point[0], n
    return hit


def within_tolerance(data, cell, tol):
    """Rule 2b: the errors the bake measured in the ray's four leaves and its viewpoint cell
    are all at most ``tol`` degrees (an unmeasured NaN is not)."""
    t = data.tree
    errs = [float(t.dir_err[lf]) for lf in cell.leaves] + [float(t.vp_err[cell.vnode])]
    return all(e <= tol for e in errs)


def one_hash(data, cell, pc):
    """Rule 2d's path test: the 16 samples of class ``pc`` that are not null share one
    ray-tree hash."""
    return len({int(data.hash[s]) for row in cell.ids for s in row
                if data.cls[s] == pc and not data.null[s]}) <= 1


def one_path(data, cell, pc):
    """Rule 2e: the 16 samples of class ``pc`` that are not null share one path: on a mirror
    the classes of the patches they meet, in order; else their ray-tree hash."""
    if not data.mirror:
        return one_hash(data, cell, pc)
    return len({data.class_path(s) for row in cell.ids for s in row
                if data.cls[s] == pc and not data.null[s]}) <= 1


def paths_allowed(data, cell, pc, opt):
    """Rules 2d and 2e as the options ask: path identity, else one path per blend under a
    tolerance (``one_path``), else nothing to check."""
    if getattr(opt, "path_identity", False):
        return same_path(data, cell, pc)
    if getattr(opt, "max_error_deg", None) is not None and getattr(opt, "one_path", True):
        return one_path(data, cell, pc)
    return True


def same_path(data, cell, pc):
    """Rule 2d: one ray-tree hash, and no leaf nor the cell carries the PATH_CHANGE flag."""
    t = data.tree
    return one_hash(data, cell, pc) \
        and not any(int(t.dir_flags[lf]) & PATH_CHANGE for lf in cell.leaves) \
        and not int(t.vp_flags[cell.vnode]) & PATH_CHANGE


def verified_miss(data, cell, tol):
    """Rule 2c: the ray's leaves and cell are within ``tol`` and none is BOUNDARY-flagged."""
    t = data.tree
    return within_tolerance(data, cell, tol) and \
        not any(int(t.dir_flags[lf]) & BOUNDARY for lf in cell.leaves) and \
        not int(t.vp_flags[cell.vnode]) & BOUNDARY


def newton_eligible(data, cell, pc, opt):
    """Rules 12 and 13 both apply to the ray (a mirror, its usable samples reflect once off
    one NURBS patch)."""
    return bool(getattr(opt, "mirror_rays", "interpolate") == "newton"
                and data.mirror and reflects_once(data, cell, pc)
                and one_patch(data, cell, pc) is not None)


def cell_errors(data, cell):
    """The bake's measured errors of the ray's four leaves and its viewpoint cell (degrees)."""
    t = data.tree
    return [float(t.dir_err[lf]) for lf in cell.leaves] + [float(t.vp_err[cell.vnode])]


def calm(data, cell, first_known):
    """Rule 13's tolerance bypass: none of the ray's leaves and its cell carries PATH_CHANGE,
    nor BOUNDARY unless the ray's exact first hit is known; the bake measured a finite error
    in every one of them, or, where the exact first hit is known, saw none answered wrongly
    (no inf; NaN, not measured, is allowed)."""
    t = data.tree
    flags = [int(t.dir_flags[lf]) for lf in cell.leaves] + [int(t.vp_flags[cell.vnode])]
    errs = cell_errors(data, cell)
    measured = all(math.isfinite(e) for e in errs) or \
        (first_known and not any(math.isinf(e) for e in errs))
    return measured and not any(f & PATH_CHANGE for f in flags) \
        and (first_known or not any(f & BOUNDARY for f in flags))


def answer_ri(data, cell, pc, o, d, tmax, opt, first=None):
    """Rules 2b-11 for a located ray whose class is ``pc`` (>= 0); ``first``: its exact first
    hit against every patch (a PatchHit of one row) where known (a two-class ray)."""
    tol = getattr(opt, "max_error_deg", None)
    if tol is not None and not within_tolerance(data, cell, tol):
        traced = Answer(TRACED, WHY_TOLERANCE, info={"pc": pc, "tolerance": True})
        if not (getattr(opt, "mirror_rays", "interpolate") == "newton"
                and data.mirror and calm(data, cell, first is not None)):
            return traced
        if not paths_allowed(data, cell, pc, opt):
            return Answer(TRACED, WHY_PATH, info={"pc": pc, "path": True})
        if not newton_eligible(data, cell, pc, opt):
            return traced
        a = answer_untested(data, cell, pc, o, d, tmax, opt, first)
        if a.info.get("newton"):
            a.info["past_tolerance"] = True
            a.info["unmeasured"] = not all(math.isfinite(e) for e in cell_errors(data, cell))
        return a if a.ans == TRACED or a.info.get("newton") else traced
    return answer_untested(data, cell, pc, o, d, tmax, opt, first)


def answer_untested(data, cell, pc, o, d, tmax, opt, first=None):
    """Rules 2d-11 (after the tolerance)."""
    if not paths_allowed(data, cell, pc, opt):
        return Answer(TRACED, WHY_PATH, info={"pc": pc, "path": True})
    samples = [[data.vals[s] for s in row] for row in cell.ids]
    usable = [[bool(data.cls[s] == pc and not data.null[s]) for s in row] for row in cell.ids]
    thresholds = opt.angle_deg is not None or opt.distance is not None
    chord = None if opt.angle_deg is None else \
        2.0 * math.sin(min(math.radians(opt.angle_deg), math.pi) / 2)
    dist = None if opt.distance is None else opt.distance * data.diag
    per_sample = thresholds and opt.threshold_on == "samples"
    if per_sample and opt.threshold_leaves == "unverified":
        checked = [int(data.tree.dir_forest.level[lf]) >= data.dir_depth for lf in cell.leaves]
    else:
        checked = [True] * 4
    info = {"pc": pc}

    # rule 4: per-sample thresholds inside each direction leaf
    thr_hit = [False] * 4
    if per_sample:
        info["unchecked"] = sum(not c for c in checked)
        for k in range(4):
            use = [usable[k][c] and checked[k] for c in range(4)]
            far = far_matrix(samples[k], use, chord, dist)
            before = sum(usable[k])
            usable[k], thr_hit[k] = drop_outlier(far, usable[k], CORNERS, cell.lq[k])
            if thr_hit[k] and sum(usable[k]) == before - 1:
                info["dq_drop"] = info.get("dq_drop", 0) + 1

    # rule 5: weights per direction leaf over up to 6 samples (4 corners + 2 extras)
    w = [[0.0] * 6 for _ in range(4)]
    sid = [list(row) + [None, None] for row in cell.ids]
    pos = [list(CORNERS) + [(0.0, 0.0), (0.0, 0.0)] for _ in range(4)]
    kind = [FAIL] * 4
    is_extra = [False] * 4
    for k in range(4):
        wk, kind[k] = cell_weights(usable[k], cell.lq[k], opt.extrapolation)
        w[k][:4] = wk
        if kind[k] == FAIL:
            ex = extra_weights(data, cell.leaves[k], usable[k], pc, cell.lq[k], opt.extrapolation)
            if ex is not None:
                w[k], (sid[k][4], sid[k][5]), (pos[k][4], pos[k][5]), kind[k], path = ex
                info.setdefault("extra", []).append(path)
                is_extra[k] = True
                samples[k] = samples[k] + [data.vals[sid[k][4]], data.vals[sid[k][5]]]
    info["dq_kind"] = list(kind)
    ok = [kind[k] != FAIL for k in range(4)]

    # rule 6: intermediate rays, perspective-weighted directions
    inter = []
    for k in range(4):
        acc = np.zeros(14)
        for j in range(6):
            if w[k][j] != 0.0:
                val = samples[k][j].copy()
                val[3:6] *= data.cube_scale(cell.leaves[k], cell.trees[k], *pos[k][j])
                acc += w[k][j] * val
        inter.append(acc)

    # rule 7: thresholds at the viewpoint level
    thr_q = False
    aq = (cell.alpha, cell.beta)
    if thresholds:
        if per_sample:
            members = []
            for k in range(4):
                if is_extra[k]:
                    mem = [j for j in range(6) if w[k][j] != 0.0]
                else:
                    mem = [j for j in range(4) if usable[k][j]]
                members.append(mem if ok[k] and checked[k] else [])
            # all members of the four leaves in one list; a leaf pair is far when any of
            # their members are
            owner = [k for k in range(4) for _ in members[k]]
            far = far_matrix([samples[k][j] for k in range(4) for j in members[k]],
                             [True] * len(owner), chord, dist)
            blocks = [[False] * 4 for _ in range(4)]
            for i, j in zip(*np.nonzero(far)):
                blocks[owner[i]][owner[j]] = True
            for k in range(4):
                if blocks[k][k]:
                    thr_hit[k] = True
                    ok[k] = False
        else:
            idir = [x[3:6] / max(float(np.linalg.norm(x[3:6])), 1e-300) for x in inter]
            rays = [np.concatenate([inter[k][0:3], idir[k], np.zeros(6)]) for k in range(4)]
            blocks = far_matrix(rays, ok, chord, dist)
        n_ok = sum(ok)
        ok, thr_q = drop_outlier(blocks, ok, CORNERS, aq)
        if thr_q and sum(ok) == n_ok - 1:
            info["vp_drop"] = True
    info["dq_ok"] = list(ok)

    # rule 8: combination over the viewpoint cell
    W, qkind = cell_weights(ok, aq, opt.extrapolation)
    few = qkind == FAIL
    cut = few and (thr_q or any(thr_hit[k] and not ok[k] for k in range(4)))
    few = few and not cut
    out = sum(W[k] * inter[k] for k in range(4))
    od, nm = out[3:6], out[9:12]
    lod, lnm = float(np.linalg.norm(od)), float(np.linalg.norm(nm))
    blend = lod > MIN_BLEND_NORM and lnm > MIN_BLEND_NORM
    if not few and not cut and blend:
        worst = max([BILINEAR, qkind] + [kind[k] for k in range(4) if ok[k]])
        once = reflects_once(data, cell, pc) \
            if getattr(opt, "mirror_rays", "interpolate") != "interpolate" \
            and data.mirror else None
        exact_hit = None
        if once and getattr(opt, "mirror_rays", "interpolate") == "newton":
            patch = one_patch(data, cell, pc)
            exact_hit = None if patch is None else nearest_on_patch(data, patch, o, d, tmax,
                                                                     first)
        return finish(KIND_CODE[worst], o, d, tmax, out[0:3], od / lod, out[6:9], nm / lnm,
                      pc, info, once, exact_hit)
    why = WHY_USABLE if few else WHY_THRESHOLD if cut else WHY_BLEND
    if few and opt.null_interp:
        nul = answer_null(data, cell, pc, o, d, tmax, info)
        if nul is not None:
            return nul
    return Answer(TRACED, why, info=info)


def extra_weights(data, leaf, usable, pc, q, extrapolation):
    """Rule 5's extra samples (paper 4.3, Figure 12) for a leaf whose corners alone fail:
    (weights over 6 slots, (id4, id5), (pos4, pos5), kind, path) or None; path = (cell kind
    1/2, side "L"/"A"/"B", triangle index, TRIANGLE/EXTRAPOLATED) says which rule answered."""
    e = data.extra.get(int(leaf))
    if e is None:
        return None
    t = data.tree
    ekind = int(t.ex_kind[e])
    exc = [int(c) for c in t.ex_corner[e]]
    exi = [int(s) for s in t.ex_ids[e]]
    exp = [(float(p[0]), float(p[1])) for p in np.asarray(t.ex_pos[e], np.float64)]
    ex_use = [bool(data.cls[s] == pc and not data.null[s]) for s in exi]
    n_use = sum(usable)
    if ekind == 1:                         # one-interpolant: lone corner L, v1, v2 in its class
        L = exc[0]
        if not (usable[L] and n_use == 1 and ex_use[0] and ex_use[1]):
            return None
        e_ids, e_pos = (exi[0], exi[1]), (exp[0], exp[1])
        tris = [(L, 4, 5)]
        side = "L"
    elif ekind == 2:                       # two-interpolant: the usable side (A or B) and its pair
        A, B = exc[0:2], exc[2:4]
        if usable[A[0]] and usable[A[1]] and n_use == 2 and ex_use[0] and ex_use[1]:
            (c1, c2), e_ids, e_pos = A, (exi[0], exi[1]), (exp[0], exp[1])
            side = "A"
        elif usable[B[0]] and usable[B[1]] and n_use == 2 and ex_use[2] and ex_use[3]:
            (c1, c2), e_ids, e_pos = B, (exi[2], exi[3]), (exp[2], exp[3])
            side = "B"
        else:
            return None
        tris = [(c1, c2, 4), (c2, 4, 5)]
    else:
        return None
    slot_pos = list(CORNERS) + list(e_pos)
    which, lam, kind = pick_triangle(q, [[slot_pos[s] for s in tri] for tri in tris],
                                     extrapolation)
    if kind == FAIL:
        return None
    w = [0.0] * 6
    for s, x in zip(tris[which], lam):
        w[s] += x
    return (w, e_ids, e_pos, (EXTRAPOLATED if kind == EXTRAPOLATED else EXTRA),
            (ekind, side, which, kind))


def answer_null(data, cell, pc, o, d, tmax, info):
    """Rule 10: the null samples of the query's class as interpolants."""
    use = [[bool(data.cls[s] == pc and data.null[s]) for s in row] for row in cell.ids]
    if not any(any(row) for row in use):
        return None
    wk, ok = [], []
    for k in range(4):
        w, kind = cell_weights(use[k], cell.lq[k])
        wk.append(w)
        ok.append(kind != FAIL)
    W, qkind = cell_weights(ok, (cell.alpha, cell.beta))
    if qkind == FAIL:
        return None
    pt, nm = np.zeros(3), np.zeros(3)
    for k in range(4):
        for c in range(4):
            x = W[k] * wk[k][c]
            if x != 0.0:
                v = data.vals[cell.ids[k][c]]
                pt += x * v[6:9]
                nm += x * v[9:12]
    ln = float(np.linalg.norm(nm))
    if not ln > MIN_BLEND_NORM:
        return None
    return finish(NULL_S, o, d, tmax, pt, np.zeros(3), pt, nm / ln, pc, {**info, "null": True})


def answer_raytree(data, cell, o, d, tmax):
    """Policy "raytree" for a located ray."""
    flat = [s for row in cell.ids for s in row]
    same = len({int(data.hash[s]) for s in flat}) == 1 and \
        len({int(data.cls[s]) for s in flat}) == 1 and not any(data.null[s] for s in flat)
    if not same:
        return Answer(TRACED, WHY_RAYTREE)
    c = int(data.cls[flat[0]])
    if c == -1:
        return Answer(MISS)
    W = bilinear(cell.alpha, cell.beta)
    out = np.zeros(14)
    for k in range(4):
        wk = bilinear(*cell.lq[k])
        for j in range(4):
            val = data.vals[cell.ids[k][j]].copy()
            val[3:6] *= data.cube_scale(cell.leaves[k], cell.trees[k], *CORNERS[j])
            out += W[k] * wk[j] * val
    od, nm = out[3:6], out[9:12]
    if not (np.linalg.norm(od) > MIN_BLEND_NORM and np.linalg.norm(nm) > MIN_BLEND_NORM):
        return Answer(TRACED, WHY_BLEND)
    return finish(FULL, o, d, tmax, out[0:3], od / np.linalg.norm(od), out[6:9],
                  nm / np.linalg.norm(nm), c, {})


# --------------------------------------------------------------------------- many rays
class Reference:
    """The reference for rays (o, d, tmax) on ``tree`` (SceneTracer ``st``). Location and the
    exact first hits depend only on the rays, so they are computed once; ``answer(options)``
    then applies the rules ray by ray."""

    def __init__(self, tree, st, o, d, tmax):
        self.data = TreeData(tree)
        self.data.mirror = st.scene.object.material.kind == "mirror"
        self.data.tracer = st.tracer
        self.o = np.asarray(o, np.float64)
        self.d = np.asarray(d, np.float64)
        self.tmax = np.asarray(tmax, np.float64)
        self.cells = [locate(tree, self.o[i], self.d[i], float(self.tmax[i]))
                      for i in range(len(self.o))]
        self.rule2 = [candidates(self.data, c) if isinstance(c, Cell) else None
                      for c in self.cells]
        # the exact first hit of every located ray against all patches (rule 2c)
        located = [i for i, c in enumerate(self.cells) if isinstance(c, Cell)]
        self.any_hit = {}
        if located:
            hit = st.tracer.intersect(self.o[located], self.d[located], tmax=self.tmax[located])
            self.any_hit = {i: bool(h) for i, h in zip(located, hit.hit)}
            self.any_first, self.any_row = hit, {i: row for row, i in enumerate(located)}
        # the exact first hit of each two-class ray against only its candidate patches
        two = [i for i, r in enumerate(self.rule2) if r is not None and r[0] == "two"]
        self.first_hit = {}
        if two:
            cand = -np.ones((len(two), 16), np.int64)
            for row, i in enumerate(two):
                cand[row, :len(self.rule2[i][1])] = self.rule2[i][1]
            hit = st.tracer.intersect(self.o[two], self.d[two], tmax=self.tmax[two],
                                      patches=cand)
            for row, i in enumerate(two):
                self.first_hit[i] = int(hit.cls[row]) if hit.hit[row] else -1

    def query_class(self, i):
        """Rule 2 for ray i: the class (-1: miss), or None (more than two classes)."""
        kind, val = self.rule2[i]
        if kind == "traced":
            return None
        return val if kind == "one" else self.first_hit[i]

    def answer_one(self, i, opt) -> Answer:
        cell = self.cells[i]
        if not isinstance(cell, Cell):
            return Answer(cell)
        o, d, tmax = self.o[i], self.d[i], float(self.tmax[i])
        if opt.policy == "raytree":
            return answer_raytree(self.data, cell, o, d, tmax)
        pc = self.query_class(i)
        many = pc is None
        if many and opt.many_classes == "trace":
            return Answer(TRACED, WHY_CLASSES)
        if many:
            row = self.any_row[i]
            pc = int(self.any_first.cls[row]) if self.any_first.hit[row] else -1
            if pc not in self.rule2[i][1] and pc != -1:
                return Answer(TRACED, WHY_UNSAMPLED, info={"unsampled": True})
        if pc == -1:
            info = {"pc": -1, "two_class": self.rule2[i][0] == "two"}
            tol = getattr(opt, "max_error_deg", None)
            if tol is not None and not verified_miss(self.data, cell, tol) and self.any_hit[i]:
                return Answer(TRACED, WHY_UNSAMPLED, info={**info, "unsampled": True})
            return Answer(MISS, info=info)
        first = self.any_first.take([self.any_row[i]]) \
            if self.rule2[i][0] in ("two", "traced") else None
        rec = answer_ri(self.data, cell, pc, o, d, tmax, opt, first)
        rec.info["two_class"] = self.rule2[i][0] == "two"
        return rec

    def answer(self, opt):
        """Per-ray answers as arrays: ans, why (int8), out_origin, out_dir, point, normal
        ((N, 3), NaN where not interpolated), cls (-1 where not interpolated), and the list
        of Answer records."""
        n = len(self.o)
        recs = [self.answer_one(i, opt) for i in range(n)]
        out = {"ans": np.array([r.ans for r in recs], np.int8),
               "why": np.array([r.why for r in recs], np.int8),
               "cls": np.array([r.cls for r in recs], np.int64), "records": recs}
        for k in ("out_origin", "out_dir", "point", "normal"):
            a = np.full((n, 3), np.nan)
            for i, r in enumerate(recs):
                if getattr(r, k) is not None:
                    a[i] = getattr(r, k)
            out[k] = a
        return out
