"""What ``riray bench`` measures: the table rows, the configuration (:class:`BenchConfig`), the
full and ``--quick`` presets, and the command line that reproduces a configuration."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from ..ritree import tree as ritree
from ..ritree.query import DEFAULT_MAX_ERROR_DEG, QueryOptions
from ..scene.samples import SAMPLES

VIEWS = ("far", "close", "zoom")
ROWS = ("exact", "interp", "interp_angle", "interp_tol", "interp_reflect", "raytree", "deeper",
        "deeper_reflect", "deeper_rules")
ROW_LABELS = {"exact": "ray traced", "interp": "interpolated (no angle threshold)",
              "interp_angle": "interpolated (angle threshold {angle:g} deg)",
              "interp_tol": f"interpolated (default: max error {DEFAULT_MAX_ERROR_DEG:g} deg)",
              "interp_reflect": "default tolerance, mirror rays from the interpolated normal "
                                "(--mirror-rays reflect)",
              "raytree": "raytree policy (Bala et al.)",
              "deeper": "default tolerance, deeper tree (viewpoint depth {vp} + refine {vr}{fm}, "
                         "direction depth {dd})",
              "deeper_reflect": "deeper tree, mirror rays from the interpolated normal",
              "deeper_rules": "deeper tree, default rules without the tolerance (one pass)"}


def paper(**kw) -> QueryOptions:
    """The paper's rules with options ``kw``: no baked-error tolerance, mirror rays
    interpolated, refused rays traced (not solved along a sample's path)."""
    return QueryOptions(**{"max_error_deg": None, "mirror_rays": "interpolate",
                           "solve_paths": False, **kw})


@dataclass
class BenchConfig:
    """What one ``riray bench`` run measures. Depths and tolerances as in BakeParams; angles in
    degrees; distances relative to the object's box diagonal; None switches an option off."""

    out: str = "bench_out"
    scenes: tuple = SAMPLES
    views: tuple = VIEWS
    size: int = 300                       # image side (the paper: 300 x 300, one ray a pixel)
    repeats: int = 3                      # passes per interpolated configuration (median)
    workers: int | None = None
    viewpoint_depth: int = 4              # table trees
    direction_depth: int = 5
    tolerance: float = 0.5                # bake tolerance of the table trees (degrees)
    # (viewpoint depth, direction depth, viewpoint refine[, finest_min_traced]) of the "deeper"
    # row's own tree: the default tolerance on a tree the bake may refine further, where its
    # tests fail, the finest level only where that many camera rays are traced (None: no row)
    deeper_tree: tuple | None = (4, 7, 4, 20)
    angle: float = 20.0                   # the "with threshold" row (the CLI default)
    sweeps: bool = True
    sweep_scenes: tuple = ("glass_sphere", "vase_glass")
    sweep_view: str = "close"
    sweep_repeats: int = 1
    pareto_repeats: int = 3               # passes per policy point (the Pareto curves), median
    vp_depths: tuple = (3, 4, 5)
    dir_depths: tuple = (4, 5, 6)
    tolerances: tuple = (0.25, 0.5, 1.0, 2.0)
    angles: tuple = (None, 45.0, 20.0, 10.0, 5.0)
    distances: tuple = (None, 0.1, 0.05, 0.02)
    extrapolations: tuple = (None, 0.1, 0.25, 0.5)
    max_errors: tuple = (16.0, 8.0, 4.0, 2.0, 1.0, 0.5, 0.25)   # --max-error (no angle threshold)
    path_max_errors: tuple = (4.0, 2.0)          # --max-error with --path-identity
    plots: bool = True
    images: bool = True
    keep_trees: bool = False
    quick: bool = False

    def validate(self) -> "BenchConfig":
        for name in (*self.scenes, *self.sweep_scenes):
            if name not in SAMPLES:
                raise ValueError(f"scenes: unknown sample {name!r}; samples: {', '.join(SAMPLES)}")
        for v in (*self.views, self.sweep_view):
            if v not in VIEWS:
                raise ValueError(f"views: unknown view {v!r}; views: {', '.join(VIEWS)}")
        if self.size < 2:
            raise ValueError(f"size: must be >= 2 (got {self.size})")
        for name in ("repeats", "sweep_repeats", "pareto_repeats"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: must be >= 1 (got {getattr(self, name)})")
        self.bake_params(self.viewpoint_depth, self.direction_depth, self.tolerance)
        if self.deeper_tree is not None:
            if len(self.deeper_tree) not in (3, 4):
                raise ValueError("deeper_tree: (viewpoint depth, direction depth, viewpoint "
                                 f"refine[, finest_min_traced]) (got {self.deeper_tree!r})")
            self.bake_params(*self.deeper_tree[:2], self.tolerance, *self.deeper_tree[2:])
        for vp in self.vp_depths:
            for dd in self.dir_depths:
                self.bake_params(vp, dd, self.tolerance)
        for t in self.tolerances:
            self.bake_params(self.viewpoint_depth, self.direction_depth, t)
        for a in (self.angle, *self.angles, *self.distances, *self.extrapolations,
                  *self.max_errors, *self.path_max_errors):
            if a is not None and not (math.isfinite(a) and a >= 0):
                raise ValueError(f"thresholds: must be finite and >= 0 (got {a!r})")
        return self

    def bake_params(self, vp, dd, tol, refine=None, finest=0) -> ritree.BakeParams:
        """BakeParams with the angular tolerance ``tol`` and the distance tolerance scaled with
        it from the defaults (0.5 deg <-> 0.002 of the box diagonal): one accuracy knob.
        ``refine``: viewpoint refinement levels (None: the default); ``finest``:
        finest_min_traced."""
        d = ritree.BakeParams()
        return ritree.BakeParams(viewpoint_depth=int(vp), direction_depth=int(dd),
                                 viewpoint_refine=d.viewpoint_refine if refine is None
                                 else int(refine),
                                 min_direction_depth=min(d.min_direction_depth, int(dd)),
                                 tolerance_deg=float(tol),
                                 tolerance_dist=d.tolerance_dist * float(tol) / d.tolerance_deg,
                                 finest_min_traced=int(finest)).validate()


# The --quick preset: a smoke check (< 2 minutes on two cores at its default size).
QUICK = dict(scenes=("glass_sphere", "vase_mirror"), views=("close", "zoom"), size=64,
             repeats=1, viewpoint_depth=3, direction_depth=4, sweep_scenes=("glass_sphere",),
             vp_depths=(2, 3), dir_depths=(3, 4), tolerances=(0.5, 2.0),
             angles=(None, 20.0, 5.0), distances=(None, 0.05), extrapolations=(None, 0.25),
             max_errors=(4.0, 1.0), path_max_errors=(2.0,), deeper_tree=(3, 5, 2), pareto_repeats=1,
             quick=True)


def command_line(cfg: BenchConfig) -> str:
    """The ``riray bench`` command that reproduces ``cfg``."""
    ref = BenchConfig(**QUICK) if cfg.quick else BenchConfig()
    parts = ["riray bench"] + (["--quick"] if cfg.quick else [])
    flags = {"scenes": "--scenes", "views": "--views", "size": "--size", "repeats": "--repeats",
             "viewpoint_depth": "--viewpoint-depth", "direction_depth": "--direction-depth",
             "tolerance": "--tolerance", "angle": "--angle", "sweep_scenes": "--sweep-scenes",
             "sweep_repeats": "--sweep-repeats", "pareto_repeats": "--pareto-repeats",
             "workers": "--workers"}
    for k, flag in flags.items():
        v = getattr(cfg, k)
        if v != getattr(ref, k):
            parts.append(f"{flag} {' '.join(map(str, v)) if isinstance(v, tuple) else v}")
    if not cfg.sweeps:
        parts.append("--no-sweeps")
    parts.append(f"--out {cfg.out}")
    return " ".join(parts)


def config_from_args(quick=False, **overrides) -> BenchConfig:
    """A BenchConfig: the full preset (or the --quick one), then every override that is not
    None."""
    base = BenchConfig(**QUICK) if quick else BenchConfig()
    return replace(base, **{k: (tuple(v) if isinstance(v, list) else v)
                            for k, v in overrides.items() if v is not None})
