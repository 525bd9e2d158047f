"""Baking the RI-Tree (paper 3.3 and 4.3), level by level over all trees at once.

1. Viewpoint trees: the six faces of the padded box, split uniformly to ``viewpoint_depth``;
   only the leaf cells in the requested region get their corner viewpoints (shared corners are
   sampled once) and, per viewpoint, the hemicube slots that can see the object (``slots``).
2. Direction trees (``directions``): each level traces the midpoints of all open cells at
   once and splits the cells whose interpolation misses them.
3. Extra samples for leaves whose corners fall in two classes (``extras``).
4. With cameras, refinement passes split the viewpoint cells where their rays are still
   traced, and the viewpoint cells are measured (``driver``).

The stages share one configuration and one state (``state``); direction trees are traced in
chunks over worker processes (``tracing``) or baked as shards on a cluster (``shards``).
``progress(fraction, message)`` is called between chunks (``progress``) and ``cancel()``
(returning True) stops the bake with ``BakeCancelled``.
"""

from __future__ import annotations

import os
import time

from ..cache import fingerprint
from ..derive import derive
from ..region import Region, check_object
from ..tree import BakeParams, PackedSamples, RITree
from ..verify import MEASURE_MIRROR_RAYS
from .driver import FINEST_TOLERANCE_DEG, REFINE_ANGLE_DEG, Baker, finest_rule, refine_rule
from .progress import Progress
from .shards import ShardedPass, bake_shard
from .slots import SLOT_MIN_DEPTH, rect_sees_boxes, rects_see_object
from .state import TRACE_CHUNK, BakeConfig
from .tracing import BakeCancelled, Tracer

__all__ = ["BakeCancelled", "FINEST_TOLERANCE_DEG", "REFINE_ANGLE_DEG", "SLOT_MIN_DEPTH",
           "TRACE_CHUNK", "Baker", "ShardedPass", "Tracer", "bake", "bake_shard", "finest_rule",
           "rect_sees_boxes", "rects_see_object", "refine_rule"]


def bake(st, params: BakeParams | None = None, region: Region | None = None, progress=None,
         cancel=None, workers=None, cluster=None) -> RITree:
    """Bake the RI-Tree of ``st`` (trace.scene_tracer.SceneTracer) with ``params`` over
    ``region``, tracing over ``workers`` local processes, or with ``cluster``
    (``...cluster.Cluster``) as shards on a Dask cluster: the same tree either way.

    With a camera region and ``params.viewpoint_refine`` > 0, the viewpoint cells where the
    cameras' own rays would still be traced (too few usable interpolants, thresholds) or where
    the measured viewpoint-level error exceeds ``viewpoint_tolerance_deg`` (verify.py) are
    split further, up to that many extra levels (non-uniform viewpoint subdivision). The final
    tree's viewpoint-level errors are measured and stored (``vp_err``, ``vp_flags``)."""
    params = (params or BakeParams()).validate()
    check_object(st)
    t0, c0 = time.perf_counter(), _cpu_seconds()
    refine = params.viewpoint_refine if region is not None and region.rays is not None else 0
    prog = Progress(progress, 1 + refine, params.direction_depth, params.search_steps,
                    clock=time.perf_counter)
    # without cameras nothing reads the samples after the bake: shards come back packed
    cfg = BakeConfig(st, params, workers=workers, cancel=cancel, cluster=cluster,
                     pack=region is None or not region.cameras, chunk=TRACE_CHUNK)
    baker = Baker(cfg, prog)
    baker.start(region)
    passes, measured = 0, False
    for _ in range(refine):
        if not baker.refine(region):
            measured = True                    # nothing split since the last measurement
            break
        passes += 1
    if not measured:
        baker.measure(region)
    tree = baker.tree()
    # what the caller renders with is exactly what a cache file stores
    if not isinstance(tree.samples, PackedSamples):
        tree.samples = tree.samples.packed(tree.box_lo, tree.box_hi)
    tree.samples = derive(tree.samples, st.tracer, tree.diag)
    stats = baker.state.stats
    tree.meta.update({"fingerprint": fingerprint(st.scene.object, st.scene.render.max_events),
                      "region": (region or Region()).describe(), "refine_passes": passes,
                      "viewpoint_mirror_rays": MEASURE_MIRROR_RAYS,
                      "bake_seconds": round(time.perf_counter() - t0, 3),
                      "bake_cpu_s": round(_cpu_seconds() - c0 + stats.remote_cpu_s, 3)})
    if cluster is not None:
        tree.meta["cluster"] = {**cluster.describe(), "shards": stats.shards,
                                "merge_s": round(stats.merge_s, 3)}
    prog.emit("done", done=True)
    return tree


def _cpu_seconds() -> float:
    """CPU seconds (user + system) of this process and of its finished worker processes."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system
