"""Newton's method on (s, t) of rational Bezier nets seen end-on along their rays.

A ray is written as the intersection of two planes through it (``ray_planes``); each net is
projected onto them once per (ray, net) pair (``project_nets``: two scalar nets and the weights),
which also serves the end-on convex-hull test (``hull_meets``). Each iteration then evaluates
three scalar polynomials and solves a 2x2 system (``newton``), from seeds on the net's corner
triangles (``newton_seed``). Given bounds of the nets' second partials
(``second_derivative_bounds``), a run stops after the step whose end Taylor's remainder proves
within tolerance, without evaluating it. Distances are in scene units (metres); (s, t) are
net-local, in [0, 1]^2.
"""

from __future__ import annotations

import numpy as np

from ..geometry import bezier as bz

# Newton convergence: residual distance from the ray, relative to the object diagonal.
# Double precision evaluation of a degree <= 5 patch is good to ~1e-15 relative.
NEWTON_TOL_REL = 1e-11
NEWTON_ITERS = 12
# Largest Newton step in local parameter units, per component: clipping keeps wild steps inside
# the patch. Each component is clipped on its own: next to a collapsed edge (a pole) the step
# along the edge is huge and meaningless (S_s ~ 0 there), while the step away from it is small
# and right; scaling both by one factor stalled the runs on the edge for many iterations.
MAX_STEP = 0.5
# Seeds: a plane hit outside the extended corner triangles (barycentric margin) seeds at the
# sub-patch midpoint instead.
SEED_MARGIN = 0.25
# A singular Newton Jacobian counts as a collapsed edge (least-squares step) when one of its
# columns is below this fraction of its norm: a pole's S_s is rounding noise there (~1e-13),
# while a ray lying in the tangent plane makes the columns parallel, both of the norm's size.
COLLAPSED_COLUMN_REL = 1e-6
# Newton runs iterated together: their working arrays (~1 kB a run) stay in a core's cache.
NEWTON_BLOCK = 4096
# Angular slack (rad) of the end-on hull test: a line within rounding of the hull's boundary
# (or through a control point, angle of a zero vector) counts as meeting it.
HULL_GAP_SLACK = 1e-9
# A control point this close to the line (relative to the farthest) is on it: meeting.
HULL_POINT_REL = 1e-12


def newton(proj, p, q, s, t, tol, stats, bound=None):
    """Newton iterations in place on (s, t) for nets of degree (p, q) projected onto their
    rays' planes (``project_nets``: proj (n, (p+1)(q+1), 3)); returns the converged mask: the
    residual distance from the ray is at most ``tol`` (m). Each step component is clipped to
    MAX_STEP; at a singular Jacobian the step is the least-squares one; runs that leave
    [-1, 2]^2 or meet a zero Jacobian stop unconverged. The live runs are kept packed (no
    per-iteration gathers); ``stats["newton_iters"]`` counts the run-iterations.

    With A, B, W the projected nets' values, the ray planes' residuals are f1 = A / W,
    f2 = B / W (distances of the surface point from the planes) and their partials
    (A_s - W_s f1) / W etc.: the rational surface's, without forming its points.

    ``bound`` (n, 3): the nets' ``second_derivative_bounds``, or None. With it a full step
    within [0, 1]^2 ends the run converged, unevaluated, where Taylor's remainder proves the
    residual at its end at most tol / 2 (``_proven``): quadratic convergence makes the last
    step's size bound the error, so no confirming iteration is spent."""
    ok = np.zeros(len(s), bool)
    for lo in range(0, len(s), NEWTON_BLOCK):         # blocks stay in cache
        hi = min(lo + NEWTON_BLOCK, len(s))
        ok[lo:hi] = _newton_block(proj[lo:hi], p, q, s[lo:hi], t[lo:hi], tol, stats,
                                  None if bound is None else bound[lo:hi])
    return ok


def _proven(bd, ss, tt, ds, dt, tol):
    """Whether the Newton step (-ds, -dt) from (ss, tt) ends within tol / 2 of the ray.

    f(x + D) = f(x) + J D + R with f(x) + J D = 0 for a full Newton step, and the residual's
    rows are the unit ray-plane normals dotted with the surface S, so |R| <= |S(x + D) - S(x)
    - S'(x) D| <= (Mss Ds^2 + 2 Mst |Ds Dt| + Mtt Dt^2) / 2 (Taylor, with ``bd`` = (Mss, Mst,
    Mtt) bounding the second partials on [0, 1]^2, which holds the whole step)."""
    a, b = np.abs(ds), np.abs(dt)
    full = np.maximum(a, b) <= MAX_STEP
    a, b = np.minimum(a, MAX_STEP), np.minimum(b, MAX_STEP)             # (no overflow)
    rem = (bd[:, 0] * a + 2.0 * bd[:, 1] * b) * a + bd[:, 2] * b * b
    # both ends in [0, 1]^2 (|x - 1/2| <= 1/2), the whole step with them
    return (full & (rem <= tol) & (np.maximum(np.abs(ss - 0.5), np.abs(ss - ds - 0.5)) <= 0.5)
            & (np.maximum(np.abs(tt - 0.5), np.abs(tt - dt - 0.5)) <= 0.5))


