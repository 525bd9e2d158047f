"""The tree render's and the benchmark's stats report the rays solved along a sample's path
(answer code SOLVED, "solved_along_path") beside the traced ones: `riray render --tree`'s
summary (solved_fraction_of_object), the bench's measured pass (solved_fraction) and its
tables, which read older results.json files (no solved_fraction) too."""

from dataclasses import replace

import numpy as np
import pytest

from riray.ritree import tree as ritree
from riray.ritree.bake import bake
from riray.ritree.query import ANSWER_NAMES, SOLVED, QueryOptions
from riray.ritree.region import region_for_cameras
from riray.scene.camera import Shot
from riray.scene.samples import build
from riray.trace.scene_tracer import SceneTracer

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")


SIZE = 24
# A tolerance no leaf meets: every located ray that hits goes to the path solver or the tracer.
REFUSE = QueryOptions(max_error_deg=0.0)


@pytest.fixture(scope="module")
def sphere():
    """glass_sphere's close view and a small tree baked for it."""
    scene = build("glass_sphere")
    st, cam = SceneTracer(scene), scene.camera("close")
    params = ritree.BakeParams(viewpoint_depth=2, viewpoint_refine=1, direction_depth=3)
    tree = bake(st, params, region_for_cameras(st, params, [cam], SIZE, SIZE), workers=1)
    return st, cam, tree


def test_render_summary_reports_solved_rays(sphere):
    from riray.render.interpolated import render_tree
    st, cam, tree = sphere
    shot = Shot(camera=cam.name, width=SIZE, height=SIZE)

    def render(opts):
        res = render_tree(st, tree, shot, options=opts, reference=False, workers=1)
        return res.stats["summary"], res.stats["answers"], res.stats["traced_because"]
    summary, answers, why = render(REFUSE)
    assert "solved_along_path" in answers and ANSWER_NAMES[SOLVED] == "solved_along_path"
    n_obj = summary["object_pixels"]
    assert answers["solved_along_path"] > 0 and n_obj > 0
    # every solved ray hits the object: the fraction is of the object's rays, like traced's
    assert summary["solved_fraction_of_object"] == pytest.approx(
        answers["solved_along_path"] / n_obj, abs=1e-5)
    assert summary["solved_fraction_of_object"] + summary["traced_fraction_of_object"] <= 1.0
    # a solved ray keeps the reason it was refused for, but is not counted as traced for it
    assert sum(why.values()) <= summary["rays_traced"] < answers["solved_along_path"]
    off, off_answers, off_why = render(replace(REFUSE, solve_paths=False))
    assert off["solved_fraction_of_object"] == 0.0 and off_answers["solved_along_path"] == 0
    assert off["traced_fraction_of_object"] > summary["traced_fraction_of_object"]
    assert off_why["tolerance"] >= answers["solved_along_path"]


def test_bench_pass_and_tables_report_solved_rays(sphere):
    from riray.bench.ritree_measure import measure_pass
    from riray.bench.ritree_output import SWEEP_CSV, TABLE_CSV, sweeps_markdown, tables_markdown
    st, cam, tree = sphere
    p = measure_pass(st, tree, cam, SIZE, REFUSE)
    solved = int(np.sum(p["answers"] == SOLVED))
    assert solved > 0          # of the rays that hit the object exactly, as traced_fraction
    assert p["solved_fraction"] == pytest.approx(solved / p["object_hits"])
    assert "solved_fraction" in TABLE_CSV and "solved_fraction" in SWEEP_CSV
    assert measure_pass(st, tree, cam, SIZE, replace(REFUSE, solve_paths=False))[
        "solved_fraction"] == 0.0

    row = {"scene": "s", "view": "close", "row": "interp_tol", "label": "tolerance",
           "viewpoint_depth": 2, "direction_depth": 3, "tolerance": 0.5, "rays_traced": 10,
           "object_rays": 100, "traced_fraction": 0.1, "solved_fraction": 0.234,
           "beyond_fraction": 0.0, "object_cpu_s": 1.0, "total_cpu_s": 2.0,
           "object_speedup": 2.0, "query_own_fraction": 0.1, "pairs": 5, "newton_iters": 9,
           "samples_gathered": 1440, "angle_mean_deg": 0.1, "angle_p99_deg": 1.0,
           "angle_max_deg": 2.0, "hit_disagreements": 0, "null_disagreements": 0,
           "psnr_db": 40.0, "cache_bytes": 1e6}
    old = {k: v for k, v in row.items() if k != "solved_fraction"}    # an older results.json

    def table_rows(md):
        return [ln for ln in md.splitlines() if ln.startswith("| close |")]
    md = tables_markdown({"tables": [row, old], "amortization": []})
    head = next(ln for ln in md.splitlines() if ln.startswith("| view |"))
    cols = [c.strip() for c in head.strip("|").split("|")]
    at = cols.index("solved along a sample's path, % of object")
    assert cols[at - 1] == "traced % of object"
    new_row, old_row = ([c.strip() for c in ln.strip("|").split("|")] for ln in table_rows(md))
    assert len(new_row) == len(old_row) == len(cols)
    assert (new_row[at - 1], new_row[at], old_row[at]) == ("10.0", "23.4", "-")

    sweep = {**row, "sweep": "max_error", "angle": None, "distance": None,
             "extrapolation": None, "max_error": 2.0, "bake_s": 1.0,
             "exact_object_cpu_s": 2.0, "exact_total_cpu_s": 4.0, "max_pixel_diff": 0.1}
    md = sweeps_markdown([sweep, {k: v for k, v in sweep.items() if k != "solved_fraction"}])
    lines = md.splitlines()
    cols = [c.strip() for c in lines[2].strip("|").split("|")]
    at = cols.index("solved %")
    assert cols[at - 1] == "traced %" and len(lines[3].strip("|").split("|")) == len(cols)
    body = [[c.strip() for c in ln.strip("|").split("|")] for ln in lines[4:6]]
    assert [len(b) for b in body] == [len(cols)] * 2
    assert (body[0][at], body[1][at]) == ("23.4", "-")
