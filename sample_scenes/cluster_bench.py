"""Measures sharded bakes on Dask (docs/benchmarks.md, "Distributed bake (Dask)").

  python sample_scenes/cluster_bench.py plan --depths 3/4 --workers 1 2 4 8 16
      a full bake of the scene on a LocalCluster of each size (processes may outnumber the
      cores: the plan runs all the same): wall, CPU, samples/s, shards, the cluster's overhead
      per shard (CPU of the client, scheduler and worker processes outside the shards' own
      work; the mean idle gap between two shards on a worker thread) and the merge time.
  python sample_scenes/cluster_bench.py project --depths 5/6 --workers 16 64 --sample 6 \
      --overhead S --tree T.rit
      the shard plan of the deeper full bake on W worker threads and the one-core cost of
      ``--sample`` of its shards (spread over the trees), baked here; the client's merge timed
      at full scale (each shard's result stands in for the others of its size; its buffers
      touched first, as the client does while it waits for the shards); projects the
      bake time on W workers from them, ``--overhead`` seconds per shard (``plan``) and the
      client's final write, timed on ``--tree`` (a baked full tree: bytes per sample, speed).

Prints one JSON document per run (times in seconds).
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
import psutil

from riray import cluster as C
from riray.trace.scene_tracer import SceneTracer
from riray.ritree import bake as B
from riray.ritree import tree as ritree
from riray.ritree.tree import BakeParams
from riray.scene.samples import build


def _params(depths: str) -> BakeParams:
    vd, dd = (int(x) for x in depths.split("/"))
    return BakeParams(viewpoint_depth=vd, direction_depth=dd, viewpoint_refine=0).validate()


def _cpu(procs) -> float:
    total = 0.0
    for p in procs:
        try:
            t = p.cpu_times()
            total += t.user + t.system
        except psutil.NoSuchProcess:
            pass
    return total


def plan(args):
    st = SceneTracer(build(args.scene))
    params = _params(args.depths)
    for w in args.workers:
        with C.connect(f"local:{w}") as cl:
            me = psutil.Process()
            kids = me.children(recursive=True)
            inside = {"run_cpu": 0.0, "shard_cpu": 0.0}
            run = cl.run

            def timed(*a, **k):
                c0 = time.process_time()
                res = run(*a, **k)
                inside["run_cpu"] += time.process_time() - c0
                inside["shard_cpu"] += sum(float(r["cpu_s"]) for r in res)
                return res
            cl.run = timed
            cl.client.get_task_stream()                 # start recording
            k0, c0, t0 = _cpu(kids), time.process_time(), time.perf_counter()
            tree = B.bake(st, params, None, cluster=cl)
            wall = time.perf_counter() - t0
            client_cpu, workers_cpu = time.process_time() - c0, _cpu(kids) - k0
            stream = cl.client.get_task_stream()
        n = tree.meta["cluster"]["shards"]
        gaps = _gaps(stream)
        print(json.dumps({
            "scene": args.scene, "depths": args.depths, "workers": w, "shards": n,
            "samples": tree.meta["samples"], "wall_s": round(wall, 2),
            "cpu_s": round(client_cpu + workers_cpu, 2),
            "samples_per_s": round(tree.meta["samples"] / wall),
            "shard_cpu_s": round(inside["shard_cpu"], 2),
            "overhead_cpu_per_shard_s": round((inside["run_cpu"] + workers_cpu
                                               - inside["shard_cpu"]) / n, 4),
            "gap_per_shard_s": round(float(np.mean(gaps)), 4) if len(gaps) else None,
            "merge_s": tree.meta["cluster"]["merge_s"],
            "client_outside_shards_s": round(client_cpu - inside["run_cpu"], 2)}), flush=True)


def _gaps(stream) -> list:
    """Idle seconds between consecutive shards on each worker thread (task stream records)."""
    by_worker = {}
    for rec in stream:
        if not str(rec.get("key", "")).startswith("('riray-shard") and \
                not str(rec.get("key", "")).startswith("riray-shard"):
            continue
        for ss in rec["startstops"]:
            if ss["action"] == "compute":
                by_worker.setdefault((rec["worker"], rec.get("thread")), []).append(
                    (ss["start"], ss["stop"]))
    gaps = []
    for spans in by_worker.values():
        spans.sort()
        gaps += [b[0] - a[1] for a, b in zip(spans, spans[1:])]
    return gaps


class _Plan:
    """A stand-in cluster: plans the shards for ``threads`` worker threads and keeps the
    client's baker and blocks of the first pass instead of running them."""

    def __init__(self, threads):
        self.threads = threads

    def shard_count(self, trees):
        return C.Cluster(None).shard_count(trees, self.threads)


