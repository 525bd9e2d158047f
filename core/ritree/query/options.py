"""Render-time choices of the RI-Tree query (QueryOptions) and their defaults."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# The default render-time tolerance (degrees): on the sample scenes' close views it keeps p99
# errors under 1.4 degrees and maxima under 2.6, and is faster than the paper's 20-degree angle
# threshold, the previous default, on four of the five (vase_glass: 1.83x against 1.86x, for a
# p99 of 1.06 instead of 5.75 degrees; docs/benchmarks.md, the Pareto plots).
DEFAULT_MAX_ERROR_DEG = 2.0

# How a mirror ray is answered (QueryOptions.mirror_rays "interpolate", "reflect", "newton"): the
# blended output ray (the paper);
# the query direction reflected about the interpolated normal at the interpolated hit, for
# units whose usable samples all reflect once; and, where those samples also share one NURBS
# patch, reflected at the exact hit that Newton finds from the interpolated patch parameters.
MIRROR_BLEND, MIRROR_NORMAL, MIRROR_NEWTON = 0, 1, 2
MIRROR_RAYS = ("newton", "reflect", "interpolate")
MANY_CLASSES = ("first_hit", "trace")


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
    many_classes: str = "first_hit"    # a ray whose 16 samples hold more than two classes:
                                       # "first_hit" takes the class of its exact first hit
                                       # (against every patch; a miss is answered exactly, a
                                       # patch none of the samples hit is traced), "trace"
                                       # traces it (the paper's two-patch condition)
    solve_paths: bool = True           # a ray the tolerance or path identity refuses, or
                                       # with too few usable samples, is solved exactly along
                                       # its nearest usable sample's path where it takes that
                                       # path (query/paths.py), else traced
    path_identity: bool = False        # trace rays whose usable samples differ in ray-tree hash
                                       # or whose leaves / cell the bake saw change path
    one_path: bool = True              # under a tolerance (max_error_deg), without
                                       # path_identity: refuse a ray whose usable samples differ
                                       # in ray-tree hash (a blend of two paths interpolates
                                       # neither), to be solved along a path or traced
    mirror_rays: str = "newton"        # mirrors ("ri" policy), a ray whose usable samples all
                                       # reflect once: "reflect" leaves along the query
                                       # direction reflected about the interpolated normal,
                                       # from the interpolated hit point; "newton" (where those
                                       # samples share one NURBS patch) the same at the exact
                                       # hit Newton finds from the interpolated patch
                                       # parameters; "interpolate": the blended output ray (paper)
    certify_first_hits: bool = True    # an exact first hit the query needs is taken from
                                       # Newton on its samples' patches where the occlusion
                                       # proxy shows nothing nearer, and a miss where the proxy
                                       # shows nothing at all (query/certify.py); the full
                                       # search for the rest. False: the full search (paper)
    fresnel_tree: bool = True          # a dielectric's answers carry the reflections at its
                                       # later crossings (trace.objectfn's Fresnel tree): traced
                                       # rays follow it, solved chains too, and with
                                       # solve_paths its interpolated rays are solved to carry
                                       # it (query/paths.py): exact colour, most of the speed-up
                                       # gone; False: the refracted chain alone (the bake's
                                       # rules, which compare output rays)

    def validate(self) -> "QueryOptions":
        if self.policy not in ("ri", "raytree"):
            raise ValueError(f"policy must be 'ri' or 'raytree', got {self.policy!r}")
        if self.threshold_on not in ("intermediate", "samples"):
            raise ValueError("threshold_on must be 'intermediate' or 'samples', "
                             f"got {self.threshold_on!r}")
        if self.threshold_leaves not in ("unverified", "all"):
            raise ValueError("threshold_leaves must be 'unverified' or 'all', "
                             f"got {self.threshold_leaves!r}")
        if self.many_classes not in MANY_CLASSES:
            raise ValueError(f"many_classes must be one of {MANY_CLASSES}, "
                             f"got {self.many_classes!r}")
        if self.mirror_rays not in MIRROR_RAYS:
            raise ValueError(f"mirror_rays must be one of {MIRROR_RAYS}, got {self.mirror_rays!r}")
        for name in ("extrapolation", "angle_deg", "distance", "max_error_deg",
                     "fallback_angle_deg"):
            val = getattr(self, name)
            if val is not None and not (np.isfinite(val) and val >= 0):
                raise ValueError(f"{name} must be None or a finite number >= 0, got {val!r}")
        return self

    @property
    def thresholds(self) -> bool:
        """Some pairwise threshold (angle or distance) is on."""
        return self.angle_deg is not None or self.distance is not None

    @property
    def per_sample(self) -> bool:
        """The pairwise thresholds compare the interpolated samples (not intermediate rays)."""
        return self.thresholds and self.threshold_on == "samples"
