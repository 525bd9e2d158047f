"""`riray bench` (docs/benchmarks.md): the --quick preset at a tiny size writes the CSV, JSON,
Markdown and PNG outputs, and they agree with each other and with what interpolation means
(never more rays traced than the exact render, errors only where rays were interpolated)."""

import csv
import json
import math

import numpy as np
import pytest

from riray.bench.pareto import dominance
from riray.bench.plots import pareto_front
from riray.bench.ritree_bench import ROWS, BenchConfig, config_from_args
from riray.cli import main
from riray.render.compare import disagreements

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """One quick run: 2 scenes x the close view at 20 x 20, one worker (about 15 s)."""
    pytest.importorskip("matplotlib")
    out = tmp_path_factory.mktemp("bench")
    rc = main(["bench", "--quick", "--size", "20", "--views", "close", "--workers", "1",
               "--quiet", "--out", str(out)])
    assert rc == 0
    return out


def _csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_outputs_exist(bench):
    for name in ("tables.csv", "sweeps.csv", "results.json", "tables.md", "sweeps.md"):
        assert (bench / name).stat().st_size > 0, name
    for name in ("pareto.png", "bake_depth.png", "amortized.png"):
        assert (bench / name).read_bytes()[:8] == PNG_MAGIC, name
    assert (bench / "images" / "glass_sphere_close_exact.png").read_bytes()[:8] == PNG_MAGIC
    assert not (bench / "trees").exists()          # trees are dropped unless --keep-trees


def refused_of(row) -> float:
    """The share of the object's rays a CSV row's rules refused: traced, or solved exactly
    along a sample's path."""
    return float(row["traced_fraction"]) + float(row["solved_fraction"])


