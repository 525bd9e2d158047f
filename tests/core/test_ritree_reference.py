"""TreeQuery against a plain per-ray reference of its rules ("The answers stay the
paper's"): tests/core/ritree_reference.py restates the query rules of commit 3bb980a as a loop
over rays; here both answer the camera rays of small real trees, baked for sample scenes, saved
and loaded back as a render does.

Per ray, over a fixed random subset of each case's rays (the reference is slow):
- the answer code and the why-traced code are identical;
- interpolated rays: output direction and normal within ANGLE_TOL, output origin and first-hit
  point within POINT_TOL x the box diagonal, the same class; ObjectRays.hit / null agree with
  the answer (a miss has no hit, a null answer is null);
- null answers: first-hit point and normal within the same tolerances, the same class.
Both read the same quantized samples (octahedral unit vectors, ~6.5e-5 rad), so the tolerances
only allow for a query that blends in float32 from a decoded table.

test_rules_are_exercised checks that the cases really reach every rule being compared: each
answer kind and why-traced code (but degenerate_blend, which these scenes never reach), the
exact first hit of two-class rays (hit and missed), both kinds of extra-sample cells and both
of a two-interpolant cell's triangles, outlier drops at both levels, the unverified-leaves
option, extrapolation and the hidden rule.

Trees are tiny (viewpoint depth 3, direction depth 5), images 64 x 64, one worker.
"""

from __future__ import annotations

import importlib.util
import math
import sys
from collections import Counter
from pathlib import Path

from dataclasses import replace

import numpy as np
import pytest

from riray.scene.camera import camera_rays
from riray.trace.scene_tracer import SceneTracer
from riray.ritree import tree as ritree
from riray.ritree.bake import bake
from riray.ritree.query import (ANSWER_NAMES, EXTRA_S, EXTRAPOLATED_S, FULL, MISS, NULL_S,
                                OUTSIDE, REDUCED, TRACED, WHY_CLASSES, WHY_NAMES, WHY_RAYTREE,
                                WHY_PATH, WHY_THRESHOLD, WHY_TOLERANCE, WHY_UNSAMPLED,
                                WHY_USABLE, QueryOptions, TreeQuery)
from riray.ritree.region import region_for_cameras
from riray.ritree.tree import BakeParams
from riray.scene.samples import build


def paper(**kw) -> QueryOptions:
    """The paper's rules (no baked-error tolerance, interpolated mirror rays) with options
    ``kw``."""
    return QueryOptions(**{"max_error_deg": None, "mirror_rays": "interpolate",
                            "many_classes": "trace", **kw})


pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

# the helper module next to this file (pytest runs with --import-mode=importlib: tests/core is
# not on sys.path)
_spec = importlib.util.spec_from_file_location(
    "riray_tests_ritree_reference", Path(__file__).with_name("ritree_reference.py"))
ref_mod = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = ref_mod          # dataclasses look their module up there
_spec.loader.exec_module(ref_mod)

ANGLE_TOL = 1e-4        # rad, output directions and normals
POINT_TOL = 1e-5        # x box diagonal, output origins and first-hit points
SIZE = 64               # camera image size (rays) the trees are baked and queried for
SUBSET = 1000           # rays per case compared with the reference
SEED = 20240917

