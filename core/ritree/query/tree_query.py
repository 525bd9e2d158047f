"""TreeQuery: answers batches of rays with a baked RI-Tree, as a list of stages over a Batch."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..answers import OUTSIDE, TRACED, WHY_TOLERANCE, is_traced
from ..locate import locate
from .batch import Batch
from .blend import answer, blend_easy
from .classes import classify
from .options import QueryOptions
from .paths import solve_paths
from .raytree import raytree
from .sets import group
from .tolerance import check_misses, one_path, same_path, within_tolerance
from .units import decide
from .weights import weights

# Stages whose time is exact tracing the query calls (the rest is the query's own work):
# "newton" is the tracer's Newton step on known patches (mirror_rays "newton"), "paths" the
# exact solves along samples' paths (query/paths.py).
TRACING_STAGES = ("first_hits", "trace", "newton", "paths")


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
        # perspective-weighted copy, dense leaf tables, answerable-leaf flags, paths by group
        tree.attach_geometry(st.tracer)
        self.table = tree.table
        tree.blend_vals, tree.vp_locator, tree.dir_locator
        tree.leaf_ok, tree.leaf_sampled, tree.cell_rect
        if self.material.kind == "mirror" and self.opt.one_path:
            tree.class_paths         # a mirror's paths by patch group (tolerance.one_path)
        # the occlusion proxy of the path solver (query/paths.py) and of certified first hits
        # (query/certify.py)
        self.proxy = st.tracer.occlusion_proxy \
            if self.opt.solve_paths or self.opt.certify_first_hits else None
        # a bake that measured no viewpoint cell (a full tree, or one whose every test ray was
        # traced) left no viewpoint-level errors to bound
        if (self.opt.max_error_deg is not None and self.opt.fallback_angle_deg is not None
                and np.isnan(tree.vp_err).all()):
            self.opt = replace(self.opt, max_error_deg=None,
                               angle_deg=self.opt.angle_deg if self.opt.angle_deg is not None
                               else self.opt.fallback_angle_deg)

    @property
    def max_angle(self):
        """The pairwise angle threshold in radians (None: off)."""
        return None if self.opt.angle_deg is None else np.radians(self.opt.angle_deg)

    @property
    def max_dist(self):
        """The pairwise distance threshold in object units (None: off)."""
        return None if self.opt.distance is None else self.opt.distance * self.tree.diag

    def __call__(self, o, d, tmax=None):
        """(ObjectRays, answers (N,), why (N,), stats) for rays o, d (unit). ``stats`` holds
        ``exact_first_hits``, ``exact_mirror_hits`` and the CPU seconds of each stage
        (``query_<stage>_cpu_s``)."""
        o = np.asarray(o, np.float64)
        d = np.asarray(d, np.float64)
        tmax = np.full(len(o), np.inf) if tmax is None else np.asarray(tmax, np.float64)
        b = Batch.of(o, d, tmax)
        with b.clock("locate"):
            b.loc, outside = locate(self.tree, o, d, tmax)
        b.ans[outside] = OUTSIDE
        if len(b.loc):
            if self.opt.policy == "raytree":
                raytree(self, b)
            else:
                self._ri(b)
        # a ray past the tolerance that Newton did not answer is traced
        b.trace(np.flatnonzero(b.must & ~b.newton_ok & (b.ans != TRACED)), WHY_TOLERANCE)
        if self.opt.solve_paths:
            solve_paths(self, b)
        self._trace(b)
        stats = {"exact_first_hits": b.exact_first_hits,
                 "certified_first_hits": b.certified_first_hits,
                 "exact_mirror_hits": b.exact_mirror_hits, "solved_along_path": b.solved,
                 **{f"query_{k}_cpu_s": v for k, v in b.clock.cpu.items()}}
        return b.res, b.ans, b.why, stats

    def _ri(self, b: Batch) -> None:
        """The paper's policy, stage by stage over the located rays."""
        group(self, b)
        classify(self, b)
        if self.opt.max_error_deg is not None:
            with b.clock("first_hits"):
                check_misses(self, b)
        b.narrow(b.pc >= 0)
        if self.opt.max_error_deg is not None:
            within_tolerance(self, b)
        if self.opt.path_identity:
            same_path(self, b)
        elif self.opt.max_error_deg is not None and self.opt.one_path:
            one_path(self, b)
        if len(b.go) == 0:
            return
        with b.clock("decide"):
            decide(self, b)
        if self.opt.per_sample or not self.opt.thresholds:
            blend_easy(self, b)
        weights(self, b)
        answer(self, b)

    def _trace(self, b: Batch) -> None:
        """Exact tracing of every ray the tree did not answer, in one call."""
        with b.clock("trace"):
            tr = np.flatnonzero(is_traced(b.ans))
            if len(tr):
                ex = self.st.object_function(b.o[tr], b.d[tr], b.tmax[tr],
                                             first=b.known.of(tr),
                                             fresnel_tree=self.opt.fresnel_tree)
                for k, val in ex.__dict__.items():
                    getattr(b.res, k)[tr] = val