def test_tables_consistent(bench):
    rows = _csv(bench / "tables.csv")
    res = json.loads((bench / "results.json").read_text())
    # 2 scenes x 1 view x 7 rows, and the mirror's 2 rows of mirror rays from the normal
    mirror_rows = {"interp_reflect", "deeper_reflect"}
    assert len(rows) == len(res["tables"]) == 2 * len(ROWS) - len(mirror_rows)
    assert res["machine"]["cpu_count"] >= 1 and res["command"].startswith("riray bench --quick")
    by = {}
    for r in rows:
        by.setdefault((r["scene"], r["view"]), {})[r["row"]] = r
    gap = beyond = 0
    assert set(by) == {("glass_sphere", "close"), ("vase_mirror", "close")}
    for view, rs in by.items():
        assert set(rs) == set(ROWS) - (set() if view[0] == "vase_mirror" else mirror_rows), view
        ex = rs["exact"]
        assert int(ex["rays_traced"]) == int(ex["object_rays"]) > 0
        assert int(ex["samples_gathered"]) == 0 and int(ex["newton_iters"]) > 0
        for kind in set(rs) - {"exact"}:
            r = rs[kind]
            assert int(r["object_rays"]) == int(ex["object_rays"])      # the same camera rays
            assert int(r["rays_traced"]) <= int(ex["rays_traced"])
            # (Newton iterations may exceed exact's: two-class rays get an exact first-hit test)
            assert int(r["pairs"]) >= 0 and int(r["exact_first_hits"]) >= 0
            assert int(r["samples_gathered"]) >= 16 * (int(r["object_rays"]) - int(r["rays_traced"]))
            assert 0.0 <= float(r["traced_fraction"]) <= 1.0
            assert float(r["object_cpu_s"]) > 0 and float(r["total_cpu_s"]) >= float(r["object_cpu_s"])
            if r["angle_mean_deg"]:
                assert 0 <= float(r["angle_mean_deg"]) <= float(r["angle_p99_deg"]) \
                    <= float(r["angle_max_deg"]) + 1e-9
            # wrong kinds of answer are answered rays (traced ones are exact)
            answered = int(r["object_rays"]) - int(r["rays_traced"])
            assert 0 <= int(r["hit_disagreements"]) <= answered
            assert 0 <= int(r["null_disagreements"]) <= answered
        # the deeper tree is its own bake, at the configured depths
        vp, dd, vr, *_ = res["config"]["deeper_tree"]
        t = rs["deeper"]
        assert (int(t["viewpoint_depth"]), int(t["direction_depth"]), int(t["viewpoint_refine"])) \
            == (vp, dd, vr) != (int(ex["viewpoint_depth"]), int(ex["direction_depth"]),
                                int(ex["viewpoint_refine"]))
        # the tolerance refuses every ray the same rules without it trace, and more, and traces
        # them or solves them exactly along a sample's path; what those rules trace or answer
        # beyond the tolerance (the floor) it refuses or answers so too
        rules, tol = rs["deeper_rules"], rs["deeper"]
        assert float(rules["solved_fraction"]) == 0.0     # only refused rays are solved
        refused = refused_of(tol)
        assert float(rules["traced_fraction"]) <= refused + 1e-9
        assert 0.0 <= float(rules["beyond_fraction"]) \
            <= 1.0 - float(rules["traced_fraction"]) + 1e-9
        assert float(rules["traced_fraction"]) + float(rules["beyond_fraction"]) \
            <= refused + float(tol["beyond_fraction"]) + 1e-9
        gap += refused - float(rules["traced_fraction"])
        beyond += float(rules["beyond_fraction"])
        # the angle threshold only ever adds traced rays to the no-threshold row
        assert int(rs["interp_angle"]["rays_traced"]) >= int(rs["interp"]["rays_traced"])
        # exact mirror hits (the default) only ever answer rays the tolerance would refuse
        # (trace or solve along a sample's path) with mirror rays from the interpolated normal
        for newton, reflect in (("interp_tol", "interp_reflect"), ("deeper", "deeper_reflect")):
            if reflect in rs:
                assert refused_of(rs[newton]) <= refused_of(rs[reflect]) + 1e-9
                assert int(rs[newton]["exact_mirror_hits"]) > 0 \
                    == int(rs[reflect]["exact_mirror_hits"])
    # the tolerance traces rays the rules alone answer, and those rules answer some beyond it
    assert gap > 0 and beyond > 0
    # the JSON and the CSV hold the same numbers
    for j, r in zip(res["tables"], rows):
        assert (j["scene"], j["view"], j["row"]) == (r["scene"], r["view"], r["row"])
        assert j["rays_traced"] == int(r["rays_traced"]) and j["pairs"] == int(r["pairs"])
        assert math.isclose(j["object_cpu_s"], float(r["object_cpu_s"]))
        assert j["null_disagreements"] == int(r["null_disagreements"])
    md = (bench / "tables.md").read_text()
    assert "| close | ray traced |" in md and "break-even" in md
    assert "| wrong hit / null |" in md and md.count(" | 0 / 0 | ") >= len(rows) // 2
    for a in res["amortization"]:
        be = a["break_even_frames"]
        saved = a["exact_frame_cpu_s"] - a["interp_frame_cpu_s"]
        assert (be is None) == (saved <= 0)
        if be is not None:
            assert be * saved >= a["bake_cpu_s"] - 1e-9


