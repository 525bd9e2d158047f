"""Evaluation of shader node graphs (``riray.scene.graph``), vectorized over shading points.

``evaluate(graph, points)`` runs every node once over all N points (no per-point loops): float
values are arrays of shape (N,) or () for constants, vectors and colours (N, 3) or (3,), so
constant sub-graphs stay scalars and broadcast. The result is a :class:`Closure`: emitted
radiance (W/m^2/sr, linear RGB) and a diffuse albedo, which Environment shades as
``emission + albedo / pi * (ambient + irradiance)`` (a Whitted renderer's reading of Cycles'
closures: Emission / Background / Principled emission -> emission, Diffuse / Principled base
colour -> albedo, Mix Shader -> weighted sum, Add Shader -> sum).

The node formulas follow Cycles' SVM kernels (intern/cycles/kernel/svm/), in float64:
safe division and modulo give 0 for a zero divisor, colour ramps are read from a 257-entry table
of the ramp as Cycles does (so stops between table entries are smoothed as in Cycles), images
are sampled with pixel centres at (i + 0.5) / W like Cycles' CPU kernel. Non-finite results
(0 ** -1, exp overflow) become 0, as Cycles drops non-finite samples.

Shading points (:class:`ShadingPoints`) follow Cycles' ShaderData: ``normal`` and
``true_normal`` are turned towards the incoming ray, ``incoming`` points back along it. For the
world (``ShadingPoints.world``) the position is the ray direction D and the normals and
incoming vector are -D, as in Cycles' background shading.

Modules: ``values`` (ShadingPoints, Closure, value kinds), ``evaluator`` (the graph walk and
the {node type: evaluation} table), and the node evaluations by kind: ``inputs``, ``maths``,
``colour``, ``procedural`` (checker, gradient, noise), ``images``, ``shaders``.
"""

from .colour import RAMP_TABLE, srgb_to_linear
from .evaluator import EVALUATORS, evaluate
from .images import equirectangular, sample_image
from .maths import FLT_EPSILON
from .procedural import CHECKER_BIAS, NOISE_REPEAT, NOISE_SCALE3, SPHERE_BIAS, hash_uint2
from .values import Closure, ShadingPoints

__all__ = ["CHECKER_BIAS", "EVALUATORS", "FLT_EPSILON", "NOISE_REPEAT", "NOISE_SCALE3",
           "RAMP_TABLE", "SPHERE_BIAS", "Closure", "ShadingPoints", "equirectangular",
           "evaluate", "hash_uint2", "sample_image", "srgb_to_linear"]
