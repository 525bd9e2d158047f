"""Sharded passes (``cluster``, see ``...cluster``): a pass's direction trees are split into
consecutive blocks (shards), each baked whole by ``bake_shard`` on a cluster worker, and
``ShardedPass.merge`` appends them exactly as one local pass over all of them would have:
direction trees share no samples (sample keys start with the tree id), a pass creates nodes
level by level and samples stage by stage (``state.Stages``), each tree on its own, so the
local order is (level or stage, tree, order within the tree) and the merge interleaves the
shards' blocks in that order (``..shardmerge``)."""

from __future__ import annotations

import time

import numpy as np

from ..dircube import N_SLOTS
from ..shardmerge import MergeBuffers, block_shifts, interleave
from ..tree import SAMPLE_FIELDS, BakeParams, PackedSamples, Samples
from .directions import DirectionPass
from .progress import Progress
from .state import BakeConfig, BakeState
from .tracing import Tracer

# The direction forest's per-node arrays a shard returns and the merge interleaves.
NODE_FIELDS = ("child", "corner", "level", "ix", "iy", "dir_err", "dir_flags")


def bake_shard(st, params: BakeParams, task: dict) -> dict:
    """Bake one shard's direction trees (``ShardedPass.task``) in this process, one core: the
    cluster workers' work. Returns plain arrays: the forest's nodes (level-major: ``node_counts``
    per level), ``root`` per tree, the samples (stage-major: ``sample_counts`` per stage), the
    extra samples, ``rays`` traced and ``cpu_s`` (this thread's CPU seconds)."""
    c0 = time.thread_time()
    cfg = BakeConfig(st, params, workers=1)
    progress = Progress(None, 1, params.direction_depth, params.search_steps)
    state = BakeState.for_shard(cfg, task)
    DirectionPass(cfg, state, Tracer(cfg, state, progress), progress).bake(task["trees"])
    state.grow_records()
    f, i32 = state.dirf, np.int32                # shard-local ids: int32 halves the transfer
    smp, fields = state.samples, SAMPLE_FIELDS
    if task["pack"]:                             # as the cache stores them (codec.py)
        smp, fields = smp.packed(cfg.box_lo, cfg.box_hi), PackedSamples.FIELDS
    return {"level": f.level, "ix": f.ix, "iy": f.iy, "child": f.child.astype(i32),
            "corner": f.corner.astype(i32), "root": f.root[task["trees"]].astype(i32),
            "dir_err": state.dir_err, "dir_flags": state.dir_flags,
            "node_counts": np.bincount(f.level, minlength=cfg.M + 1),
            "sample_counts": state.stages.count, "rays": state.stats.rays,
            "cpu_s": time.thread_time() - c0,
            **{k: getattr(smp, k) for k in fields},
            **{k: v.astype(i32) if k in ("ex_node", "ex_ids", "ex_corner") else v
               for k, v in state.ex.items()}}