def test_sweeps_consistent(bench):
    rows = _csv(bench / "sweeps.csv")
    q = BenchConfig(**config_from_args(quick=True).__dict__)
    assert {r["scene"] for r in rows} == {"glass_sphere", "vase_mirror"}
    for scene in ("glass_sphere", "vase_mirror"):
        kinds = [r["sweep"] for r in rows if r["scene"] == scene]
        swept = scene in q.sweep_scenes          # depth and bake sweeps on the swept scenes only
        assert kinds.count("depth") == swept * len(q.vp_depths) * len(q.dir_depths)
        assert kinds.count("tolerance") == swept * len(q.tolerances)
        assert kinds.count("distance") == swept * len(q.distances)
        assert kinds.count("extrapolation") == swept * len(q.extrapolations)
        # every scene's Pareto plot compares the render-time policies on one tree
        assert kinds.count("angle") == len(q.angles)
        assert kinds.count("max_error") == len(q.max_errors)
        assert kinds.count("path") == len(q.path_max_errors)
        assert kinds.count("raytree") == 1
        rs = [r for r in rows if r["scene"] == scene]
        # without any threshold fewer rays are traced than with the tightest angle threshold
        ang = {r["angle"]: int(r["rays_traced"]) for r in rs if r["sweep"] == "angle"}
        assert ang[""] <= min(v for k, v in ang.items() if k)
        # a tighter --max-error never interpolates a worse ray, and refuses (traces or solves
        # along a sample's path) at least as many
        tol = sorted(((float(r["max_error"]), r) for r in rs if r["sweep"] == "max_error"),
                     key=lambda x: -x[0])
        for (_, a), (_, b) in zip(tol, tol[1:]):
            assert float(b["angle_max_deg"] or 0) <= float(a["angle_max_deg"] or 0)
            assert refused_of(b) >= refused_of(a) - 1e-9
        # the policy points share one tree
        assert len({r["tree_samples"] for r in rs if r["sweep"] in ("angle", "raytree")}) == 1
    for r in rows:
        assert float(r["bake_s"]) > 0 and int(r["cache_bytes"]) > 0
        assert 0.0 <= float(r["traced_fraction"]) <= 1.0
    # the Pareto judgement names, per threshold point, tolerance points that beat it in the CSV
    res = json.loads((bench / "results.json").read_text())
    assert sorted(p["scene"] for p in res["pareto"]) == ["glass_sphere", "vase_mirror"]
    assert "tolerance dominate the angle threshold" in (bench / "sweeps.md").read_text()
    for judged in res["pareto"]:
        rs = [r for r in rows if r["scene"] == judged["scene"]]
        thr = [r for r in rs if r["sweep"] == "angle"]
        tol = {f"{float(r['max_error']):g} deg": r for r in rs if r["sweep"] == "max_error"}
        assert len(judged["points"]) == len(thr)
        for t, p in zip(thr, judged["points"]):
            for name in p["by_curve"]:
                c = tol[name]
                assert float(c["object_speedup"]) >= float(t["object_speedup"])
                for k in ("angle_mean_deg", "angle_p99_deg"):
                    assert float(c[k] or 0) <= float(t[k] or 0) + 1e-6
        assert judged["curve_dominates"] == all(p["by_curve"] for p in judged["points"])
    # deeper direction trees never hold fewer samples (same viewpoint depth, same tolerance)
    depth = [r for r in rows if r["sweep"] == "depth"]
    for vp in q.vp_depths:
        s = [int(r["tree_samples"]) for r in depth if int(r["viewpoint_depth"]) == vp]
        assert s == sorted(s)


def test_disagreements_count_both_directions():
    """A hit answered for a miss and a miss for a hit; null answered for a ray that leaves and
    an exit answered for a trapped ray: each counts once, agreement not at all."""
    class Rays:
        def __init__(self, hit, null):
            self.hit, self.null = np.array(hit, bool), np.array(null, bool)

    answer = Rays([1, 0, 1, 1, 1, 0], [0, 0, 1, 0, 1, 0])
    exact = Rays([0, 1, 1, 1, 1, 0], [0, 0, 0, 1, 1, 0])
    assert disagreements(answer, exact) == (2, 2)
    assert disagreements(exact, exact) == (0, 0)


def test_pareto_front():
    pts = [(1.0, 5.0), (2.0, 3.0), (2.5, 4.0), (3.0, 1.0), (0.5, 9.0), (3.0, 2.0)]
    assert pareto_front(pts) == [4, 0, 1, 3]


def _row(scene, sweep, speedup, mean, p99, angle=None, max_error=None):
    return {"scene": scene, "sweep": sweep, "object_speedup": speedup, "angle_mean_deg": mean,
            "angle_p99_deg": p99, "angle": angle, "max_error": max_error}


