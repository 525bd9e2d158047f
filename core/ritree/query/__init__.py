"""Answering rays through the RI-Tree (paper 4.1, 4.2, 4.3, 5.1-5.4), as a list of stages over
one Batch (tree_query.TreeQuery).

For each query ray that enters the padded box: its entry point Q and face give the viewpoint
cell (four viewpoints, bilinear weights); its direction gives the hemicube slot and (u, v);
the four direction trees give four leaf cells (DQs), 16 samples in all. Then
- policy "ri" (the paper): the two-patch condition over the 16 class ids; with two classes
  the exact first hit against only the <= 16 candidate patches picks the class; usable samples
  are those of that class that are not null; each DQ interpolates bilinearly (4 usable),
  barycentrically (3) or from its extra samples (one/two-interpolant cells); the QNode level
  combines the DQs the same way; extrapolation and the pairwise angle/distance thresholds
  apply; anything short of three interpolants at either level is traced exactly - except
  where counting the null samples of the class as usable gives an interpolation whose
  interpolants are all null: that ray may be answered null (``null_interp``; off by default,
  as in the paper: a trapped region can hide an exit no sample shows, see QueryOptions).
- policy "raytree" (Bala et al., for comparison): interpolate only when all 16 samples have
  identical ray trees; trace otherwise.
Interpolated first-hit points and normals feed local illumination; a dielectric's reflected
ray and Fresnel weight come from the interpolated normal. A mirror ray whose usable samples
all reflect once is answered as the exact tracer answers it from its hit: the query direction
reflected about its normal (``mirror_rays``; the paper blends the output rays). By default
("newton"), where those samples share one NURBS patch, the hit and normal are the exact ones
Newton's method finds on it from the interpolated patch parameters (trace.polish), and such a
ray outside the tolerance is answered so too where the bake saw no path change there;
"reflect" uses the interpolated hit and normal.

Modules, in stage order: sets (group rays by sample set), classes (each ray's class: the
two-class first hits), tolerance (the bake's measured errors and flags), units (per (set,
class) decisions), thresholds and weights (per ray), blend and fill (the answers); raytree
(Bala et al.'s policy); batch (the Batch every stage reads and writes), options.
"""

from ..answers import (ANSWER_NAMES, EXTRA_S, EXTRAPOLATED_S, FULL, MISS, NULL_S, OUTSIDE,
                       REDUCED, SOLVED, TRACED, WHY_BLEND, WHY_CLASSES, WHY_NAMES, WHY_PATH, WHY_RAYTREE,
                       WHY_THRESHOLD, WHY_TOLERANCE, WHY_UNSAMPLED, WHY_USABLE, is_interpolated,
                       is_traced)
from .batch import StageClock
from .options import DEFAULT_MAX_ERROR_DEG, MIRROR_RAYS, QueryOptions
from .sets import group_rows
from .tree_query import TRACING_STAGES, TreeQuery

__all__ = ["ANSWER_NAMES", "DEFAULT_MAX_ERROR_DEG", "EXTRAPOLATED_S", "EXTRA_S", "FULL",
           "MIRROR_RAYS", "MISS", "NULL_S", "OUTSIDE", "QueryOptions", "REDUCED", "SOLVED", "StageClock",
           "TRACED", "TRACING_STAGES", "TreeQuery", "WHY_BLEND", "WHY_CLASSES", "WHY_NAMES",
           "WHY_PATH", "WHY_RAYTREE", "WHY_THRESHOLD", "WHY_TOLERANCE", "WHY_UNSAMPLED",
           "WHY_USABLE", "group_rows", "is_interpolated", "is_traced"]