def _first_pass(st, params, threads):
    """(baker, blocks, seconds): the client's state just before its first pass is sharded."""
    plan, kept = _Plan(threads), {}

    def keep(baker, trees):
        n = baker.cfg.cluster.shard_count(len(trees))
        kept["baker"], kept["blocks"] = baker, [b for b in np.array_split(trees, n) if len(b)]
        raise StopIteration
    real, B.ShardedPass.bake = B.ShardedPass.bake, keep
    t0 = time.perf_counter()
    try:
        B.bake(st, params, None, cluster=plan)
    except StopIteration:
        pass
    finally:
        B.ShardedPass.bake = real
    return kept["baker"], kept["blocks"], time.perf_counter() - t0


def _write_rate(path):
    """(bytes per sample, bytes written per second) of saving the tree at ``path`` again."""
    import os
    import tempfile
    tree = ritree.load(path)
    with tempfile.TemporaryDirectory(dir=os.path.dirname(os.path.abspath(path))) as d:
        t0 = time.perf_counter()
        ritree.save(tree, os.path.join(d, "t.rit"))
        secs = time.perf_counter() - t0
        size = os.path.getsize(os.path.join(d, "t.rit"))
    return size / len(tree.samples), size / secs


def project(args):
    st = SceneTracer(build(args.scene))
    params = _params(args.depths)
    per_sample, write_rate = _write_rate(args.tree)
    out = {"scene": args.scene, "depths": args.depths, "overhead_per_shard_s": args.overhead,
           "bytes_per_sample": round(per_sample, 1), "write_bytes_per_s": round(write_rate),
           "workers": {}}
    for w in args.workers:
        baker, blocks, setup = _first_pass(st, params, w)
        sizes = sorted({len(b) for b in blocks})
        baked, cpu, trees_baked = {}, 0.0, 0
        for n in sizes:                     # --sample shards, spread over the trees
            idx = [i for i, b in enumerate(blocks) if len(b) == n]
            for j in np.linspace(0, len(idx) - 1, max(1, args.sample // len(sizes))).round():
                c0 = time.process_time()
                baked.setdefault(n, []).append(
                    B.bake_shard(st, params, baker.task(blocks[idx[int(j)]])))
                cpu += time.process_time() - c0
                trees_baked += n
        per_tree = cpu / trees_baked
        trees = sum(len(b) for b in blocks)
        # every shard's result stands in for one of the same size: the merge at full scale
        results = [baked[len(b)][i % len(baked[len(b)])] for i, b in enumerate(blocks)]
        samples = sum(len(r["patch"]) for r in results)
        # the client's touching of the merge buffers, done while it waits for the shards
        t0 = time.perf_counter()
        buffers = baker.buffers(trees)
        for r, b in zip(results, blocks):
            buffers.add(r, len(b))
        while True:
            before = buffers.touched_bytes
            buffers.touch()
            if buffers.touched_bytes == before:
                break
        touch = time.perf_counter() - t0
        t0 = time.perf_counter()
        baker.merge(blocks, results, buffers)
        merge = time.perf_counter() - t0
        shard_s = per_tree * trees / len(blocks)
        waves = math.ceil(len(blocks) / w)
        write = samples * per_sample / write_rate
        bake_s = setup + waves * (shard_s + args.overhead) + merge + write
        out["workers"][w] = {"trees": trees, "shards": len(blocks),
                             "trees_per_shard": round(trees / len(blocks), 1),
                             "setup_s": round(setup, 2),
                             "sampled_shards": sum(len(v) for v in baked.values()),
                             "cpu_per_tree_s": round(per_tree, 4), "shard_s": round(shard_s, 2),
                             "waves": waves, "samples": samples, "merge_s": round(merge, 2),
                             "touch_s": round(touch, 2), "touched_gb": round(
                                 buffers.touched_bytes / 1e9, 2),
                             "write_s_est": round(write, 2), "bake_s_est": round(bake_s, 1),
                             "merge_share": round(merge / bake_s, 3)}
        print(json.dumps(out["workers"][w]), flush=True)
    print(json.dumps(out))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("plan")
    p.add_argument("--scene", default="glass_sphere")
    p.add_argument("--depths", default="3/4")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    p.set_defaults(fn=plan)
    p = sub.add_parser("project")
    p.add_argument("--scene", default="glass_sphere")
    p.add_argument("--depths", default="5/6")
    p.add_argument("--workers", type=int, nargs="+", default=[16, 64])
    p.add_argument("--sample", type=int, default=6)
    p.add_argument("--overhead", type=float, required=True, help="seconds per shard (plan)")
    p.add_argument("--tree", required=True, help="a baked full tree (.rit), to time the write")
    p.set_defaults(fn=project)
    args = ap.parse_args()
    args.fn(args)


if __name__ == "__main__":
    main()