def test_dominance_of_the_threshold_curve():
    """The bench's Pareto judgement: a threshold point is dominated by a tolerance point at
    least as fast with mean and p99 no higher (ties count); a faster point with a higher p99
    does not; "reflect" points count only for "any"; a threshold point that traces every ray
    (no error reported) is dominated by one whose errors are at the tracer's own 1e-9 deg."""
    rows = [_row("s", "angle", 2.0, 1.0, 10.0),                      # no threshold: time 0.5
            _row("s", "angle", 1.0, 0.3, 2.0, angle=20.0),          # time 1.0
            _row("s", "angle", 0.9, None, None, angle=5.0),         # traces every ray
            _row("s", "max_error", 2.0, 0.5, 10.0, max_error=8.0),   # ties no threshold
            _row("s", "max_error", 1.25, 0.3, 2.0, max_error=2.0),   # ties 20 deg's errors
            _row("s", "max_error", 1.0, 1e-9, 1e-9, max_error=0.25),
            _row("s", "reflect", 4.0, 0.1, 0.5, max_error=1.0),
            _row("t", "angle", 2.0, 1.0, 10.0),
            _row("t", "max_error", 2.5, 0.5, 10.01, max_error=8.0),  # faster, p99 higher
            _row("u", "max_error", 2.5, 0.5, 1.0, max_error=8.0)]    # no threshold points
    s, t = dominance(rows)
    assert [p["threshold"] for p in s["points"]] == ["no threshold", "20 deg", "5 deg"]
    assert [p["by_curve"] for p in s["points"]] == [["8 deg"], ["2 deg", "0.25 deg"],
                                                    ["0.25 deg"]]
    assert [p["by_any"] for p in s["points"]] == [["8 deg", "1 deg reflect"],
                                                  ["2 deg", "0.25 deg", "1 deg reflect"],
                                                  ["0.25 deg"]]
    assert s["curve_dominates"] and s["any_dominates"]
    assert t["points"][0]["by_curve"] == [] and not t["curve_dominates"]
    assert not t["curve_dominates_angles"]             # no angle point: nothing shown
    rows[1] = _row("s", "angle", 1.5, 0.3, 2.0, angle=20.0)     # now faster than 2 deg
    s, _ = dominance(rows)
    assert s["points"][1]["by_curve"] == [] and not s["curve_dominates_angles"]
    assert t["scene"] == "t" and t["points"][0]["time"] == 0.5


def test_bad_options(capsys):
    assert main(["bench", "--size", "1", "--out", "unused"]) == 2
    assert "size" in capsys.readouterr().err
    assert main(["bench", "--quick", "--repeats", "0", "--out", "unused"]) == 2
    assert main(["bench", "--quick", "--pareto-repeats", "0", "--out", "unused"]) == 2
    assert "pareto_repeats: must be >= 1" in capsys.readouterr().err


def test_passes_run_per_config_in_parallel(tmp_path):
    """measure_configs runs each pass whole in one process, two processes at a time: every
    config's row is made of its own passes on its own tree (same answers and errors as the
    config measured alone in this process), as many as it asks for, each with its own exact
    half."""
    from riray.bench.ritree_bench import bake_view, measure_configs, measure_pass, paper
    from riray.trace.scene_tracer import SceneTracer
    from riray.scene.samples import build

    scene = build("glass_sphere")
    st, cam = SceneTracer(scene), scene.camera("close")
    tree, _ = bake_view(st, scene, cam, 24, BenchConfig().bake_params(3, 4, 0.5, 1), 1,
                        tmp_path)
    other, _ = bake_view(st, scene, cam, 24, BenchConfig().bake_params(2, 4, 0.5, 1), 1,
                         tmp_path)
    configs = {"off": (tree, paper(angle_deg=None), 2), "10": (tree, paper(angle_deg=10.0), 1),
               "20": (tree, paper(angle_deg=20.0), 3), "other": (other, paper(angle_deg=20.0), 2)}
    rows = measure_configs(st, cam, 24, configs, workers=2)
    alone = {k: measure_pass(st, t, cam, 24, opt) for k, (t, opt, _) in configs.items()}
    assert len({alone[k]["rays_traced"] for k in configs}) == len(configs)   # all differ
    for k, (_, _, n) in configs.items():
        assert rows[k]["rays_traced"] == alone[k]["rays_traced"], k
        assert rows[k]["angle_max_deg"] == pytest.approx(float(alone[k]["err"].max()), abs=1e-9)
        assert len(rows[k]["object_cpu_s_all"]) == n
        assert rows[k]["exact_object_cpu_s"] > 0
    assert len(rows["exact"]["object_cpu_s_all"]) == 8