def _newton_block(proj, p, q, s, t, tol, stats, bound):
    """newton on one block (s, t: views, updated in place)."""
    ok = np.zeros(len(s), bool)
    act = np.arange(len(s))
    fa, ss, tt, bd = proj, s.copy(), t.copy(), bound
    for _ in range(NEWTON_ITERS):
        if len(act) == 0:
            break
        stats["newton_iters"] += len(act)
        H = bz.tensor_weights(ss, tt, p, q, 1) @ fa         # (k, partial S/Ss/St, A/B/W)
        w = H[:, 0, 2]
        f1 = H[:, 0, 0] / w
        f2 = H[:, 0, 1] / w
        conv = np.hypot(f1, f2) <= tol
        a = (H[:, 1, 0] - H[:, 1, 2] * f1) / w
        b = (H[:, 2, 0] - H[:, 2, 2] * f1) / w
        c = (H[:, 1, 1] - H[:, 1, 2] * f2) / w
        e = (H[:, 2, 1] - H[:, 2, 2] * f2) / w
        det = a * e - b * c
        sing = ~(np.abs(det) > 1e-300 + 1e-14 * (np.abs(a * e) + np.abs(b * c)))
        # a rank-one Jacobian on a collapsed edge (one column, S_s or S_t, vanishes): the
        # least-squares step J^T f / |J|^2 moves off the edge. A singular Jacobian whose
        # columns are both alive is a ray in the tangent plane (on a flat patch, a ray in
        # its plane), whose crossing is undefined: that run ends, as does a zero Jacobian
        col_s, col_t = a * a + c * c, b * b + e * e
        frob = col_s + col_t
        collapsed = np.minimum(col_s, col_t) <= COLLAPSED_COLUMN_REL ** 2 * frob
        dead = sing & ~((frob > 1e-300) & collapsed)
        safe = np.where(sing, np.where(dead, 1.0, frob), det)
        ds = np.where(sing, a * f1 + c * f2, e * f1 - b * f2) / safe
        dt = np.where(sing, b * f1 + e * f2, a * f2 - c * f1) / safe
        # a full step (no clipping: |ds|, |dt| <= MAX_STEP) proven to land within tolerance
        proven = False if bd is None else ~sing & _proven(bd, ss, tt, ds, dt, tol)
        ss -= np.where(conv, 0.0, np.clip(ds, -MAX_STEP, MAX_STEP))
        tt -= np.where(conv, 0.0, np.clip(dt, -MAX_STEP, MAX_STEP))
        conv = conv | proven
        done = conv | dead | (ss < -1.0) | (ss > 2.0) | (tt < -1.0) | (tt > 2.0)
        if done.any():
            ok[act[conv]] = True
            s[act[done]] = ss[done]
            t[act[done]] = tt[done]
            keep = ~done
            act, fa, ss, tt = act[keep], fa[keep], ss[keep], tt[keep]
            bd = None if bd is None else bd[keep]
    s[act] = ss
    t[act] = tt
    return ok


def second_derivative_bounds(ctrl):
    """Upper bounds (n, 3) of |S_ss|, |S_st|, |S_tt| (scene units per local parameter unit
    squared) on [0, 1]^2 for rational Bezier nets ``ctrl`` (n, p+1, q+1, 4), weights > 0.

    With Y = S - c (c the control points' centroid), P = w Y's homogeneous net and w the
    weights: Y_s = (P_s - w_s Y) / w, Y_ss = (P_ss - 2 w_s Y_s - w_ss Y) / w, Y_st = (P_st - w_s
    Y_t - w_t Y_s - w_st Y) / w; each polynomial partial is at most its degree factor times the
    largest forward difference of its net (the Bernstein weights are >= 0 and sum to 1 on
    [0, 1]^2), |Y| at most the farthest control point from c, w at least the least weight."""
    p, q = ctrl.shape[1] - 1, ctrl.shape[2] - 1
    w = ctrl[..., 3]
    X = ctrl[..., :3] / w[..., None]
    c = X.mean(axis=(1, 2))
    R = np.linalg.norm(X - c[:, None, None], axis=-1).max(axis=(1, 2))
    P = ctrl[..., :3] - w[..., None] * c[:, None, None]

    def diff(net, ks, kt):
        """Degree factor times the largest norm of the (ks, kt)-th forward difference."""
        if ks > p or kt > q:
            return np.zeros(len(net))
        for _ in range(ks):
            net = net[:, 1:] - net[:, :-1]
        for _ in range(kt):
            net = net[:, :, 1:] - net[:, :, :-1]
        size = np.linalg.norm(net, axis=-1) if net.ndim == 4 else np.abs(net)
        fac = np.prod(np.arange(p - ks + 1, p + 1)) * np.prod(np.arange(q - kt + 1, q + 1))
        return float(fac) * size.max(axis=(1, 2))

    wmin = w.min(axis=(1, 2))
    ws, wt = diff(w, 1, 0), diff(w, 0, 1)
    ys = (diff(P, 1, 0) + ws * R) / wmin
    yt = (diff(P, 0, 1) + wt * R) / wmin
    return np.stack([(diff(P, 2, 0) + 2.0 * ws * ys + diff(w, 2, 0) * R) / wmin,
                     (diff(P, 1, 1) + ws * yt + wt * ys + diff(w, 1, 1) * R) / wmin,
                     (diff(P, 0, 2) + 2.0 * wt * yt + diff(w, 0, 2) * R) / wmin], axis=1)


