"""Bake settings (``BakeParams``), their quality presets (``QUALITY_PRESETS``) and the
constants of the tree's array layout: its version, the extra samples' position codes and the
bits of the bake's per-cell flags."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np

# Version of the tree's array layout inside a .rit file (the file format has its own version):
# a reader refuses other layouts with a message to re-bake. 2: the bake's measured errors and
# flags per direction node and viewpoint node (dir_err, dir_flags, vp_err, vp_flags). 3: what
# follows from the rest is not stored (levels, cell indices and inner corners of the forests,
# the outputs of samples that miss the object), small ranges in small dtypes. 4: each hit
# sample's normalized first-hit patch parameters (s.uv_q), the seeds of the mirror query's
# Newton step. 5: hit points and normals that follow from a sample's patch and parameters are
# not stored (s.geom; derive.py). 6: each hit sample's path seeds, the patches and normalized
# parameters of its events after the first (s.ev_patch, s.ev_uv_q), from which the query
# solves a ray exactly along a sample's path.
TREE_LAYOUT = 6
# Extra samples' cell-local positions are stored as uint16 multiples of 1 / EX_POS_SCALE where
# that is exact (the bake's edge search lands on binary fractions: search_steps <= 15), else
# as float32.
EX_POS_SCALE = 1 << 15
# Bits of dir_flags / vp_flags: what the bake's tests saw in a leaf cell.
UNVERIFIED = 1    # the cell failed its test (error above the tolerance, a class or null state its
                  # corners do not share, no interpolation) and could not be split further
BOUNDARY = 2      # an object/miss boundary crosses it: corners or test rays both hit and miss
                  # (or, direction cells, all miss while their frustum meets the object's boxes)
PATH_CHANGE = 4   # its corners or test rays do not all share one ray-tree hash (event sequence)


@dataclass
class BakeParams:
    """Bake settings. Angles in degrees, distances relative to the object's box diagonal."""

    viewpoint_depth: int = 5          # uniform viewpoint-tree depth (paper: 5)
    viewpoint_refine: int = 2         # extra viewpoint levels where camera rays lack interpolants
                                      # or the viewpoint-level error is too large
    direction_depth: int = 6          # maximum direction-tree depth (paper: 6)
    min_direction_depth: int = 1      # direction trees are split at least this deep
    tolerance_deg: float = 0.5        # split while the midpoint's interpolated output ray ...
    tolerance_dist: float = 0.002     # ... (or first hit / normal) misses the traced one by more
    viewpoint_tolerance_deg: float = 0.25  # split viewpoint cells whose camera test rays answered
                                      # through the tree miss the exact ones by more (verify.py)
    finest_min_traced: int = 0        # > 0: the finest viewpoint level (depth + refine) splits
                                      # only cells through which at least this many camera rays
                                      # are traced under the 2-degree baked-error tolerance
                                      # (bake.finest_rule; 0: by the rule of the other levels)
    search_steps: int = 4             # binary-search steps for the extra samples (paper 4.3):
                                      # a boundary to 1/16 of a cell edge (see docs/ritree.md)
    pad: float = 1e-3                 # bounding-box padding, relative to the diagonal

    def validate(self) -> "BakeParams":
        checks = [
            (1 <= self.viewpoint_depth <= 9, "viewpoint_depth must be in 1..9"),
            (1 <= self.direction_depth <= 10, "direction_depth must be in 1..10"),
            (0 <= self.viewpoint_refine <= 4 and self.viewpoint_depth + self.viewpoint_refine <= 10,
             "viewpoint_refine must be in 0..4 with viewpoint_depth + viewpoint_refine <= 10"),
            (0 <= self.min_direction_depth <= self.direction_depth,
             "min_direction_depth must be in 0..direction_depth"),
            (np.isfinite(self.tolerance_deg) and self.tolerance_deg > 0, "tolerance_deg must be > 0"),
            (np.isfinite(self.tolerance_dist) and self.tolerance_dist > 0,
             "tolerance_dist must be > 0"),
            (np.isfinite(self.viewpoint_tolerance_deg) and self.viewpoint_tolerance_deg > 0,
             "viewpoint_tolerance_deg must be > 0"),
            (0 <= self.search_steps <= 30, "search_steps must be in 0..30"),
            (0 <= self.finest_min_traced <= 1 << 30, "finest_min_traced must be in 0..2^30"),
            (np.isfinite(self.pad) and 0 <= self.pad <= 0.5, "pad must be in [0, 0.5]"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ValueError(f"bake parameters: {msg} (got {asdict(self)})")
        return self

    @classmethod
    def preset(cls, quality: str, **overrides) -> "BakeParams":
        """The parameters of the quality preset ``quality`` (QUALITY_PRESETS), then
        ``overrides`` (BakeParams fields) over them."""
        if quality not in QUALITY_PRESETS:
            raise ValueError(f"bake parameters: unknown quality {quality!r} (one of "
                             f"{', '.join(QUALITY_PRESETS)})")
        return cls(**{**QUALITY_PRESETS[quality], **overrides})


# The BakeParams fields a quality preset sets; the others keep their defaults.
PRESET_FIELDS = ("viewpoint_depth", "direction_depth", "viewpoint_refine", "tolerance_deg")
_DEFAULTS = {f.name: f.default for f in fields(BakeParams)}
# Bake quality presets, coarsest first: name -> the values of PRESET_FIELDS, the same in the CLI
# (riray bake --quality) and the add-on (its Quality menu). "default" is BakeParams' defaults,
# the paper's depths; "fast", for interactive use, bakes two sample scenes' three cameras in
# about a third of default's time, into under half its cache (docs/blender.md); "draft" is the
# quickest bake and smallest cache, with the most rays traced at render time.
QUALITY_PRESETS = {
    "draft": {"viewpoint_depth": 3, "direction_depth": 4, "viewpoint_refine": 1,
              "tolerance_deg": 1.0},
    "fast": {"viewpoint_depth": 4, "direction_depth": 5, "viewpoint_refine": 2,
             "tolerance_deg": 0.5},
    "default": {k: _DEFAULTS[k] for k in PRESET_FIELDS},
}
