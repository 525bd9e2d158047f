"""The bake's progress, weighted by work, with an estimate of the seconds left."""

from __future__ import annotations

import time


class Progress:
    """The bake's progress weighted by work: seconds spent / (seconds spent + seconds still
    expected), reported as ``progress(fraction, "label: NN% (eta S s)")``; the fraction never
    goes back (it holds while the estimate grows), S is the current estimate. ``clock()`` gives
    the seconds (time.perf_counter).

    Work is traced rays of two kinds, "level" (direction-tree corners and midpoints) and
    "extra" (the extra samples' binary search), at the seconds per ray measured for each kind
    (times the passes' measured overhead outside tracing). What is still expected is
    re-estimated as the bake goes: the deeper direction levels of a pass grow as the last level
    did; the extra samples are known exactly from their first step (``steps`` equal traces),
    before that as many per level ray as in the last pass; until then a pass after the first
    is expected to cost the mean seconds per direction tree of the passes before (the levels'
    first guesses are far off for deep trees). A camera bake's refinement passes are
    preceded, and the bake is ended, by the viewpoint cells' measurement (``refine`` /
    ``measure``), each expected to last as long as the last one did. The passes left grow in
    direction trees by the ratio of the last two refinement passes (``PASS_GROWTH0`` until two
    ran; the first refinement pass as many as the uniform pass)."""

    GROWTH0 = 2.0           # cells per cell from one direction level to the next, first guess
    RAYS_PER_CELL0 = 2.0    # rays traced per tested cell (midpoint, new corners), first guess
    EXTRA_PER_LEVEL0 = 1.0  # extra-sample rays per level ray, first guess
    EXTRA_COST0 = 2.0       # an extra-sample ray's cost in level rays until one was timed
    PASS_GROWTH0 = 3.0      # direction trees per tree from one refinement pass to the next,
                            # first guess (teapot close, depths 4/7, refine 3: 3.2, 3.4)
    PASS_GROWTH_MAX = 4.0   # a split viewpoint cell has four children

    def __init__(self, progress, passes: int, levels: int, steps: int,
                 clock=time.perf_counter):
        self.cb, self.passes, self.M, self.steps = progress, passes, levels, steps
        self.clock = clock
        self.t0 = clock()
        self.last, self.label, self.passes_done = 0.0, "starting", 0
        self.extra_per_level = self.EXTRA_PER_LEVEL0
        self.rays = {"level": 0, "extra": 0}          # rays traced (whole bake) ...
        self.secs = {"level": 0.0, "extra": 0.0}      # ... and the seconds they took
        self.call = None                              # (kind, rays, start) of the trace running
        self.pass_trees, self.pass_s = [], 0.0        # trees of each pass; seconds of the ended
        self.between_s = None                         # seconds of the last measurement
        self.pass_t0 = self.ended = self.t0
        self.trees, self.open = 0, False
        self._counts()

    def start_pass(self, trees: int):
        """A pass that bakes ``trees`` new direction trees begins (what ran since the last
        one ended, the viewpoint cells' measurement, is timed)."""
        now = self.clock()
        if self.pass_trees:
            self.between_s = now - self.ended
        self.pass_t0, self.trees, self.open = now, trees, True
        self.pass_trees.append(trees)
        self._counts()

    def _counts(self):
        """Zero the open pass's counts and plan."""
        self.done = {"level": 0, "extra": 0}          # traced in this pass
        self.plan = {"level": 0.0, "extra": None}     # expected in this pass
        self.cells = self.level_start = 0

    def level(self, level: int, cells: int):
        """Direction level ``level`` of this pass is about to test ``cells`` cells (the deepest
        level, M, only traces their midpoints)."""
        per_cell, growth = self.RAYS_PER_CELL0, self.GROWTH0
        if self.cells:
            per_cell = (self.done["level"] - self.level_start) / self.cells
            growth = min(cells / self.cells, 4.0)
        ahead = [cells * growth ** j for j in range(self.M + 1 - level)]
        self.plan["level"] = self.done["level"] + per_cell * sum(ahead[:-1]) + ahead[-1]
        self.cells, self.level_start = cells, self.done["level"]
        self.emit(f"direction level {level}")

    def begin(self, kind: str, rays: int):
        if kind == "extra" and self.plan["extra"] is None:
            self.plan["level"] = self.done["level"]   # the levels are over: exact
            self.plan["extra"] = self.done["extra"] + rays * self.steps
        self.call = (kind, rays, self.clock())

    def tracing(self, frac: float):
        self.emit(partial=frac)

    def end(self):
        kind, rays, t = self.call
        self.rays[kind] += rays
        self.secs[kind] += self.clock() - t
        self.done[kind] += rays
        self.call = None

    def end_pass(self):
        if self.done["level"]:
            self.extra_per_level = self.done["extra"] / self.done["level"]
        self.ended = self.clock()
        self.pass_s += self.ended - self.pass_t0
        self.passes_done, self.open = self.passes_done + 1, False

    def remaining_s(self, partial: float = 0.0) -> float | None:
        """Seconds still expected (None before any ray was timed)."""
        if not self.rays["level"] or not self.secs["level"]:
            return None
        now = self.clock()
        baked = sum(self.pass_trees[:self.passes_done])
        per_tree = self.pass_s / baked if baked and self.pass_s > 0 else None
        between = self.between_s or 0.0
        if self.open:
            left = self._pass_left(now, partial)
            if per_tree is not None and self.plan["extra"] is None:
                # while the levels run: the mean cost per tree of the passes before
                est = per_tree * self.trees - (now - self.pass_t0)
                left = est if est > 0 else left
        else:                               # measuring the viewpoint cells
            left = max(between - (now - self.ended), 0.0)
        future = max(self.passes - self.passes_done - self.open, 0)
        if future:
            trees = self.pass_trees[-1]
            refined = self.pass_trees[1:]
            growth = min(refined[-1] / max(refined[-2], 1), self.PASS_GROWTH_MAX) \
                if len(refined) >= 2 else self.PASS_GROWTH0
            cost = per_tree if per_tree is not None else \
                (now - self.pass_t0 + left) / max(self.trees, 1)
            for k in range(future):
                after_uniform = k == 0 and len(self.pass_trees) == 1   # the first refinement
                trees *= 1.0 if after_uniform else growth
                left += between + cost * trees
        return left + (between if self.open else 0.0)     # the last measurement

    def _pass_left(self, now, partial) -> float:
        """Seconds still expected in the open pass, from its rays."""
        cost = {"level": self.secs["level"] / self.rays["level"]}
        cost["extra"] = (self.secs["extra"] / self.rays["extra"] if self.rays["extra"]
                         else self.EXTRA_COST0 * cost["level"])
        tracing = self.secs["level"] + self.secs["extra"] + (
            now - self.call[2] if self.call is not None else 0.0)
        overhead = (self.pass_s + now - self.pass_t0) / max(tracing, 1e-9)
        plan = dict(self.plan)
        if plan["extra"] is None:
            plan["extra"] = self.extra_per_level * plan["level"]
        left = 0.0
        for kind in ("level", "extra"):
            done = self.done[kind]
            if self.call is not None and self.call[0] == kind:
                done += partial * self.call[1]
            left += max(plan[kind] - done, 0.0) * cost[kind]
        return left * max(overhead, 1.0)

    def emit(self, label: str | None = None, partial: float = 0.0, done: bool = False):
        self.label = label or self.label
        if self.cb is None:
            return
        el = self.clock() - self.t0
        left = 0.0 if done else self.remaining_s(partial)
        if left is None:
            return
        frac = min(max(el / (el + left) if el + left > 0 else 1.0, self.last), 1.0)
        self.last = frac
        where = self.label
        if self.passes > 1 and not done:
            where += f" (pass {min(self.passes_done + 1, self.passes)} of up to {self.passes})"
        self.cb(frac, f"{where}: {100 * frac:.0f}% (eta {left:.0f} s)")