def ray_planes(d):
    """Two unit normals orthogonal to each direction and to each other (Duff et al.'s basis)."""
    sign = np.where(d[:, 2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + d[:, 2])
    b = d[:, 0] * d[:, 1] * a
    n1 = np.stack([1.0 + sign * d[:, 0] ** 2 * a, sign * b, -sign * d[:, 0]], 1)
    n2 = np.stack([b, sign + d[:, 1] ** 2 * a, -d[:, 1]], 1)
    return n1, n2


def newton_seed(ctrl, ro, rd):
    """Newton seeds (s, t) from the ray's hit on the two triangles spanned by the net's corner
    points (its surface corners); the net's midpoint where the plane hit lies far outside."""
    corners = ctrl[:, [0, -1, 0, -1], [0, 0, -1, -1]]
    cP = corners[..., :3] / corners[..., 3:]
    n = len(ro)
    s = np.full(n, 0.5)
    t = np.full(n, 0.5)
    found = np.zeros(n, bool)
    # triangle A: (00, 10, 11) -> s = b1 + b2, t = b2 ; triangle B: (00, 11, 01) -> s = b1, t = b1 + b2
    for (i1, i2), a_is_s in (((1, 3), True), ((3, 2), False)):
        p0, e1, e2 = cP[:, 0], cP[:, i1] - cP[:, 0], cP[:, i2] - cP[:, 0]
        pv = np.cross(rd, e2)
        det = np.einsum("ij,ij->i", e1, pv)
        usable = np.abs(det) > 1e-300
        safe = np.where(usable, det, 1.0)
        tv = ro - p0
        b1 = np.einsum("ij,ij->i", tv, pv) / safe
        b2 = np.einsum("ij,ij->i", rd, np.cross(tv, e1)) / safe
        hit = usable & (b1 >= -SEED_MARGIN) & (b2 >= -SEED_MARGIN) \
            & (b1 + b2 <= 1.0 + SEED_MARGIN) & ~found
        ls, lt = (b1 + b2, b2) if a_is_s else (b1, b1 + b2)
        s = np.where(hit, np.clip(ls, 0.0, 1.0), s)
        t = np.where(hit, np.clip(lt, 0.0, 1.0), t)
        found |= hit
    return s, t



def project_nets(ctrl, ro, rd):
    """Homogeneous nets ``ctrl`` (n, p+1, q+1, 4) projected onto their rays' two planes
    (``ray_planes``: n_i . x = c_i through the origin ``ro``): (n, (p+1)(q+1), 3) holding per
    control point A = n1 . X - c1 w, B = n2 . X - c2 w and w. A / w and B / w are the point's
    coordinates in the plane seen end-on along the ray, which passes through (0, 0)."""
    n1, n2 = ray_planes(rd)
    h = ctrl.reshape(len(ctrl), -1, 4)
    m = np.zeros((len(h), 4, 3))               # (x, y, z, w) -> (A, B, w): one matmul
    m[:, :3, 0], m[:, :3, 1] = n1, n2
    m[:, 3, 0] = -np.einsum("ij,ij->i", n1, ro)
    m[:, 3, 1] = -np.einsum("ij,ij->i", n2, ro)
    m[:, 3, 2] = 1.0
    return h @ m


def hull_meets(proj):
    """False where the ray certainly misses the net's surface: the ray's line, seen end-on in
    the plane of (n1, n2), lies outside the 2D convex hull of the control points (convex hull
    property; w > 0 keeps the homogeneous points' angles). ``proj``: the projected nets
    (``project_nets``). First the hull's bounding box (all points on one side of one ray plane),
    then the hull itself: the line is outside it when the points' angles around it leave a
    gap wider than pi."""
    f1, f2 = proj[..., 0], proj[..., 1]
    meets = ~((f1.min(1) > 0) | (f1.max(1) < 0) | (f2.min(1) > 0) | (f2.max(1) < 0))
    idx = np.flatnonzero(meets)
    if len(idx):
        a, b = f1[idx], f2[idx]
        ang = np.sort(np.arctan2(b, a), axis=1)
        gap = np.maximum(np.diff(ang, axis=1).max(axis=1), ang[:, 0] + 2 * np.pi - ang[:, -1])
        r = np.hypot(a, b)
        on_point = r.min(axis=1) <= HULL_POINT_REL * r.max(axis=1)
        meets[idx] = (gap <= np.pi + HULL_GAP_SLACK) | on_point
    return meets