# Query options (name -> QueryOptions) compared per case.
OPTIONS = {
    "angle_off": paper(angle_deg=None),
    "angle20": paper(angle_deg=20.0),
    "angle5": paper(angle_deg=5.0),
    "distance": paper(angle_deg=None, distance=0.05),
    "unverified": paper(angle_deg=20.0, threshold_leaves="unverified"),
    "extrapolation": paper(angle_deg=None, extrapolation=0.25),
    "extrapolation_angle20": paper(angle_deg=20.0, extrapolation=0.25),
    "null": paper(angle_deg=None, null_interp=True),
    "null_angle20": paper(angle_deg=20.0, null_interp=True),
    "null_tolerance_angle20": QueryOptions(angle_deg=20.0, max_error_deg=4.0, null_interp=True),
    "raytree": paper(policy="raytree"),
    "intermediate": paper(angle_deg=20.0, threshold_on="intermediate"),
    "intermediate_dist": paper(angle_deg=None, distance=0.05, threshold_on="intermediate"),
    "tolerance": QueryOptions(angle_deg=None, max_error_deg=1.0),
    "tolerance_mixed_paths": QueryOptions(angle_deg=None, max_error_deg=1.0, one_path=False),
    "tolerance_angle20": QueryOptions(angle_deg=20.0, max_error_deg=4.0),
    "path": paper(angle_deg=None, path_identity=True),
    "tolerance_path": QueryOptions(angle_deg=None, max_error_deg=2.0, path_identity=True),
    "mirror_normal": paper(angle_deg=None, mirror_rays="reflect"),
    "mirror_normal_angle20": paper(angle_deg=20.0, extrapolation=0.25, mirror_rays="reflect"),
    "tolerance_mirror_normal": QueryOptions(angle_deg=None, max_error_deg=2.0,
                                            mirror_rays="reflect"),
    "mirror_newton": paper(angle_deg=None, mirror_rays="newton"),
    "tolerance_mirror_newton": QueryOptions(angle_deg=None, max_error_deg=2.0),   # the default
    "tolerance_path_mirror_newton": QueryOptions(angle_deg=None, max_error_deg=1.0,
                                                 path_identity=True),
}

# Cases: scene, camera baked for, BakeParams, max_events override, extra cameras whose rays are
# also queried (rays outside the baked region), the fraction of rays whose tmax is cut short
# (something in front of the object: the hidden rule, first hits limited by tmax), options.
CASES = {
    "glass_sphere": dict(scene="glass_sphere", camera="close",
                         params=BakeParams(viewpoint_depth=3, direction_depth=5,
                                           viewpoint_refine=1),
                         max_events=None, extra_cameras=("far",), clip=0.0,
                         options=("angle_off", "angle20", "angle5", "distance", "unverified",
                                  "extrapolation", "raytree", "intermediate", "tolerance",
                                  "path")),
    # Newell's teapot: six classes, many two-class rays (exact first hit) and > 2 classes
    "teapot": dict(scene="teapot", camera="close",
                   params=BakeParams(viewpoint_depth=3, direction_depth=5, viewpoint_refine=0),
                   max_events=None, extra_cameras=(), clip=0.0,
                   options=("angle_off", "angle20", "unverified", "extrapolation", "raytree",
                            "intermediate_dist", "tolerance", "tolerance_mixed_paths",
                            "tolerance_path", "mirror_normal",
                            "mirror_normal_angle20", "mirror_newton", "tolerance_mirror_newton")),
    # the glass vase with at most 3 events: rays through both walls are trapped (null)
    "vase_glass_trapped": dict(scene="vase_glass", camera="close",
                               params=BakeParams(viewpoint_depth=3, direction_depth=5,
                                                 viewpoint_refine=0),
                               max_events=3, extra_cameras=(), clip=0.0,
                               options=("angle_off", "angle20", "null", "null_angle20",
                                        "extrapolation_angle20", "tolerance_angle20",
                                        "null_tolerance_angle20")),
    "vase_mirror": dict(scene="vase_mirror", camera="close",
                        params=BakeParams(viewpoint_depth=3, direction_depth=5,
                                          viewpoint_refine=0),
                        max_events=None, extra_cameras=(), clip=0.3,
                        options=("angle_off", "unverified", "extrapolation", "intermediate",
                                 "distance", "tolerance", "tolerance_mirror_normal",
                                 "tolerance_mirror_newton", "tolerance_path_mirror_newton")),
}
PAIRS = [(c, o) for c, spec in CASES.items() for o in spec["options"]]


