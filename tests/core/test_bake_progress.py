"""The bake's progress is weighted by work: on a clock that advances with the rays traced (an
extra-sample ray costing twice a direction-level ray, as measured on the sample scenes), the
reported fraction follows the share of the work done and the ETA the work left, from the
direction levels through the extra samples. (Counting stages, the bar sat still while the
extra samples, most of the work, ran.)"""

import types

import numpy as np
import pytest

from riray.geometry.primitives import sphere
from riray.trace.scene_tracer import SceneTracer
from riray.ritree import bake as bake_mod
from riray.ritree.region import region_for_cameras
from riray.ritree.tree import BakeParams
from riray.scene.model import ObjectMaterial, Patch, RenderSettings, Scene, SpecularObject
from riray.scene.samples import build

EXTRA_COST = 2


@pytest.fixture
def work_clock(monkeypatch):
    """bake's clock reads the work traced so far: 1 per level ray, EXTRA_COST per extra ray."""
    clock = {"now": 0, "kind": "level"}
    monkeypatch.setattr(bake_mod, "time",
                        types.SimpleNamespace(perf_counter=lambda: float(clock["now"])))
    monkeypatch.setattr(bake_mod, "TRACE_CHUNK", 256)
    call = bake_mod.Tracer.__call__

    def traced(self, *args):
        clock["kind"] = getattr(self, "kind", "level")
        return call(self, *args)
    monkeypatch.setattr(bake_mod.Tracer, "__call__", traced)
    return clock


def _clocked_bake(work_clock, st, params, region=None):
    """Bake on the work clock: (share of the whole bake's work done at each report, the
    fractions reported, their messages)."""
    f = st.object_function

    def counted(o, d, tmax=None, first=None, record=None, **kw):
        work_clock["now"] += len(o) * (EXTRA_COST if work_clock["kind"] == "extra" else 1)
        return f(o, d, tmax, first, record, **kw)
    st.object_function = counted
    calls = []
    bake_mod.bake(st, params, region, workers=1,
                  progress=lambda frac, msg: calls.append((work_clock["now"], frac, msg)))
    done, frac = np.array([c[0] for c in calls], float), np.array([c[1] for c in calls])
    return done / work_clock["now"], frac, [c[2] for c in calls]


def test_progress_follows_the_work(work_clock):
    ball = SpecularObject("ball", [Patch("s", 0, surface=sphere((0.0, 0.0, 0.0), 0.5))],
                          ObjectMaterial(kind="glass", ior=1.5))
    st = SceneTracer(Scene(objects=[ball], render=RenderSettings(max_events=8)))
    share, frac, msg = _clocked_bake(work_clock, st, BakeParams(viewpoint_depth=1,
                                                                direction_depth=4))
    assert np.all(np.diff(frac) >= 0) and frac[-1] == pytest.approx(1.0)
    extra = np.array(["extra samples" in m for m in msg])
    assert extra.any()
    assert share[extra].min() < 0.5 < share[extra].max()       # the extras are most of it
    late = share >= 0.2                     # the first levels cannot know what follows
    assert np.abs(frac - share)[late].max() < 0.15, np.c_[share, frac][late][::50]
    # once the extra samples run, their amount is known: the ETA is within 25 % of the work
    # left (both as shares of the whole bake's work)
    eta = share / np.maximum(frac, 1e-9) - share
    left = 1.0 - share
    known = extra & (share > share[extra].min()) & (share <= 0.9)
    assert np.all(np.abs(eta - left)[known] < 0.25 * left[known])


def test_refinement_passes_progress_follows_the_work(work_clock):
    """A camera bake's refinement passes grow (more viewpoint cells split at each level): the
    fraction keeps following the work, neither sitting still while a pass larger than the
    last runs (it did: it held until the work caught up with an estimate that assumed equal
    passes) nor far ahead of it."""
    st = SceneTracer(build("glass_sphere"))
    params = BakeParams(viewpoint_depth=2, direction_depth=3, viewpoint_refine=2)
    region = region_for_cameras(st, params, [st.scene.camera("close")], 60, 60)
    share, frac, msg = _clocked_bake(work_clock, st, params, region)
    passes = {m.split("(pass ")[1][0] for m in msg if "(pass " in m}
    assert passes == {"1", "2", "3"}, passes            # the bake did refine twice
    assert np.all(np.diff(frac) >= 0) and frac[-1] == pytest.approx(1.0)
    late = share >= 0.2
    assert np.abs(frac - share)[late].max() < 0.2, np.c_[share, frac][late][::20]
    # the longest stretch of work during which the fraction does not move
    moved = np.flatnonzero(np.diff(frac) > 1e-3) + 1
    marks = np.concatenate([[0.0], share[moved], [1.0]])
    assert np.diff(marks).max() < 0.15, np.diff(marks).max()