class ShardedPass:
    """Bakes a pass's direction trees into ``state`` as shards on ``cfg.cluster``: the tasks
    sent, the merge buffers touched while waiting, the results merged."""

    def __init__(self, cfg: BakeConfig, state: BakeState, progress: Progress):
        self.cfg, self.state, self.progress = cfg, state, progress

    def bake(self, trees) -> None:
        """Consecutive blocks of direction trees ``trees`` baked by ``bake_shard`` on the
        workers, merged here (into buffers touched while waiting)."""
        cfg, prog = self.cfg, self.progress
        blocks = np.array_split(trees, cfg.cluster.shard_count(len(trees)))
        blocks = [b for b in blocks if len(b)]
        buffers = self.buffers(len(trees))
        results = cfg.cluster.run(cfg.st, cfg.params, [self.task(b) for b in blocks],
                                  cfg.cancel, prog.cb, (prog.passes_done, prog.passes), buffers)
        t0 = time.perf_counter()
        self.merge(blocks, results, buffers)
        self.state.stats.merge_s += time.perf_counter() - t0
        self.state.stats.shards += len(blocks)
        prog.end_pass()

    def _id_dtype(self):
        """Dtype of merged node and sample ids (packed: the final tree, as a file holds it)."""
        return np.dtype(np.int32 if self.cfg.pack else np.int64)

    def buffers(self, trees: int) -> MergeBuffers:
        """Buffers for the merge of a pass over ``trees`` direction trees."""
        groups = {k: "nodes" for k in NODE_FIELDS}
        groups.update({k: "samples" for k in (PackedSamples.FIELDS if self.cfg.pack
                                               else SAMPLE_FIELDS)})
        return MergeBuffers(groups, {"nodes": len(self.state.dirf.child),
                                     "samples": len(self.state.samples)}, trees,
                            {"child": self._id_dtype(), "corner": self._id_dtype()})

    def task(self, block) -> dict:
        """What a worker needs to bake direction trees ``block`` (sorted): their viewpoints and
        baked rectangles, renumbered from 0 in the same order."""
        s = self.state
        vps, inv = np.unique(block // N_SLOTS, return_inverse=True)
        rows = (vps[:, None] * N_SLOTS + np.arange(N_SLOTS)).ravel()
        return {"trees": inv.ravel() * N_SLOTS + block % N_SLOTS, "vp_pos": s.vp_pos[vps],
                "vp_face": s.vp_face[vps], "rect": s.rect[rows], "pack": self.cfg.pack}

    def merge(self, blocks, results, buffers=None) -> None:
        """Append the shards' trees (``results`` of ``bake_shard`` for ``blocks``) as one local
        pass over all of them makes them: nodes in (level, shard, shard's order), samples in
        (stage, shard, shard's order); ids in node and sample arrays renumbered to match, shard
        by shard as they are copied. Each array is written once, into ``buffers`` (a
        MergeBuffers) where they hold it."""
        s = self.state
        f, K0, S0 = s.dirf, len(s.dirf.child), len(s.samples)
        s.grow_records()                                                 # grow to K0
        ncount = np.array([r["node_counts"] for r in results])
        scount = np.array([r["sample_counts"] for r in results])
        nshift, sshift = block_shifts(ncount, K0), block_shifts(scount, S0)
        nmaps, smaps, ex = [], [], {k: [v] for k, v in s.ex.items()}
        ids = self._id_dtype()
        for i, (block, r) in enumerate(zip(blocks, results)):
            # new ids of the shard's nodes and samples, and -1 (an id of -1 stays -1)
            nmap = np.append(np.arange(len(r["level"])) + nshift[i, r["level"]], -1).astype(ids)
            smap = np.append(np.arange(len(r["patch"])) + np.repeat(sshift[i], scount[i]),
                             -1).astype(ids)
            nmaps.append(nmap)
            smaps.append(smap)
            f.root[block] = nmap[r["root"]]
            ex["ex_node"].append(nmap[r["ex_node"]])
            ex["ex_ids"].append(smap[r["ex_ids"]])
            for k in ("ex_kind", "ex_pos", "ex_corner"):
                ex[k].append(r[k])
            s.stats.rays += int(r["rays"])
            s.stats.remote_cpu_s += float(r["cpu_s"])

        def merged(name, counts, head, maps=None):
            return interleave([r[name] for r in results], counts, head,
                              None if buffers is None else buffers.get(name), maps)

        f.child = merged("child", ncount, f.child.astype(ids), nmaps)
        f.corner = merged("corner", ncount, f.corner.astype(ids), smaps)
        for k in ("level", "ix", "iy"):
            setattr(f, k, merged(k, ncount, getattr(f, k)))
        s.dir_err = merged("dir_err", ncount, s.dir_err)
        s.dir_flags = merged("dir_flags", ncount, s.dir_flags)
        if self.cfg.pack:              # the first and only pass: nothing to put before it
            s.samples = PackedSamples(**{k: merged(k, scount, results[0][k][:0])
                                         for k in PackedSamples.FIELDS},
                                      lo=self.cfg.box_lo, hi=self.cfg.box_hi)
        else:
            s.samples = Samples(**{k: merged(k, scount, getattr(s.samples, k))
                                   for k in SAMPLE_FIELDS})
        s.ex = {k: np.concatenate(v) for k, v in ex.items()}
        order = np.argsort(s.ex["ex_node"], kind="stable")      # sorted runs: merged
        s.ex = {k: v[order] for k, v in s.ex.items()}