class Case:
    """A baked, saved and reloaded tree with its query rays, the compared subset and the
    reference (location and exact first hits computed once for all options)."""

    def __init__(self, name, spec, tmp: Path):
        scene = build(spec["scene"])
        if spec["max_events"] is not None:
            scene.render.max_events = spec["max_events"]
        self.scene, self.st = scene, SceneTracer(scene)
        params = spec["params"].validate()
        cam = scene.camera(spec["camera"])
        region = region_for_cameras(self.st, params, [cam], SIZE, SIZE)
        path = tmp / f"{name}.rit"
        ritree.save(bake(self.st, params, region, workers=1), path)
        self.tree = ritree.load(path, scene)
        self.tree.attach_geometry(self.st.tracer)      # the reference reads the samples too
        rays = [camera_rays(cam, SIZE, SIZE)]
        rays += [camera_rays(scene.camera(c), SIZE // 2, SIZE // 2) for c in spec["extra_cameras"]]
        o = np.concatenate([r[0] for r in rays])
        d = np.concatenate([r[1] for r in rays])
        tmax = self.st.env.hit_distance(o, d)
        rng = np.random.default_rng(SEED)
        t_box = self.st.box_entry(o, d)
        cut = rng.random(len(o)) < spec["clip"]
        tmax[cut] = np.minimum(tmax[cut], t_box[cut] + rng.uniform(0.0, 0.5, cut.sum())
                               * self.st.tracer.diag)
        keep = t_box < tmax          # the rays a render asks the object about
        self.o, self.d, self.tmax = o[keep], d[keep], tmax[keep]
        n = len(self.o)
        self.subset = np.sort(rng.choice(n, size=min(SUBSET, n), replace=False))
        self.ref = ref_mod.Reference(self.tree, self.st, self.o[self.subset],
                                     self.d[self.subset], self.tmax[self.subset])
        self.answers = {}

    def reference(self, opt_name):
        if opt_name not in self.answers:
            self.answers[opt_name] = self.ref.answer(OPTIONS[opt_name])
        return self.answers[opt_name]


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ritree_reference")
    built = {}

    def get(name):
        if name not in built:
            built[name] = Case(name, CASES[name], tmp)
        return built[name]
    return get


def angle(a, b):
    """Angle (rad) between unit vectors, rows of a and b (accurate for tiny angles)."""
    return 2.0 * np.arctan2(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))


def describe(case, ref, ans, why, rows, limit=8):
    lines = []
    for i in rows[:limit]:
        rec = ref["records"][i]
        lines.append(f"ray {case.subset[i]}: query {ANSWER_NAMES[ans[i]]}/{WHY_NAMES[why[i]]}, "
                     f"reference {ANSWER_NAMES[rec.ans]}/{WHY_NAMES[rec.why]} {rec.info}")
    return "\n".join(lines) + (f"\n... {len(rows)} in all" if len(rows) > limit else "")


@pytest.mark.parametrize("case_name,opt_name", PAIRS, ids=[f"{c}-{o}" for c, o in PAIRS])
def test_query_matches_reference(cases, case_name, opt_name):
    case = cases(case_name)
    ref = case.reference(opt_name)
    # the query answers all the case's rays in one call (as a render does); compared on the subset.
    # The rules decide what is traced; the path solver, which answers some of those rays exactly
    # instead, is checked against the tracer in test_path_solve.py.
    opt = replace(OPTIONS[opt_name], solve_paths=False)
    res, ans, why, _ = TreeQuery(case.tree, case.st, opt)(case.o, case.d, case.tmax)
    s = case.subset
    ans, why = np.asarray(ans)[s], np.asarray(why)[s]
    hit, null = np.asarray(res.hit)[s], np.asarray(res.null)[s]

    bad = np.flatnonzero((ans != ref["ans"]) | (why != ref["why"]))
    assert len(bad) == 0, "answer / why codes differ:\n" + describe(case, ref, ans, why, bad)

    diag = case.tree.diag
    interp = (ans >= FULL) & (ans <= EXTRAPOLATED_S)
    nul = ans == NULL_S
    assert np.all(hit[interp | nul]) and not np.any(hit[ans == MISS])
    assert np.all(null[nul]) and not np.any(null[interp])
    checks = [("out_dir", interp, "angle"), ("normal", interp | nul, "angle"),
              ("out_origin", interp, "point"), ("point", interp | nul, "point")]
    for field, rows, kind in checks:
        got = np.asarray(getattr(res, field))[s][rows]
        want = ref[field][rows]
        err = angle(got, want) if kind == "angle" else np.linalg.norm(got - want, axis=1) / diag
        tol = ANGLE_TOL if kind == "angle" else POINT_TOL
        far = np.flatnonzero(rows)[~(err <= tol)]
        assert len(far) == 0, (f"{field}: {len(far)} rays off by more than {tol} "
                               f"(max {err.max():.3g}):\n" + describe(case, ref, ans, why, far))
    cls = np.asarray(res.cls)[s]
    wrong = np.flatnonzero((interp | nul) & (cls != ref["cls"]))
    assert len(wrong) == 0, "classes differ:\n" + describe(case, ref, ans, why, wrong)


def ans_interpolated(a):
    return FULL <= a <= EXTRAPOLATED_S or a == NULL_S


def test_rules_are_exercised(cases):
    """The compared rays reach every rule (counted on the reference's answers, over all cases
    and options), so an agreement above means something for each."""
    kinds, paths = Counter(), Counter()
    for case_name, opt_name in PAIRS:
        ref = cases(case_name).reference(opt_name)
        for rec in ref["records"]:
            kinds[(rec.ans, rec.why)] += 1
            info = rec.info
            if rec.ans != TRACED or rec.why != WHY_CLASSES:
                if info.get("two_class"):        # the exact first hit gave the class
                    paths["two-class " + ("miss" if info["pc"] == -1 else "hit")] += 1
            for ex_kind, side, tri, how in info.get("extra", ()):
                paths[f"extra kind {ex_kind} side {side}"] += 1
                paths[f"extra triangle {tri}"] += 1
                if how == ref_mod.EXTRAPOLATED:
                    paths["extra extrapolated"] += 1
            if info.get("dq_drop") and ans_interpolated(rec.ans):
                paths["direction-level outlier dropped, answered"] += 1
            if info.get("vp_drop") and ans_interpolated(rec.ans):
                paths["viewpoint-level outlier dropped, answered"] += 1
            if info.get("unchecked"):
                paths["unverified leaves skipped"] += 1
            if info.get("hidden"):
                paths["hidden"] += 1
            if info.get("once") is not None and ans_interpolated(rec.ans):
                paths["mirror normal" if info["once"] else "mirror normal declined"] += 1
            if info.get("newton") and ans_interpolated(rec.ans):
                paths["mirror newton hit"] += 1
                if info.get("past_tolerance"):
                    paths["mirror newton hit past the tolerance"] += 1
                    if info.get("unmeasured"):
                        paths["mirror newton hit past the tolerance, unmeasured"] += 1
    print("answer kinds:", {f"{ANSWER_NAMES[a]}/{WHY_NAMES[w] or '-'}": n
                            for (a, w), n in sorted(kinds.items())})
    print("rule paths:", dict(sorted(paths.items())))
    need_kinds = {"miss": (MISS, 0), "16": (FULL, 0), "reduced": (REDUCED, 0),
                  "extra": (EXTRA_S, 0), "extrapolated": (EXTRAPOLATED_S, 0), "null": (NULL_S, 0),
                  "outside": (OUTSIDE, 0), "traced classes": (TRACED, WHY_CLASSES),
                  "traced usable": (TRACED, WHY_USABLE),
                  "traced threshold": (TRACED, WHY_THRESHOLD),
                  "traced raytree": (TRACED, WHY_RAYTREE),
                  "traced tolerance": (TRACED, WHY_TOLERANCE),
                  "traced unsampled hit": (TRACED, WHY_UNSAMPLED),
                  "traced path change": (TRACED, WHY_PATH)}
    missing = {k: kinds[v] for k, v in need_kinds.items() if kinds[v] < 3}
    assert not missing, f"answer kinds too rare in the compared rays: {missing}; all: {kinds}"
    need_paths = ("two-class miss", "two-class hit", "extra kind 1 side L",
                  "extra kind 2 side A", "extra kind 2 side B", "extra triangle 0",
                  "extra triangle 1", "extra extrapolated",
                  "direction-level outlier dropped, answered",
                  "viewpoint-level outlier dropped, answered", "unverified leaves skipped",
                  "hidden", "mirror normal", "mirror normal declined", "mirror newton hit",
                  "mirror newton hit past the tolerance",
                  "mirror newton hit past the tolerance, unmeasured")
    missing = {p: paths[p] for p in need_paths if paths[p] < 3}
    assert not missing, f"rules too rarely reached: {missing}; all: {dict(paths)}"


def test_reference_primitives():
    """The reference's own small rules against hand-worked answers (so a disagreement above
    is not a bug of the reference's arithmetic)."""
    r = ref_mod
    w, k = r.cell_weights([True] * 4, (0.25, 0.5))
    assert k == r.BILINEAR and np.allclose(w, [0.375, 0.125, 0.375, 0.125])
    # three usable corners: barycentric on their triangle; outside it -> fail or extrapolated
    w, k = r.cell_weights([True, True, True, False], (0.25, 0.5))
    assert k == r.TRIANGLE and np.allclose(w, [0.25, 0.25, 0.5, 0.0])
    assert r.cell_weights([True, True, True, False], (0.75, 0.5))[1] == r.FAIL
    w, k = r.cell_weights([True, True, True, False], (0.6, 0.5), extrapolation=0.25)
    assert k == r.EXTRAPOLATED and np.allclose(w, [-0.1, 0.6, 0.5, 0.0])
    assert r.cell_weights([True, False, False, True], (0.5, 0.5))[1] == r.FAIL
    # pick_triangle: the first containing triangle wins, else extrapolation over the last
    tris = [[(0, 0), (1, 0), (0, 0.5)], [(1, 0), (0, 0.5), (1, 0.5)]]
    assert r.pick_triangle((0.2, 0.2), tris, None)[::2] == (0, r.TRIANGLE)
    assert r.pick_triangle((0.8, 0.4), tris, None)[::2] == (1, r.TRIANGLE)
    assert r.pick_triangle((0.8, 0.6), tris, None)[2] == r.FAIL
    which, lam, kind = r.pick_triangle((0.8, 0.6), tris, 0.25)
    assert (which, kind) == (1, r.EXTRAPOLATED) and np.allclose(lam, [-0.2, 0.2, 1.0])
    # drop_outlier: most far pairs first, ties -> farthest from the query, then all lost
    far = np.zeros((4, 4), bool)
    far[0, 1] = far[1, 0] = True
    assert r.drop_outlier(far, [True] * 4, r.CORNERS, (0.1, 0.1)) == ([True, False, True, True],
                                                                       True)
    assert r.drop_outlier(far, [True] * 4, r.CORNERS, (0.9, 0.1)) == ([False, True, True, True],
                                                                      True)
    far[2, 3] = far[3, 2] = True
    assert r.drop_outlier(far, [True] * 4, r.CORNERS, (0.1, 0.1)) == ([False] * 4, True)
    far[:] = False
    far[0, 1:] = far[1:, 0] = True
    assert r.drop_outlier(far, [True] * 4, r.CORNERS, (0.1, 0.1)) == ([False, True, True, True],
                                                                      True)
    # far_matrix: chord of the angle limit, squared distances, only used pairs
    v = np.zeros((3, 12))
    v[:, 3:6] = [[1, 0, 0], [math.cos(0.2), math.sin(0.2), 0], [math.cos(0.4), math.sin(0.4), 0]]
    v[:, 0:3] = [[0, 0, 0], [0, 0, 0.1], [0, 0, 0.3]]
    chord = 2 * math.sin(math.radians(15) / 2)       # 15 degrees = 0.26 rad
    f = r.far_matrix(v, [True] * 3, chord, None)
    assert f.tolist() == [[False, False, True], [False, False, False], [True, False, False]]
    assert not r.far_matrix(v, [True, True, False], chord, None).any()
    f = r.far_matrix(v, [True] * 3, None, 0.15)
    assert f.tolist() == [[False, False, True], [False, False, True], [True, True, False]]
