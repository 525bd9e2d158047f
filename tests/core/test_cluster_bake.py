"""Sharded bakes on a real Dask cluster (riray.cluster; 2 worker processes on loopback): the
merged tree is the local bake's tree leaf by leaf, a worker killed mid-shard is replaced and the
tree is still the same, a shard's own error fails the bake with its message, a cancelled bake or
Ctrl-C stops the shards and keeps the previous cache byte for byte, a bad address is exit 2
with one line before any slow work, and the local bake never needs Dask."""

import json
import os
import pickle
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")
import dask  # noqa: E402  (after the skip: installed with distributed)

from riray import cluster as C  # noqa: E402
from riray.cli import main  # noqa: E402
from riray.trace.scene_tracer import SceneTracer  # noqa: E402
from riray.ritree import tree as ritree  # noqa: E402
from riray.ritree.bake import BakeCancelled, bake  # noqa: E402
from riray.ritree.region import region_for_cameras  # noqa: E402
from riray.ritree.tree import BakeParams  # noqa: E402
from riray.scene.samples import build  # noqa: E402

FULL = BakeParams(viewpoint_depth=1, direction_depth=3, viewpoint_refine=0)
CAMS = BakeParams(viewpoint_depth=1, direction_depth=3, viewpoint_refine=1)
LIMIT_S = 180          # no cluster test may hang: each bake runs under this limit


@pytest.fixture(scope="module")
def cluster():
    with C.connect("local:2") as c:
        yield c


@pytest.fixture(scope="module")
def st():
    return SceneTracer(build("glass_sphere"))


@pytest.fixture(scope="module")
def local_full(st):
    return bake(st, FULL, workers=1)


def _region(st):
    return region_for_cameras(st, CAMS, [st.scene.camera("close")], 40, 40)


def _within(fn, seconds=LIMIT_S):
    """fn() in a thread; its result or exception, failing the test if it runs longer."""
    out = {}

    def target():
        try:
            out["value"] = fn()
        except BaseException as e:      # noqa: BLE001 - handed to the test
            out["error"] = e
    t = threading.Thread(target=target, daemon=True)
    t.start()
    t.join(seconds)
    assert not t.is_alive(), f"still running after {seconds} s"
    if "error" in out:
        raise out["error"]
    return out["value"]


def assert_same_tree(a, b):
    """Structure arrays (every integer array: forests, corners, extra-sample cells, sample
    patches, flags) equal; decoded sample geometry and measured errors within float noise."""
    A, B = a.arrays(), b.arrays()
    assert A.keys() == B.keys()
    for k in A:
        if k.startswith("s.") and k.endswith("_q"):
            continue                                      # compared decoded below
        assert A[k].shape == B[k].shape, k
        if A[k].dtype.kind in "biu":
            np.testing.assert_array_equal(A[k], B[k], err_msg=k)
        else:
            np.testing.assert_allclose(A[k], B[k], rtol=0, atol=1e-6, equal_nan=True, err_msg=k)
    for k in ("out_o", "out_d", "point", "normal"):
        np.testing.assert_allclose(getattr(a.samples, k), getattr(b.samples, k), rtol=0,
                                   atol=1e-6, err_msg=k)
    for k in ("rays_traced", "samples", "extra_cells", "direction_trees", "viewpoints"):
        assert a.meta[k] == b.meta[k], k


def _idle(cluster, seconds=20.0):
    """True once no task is processing on any worker (within ``seconds``)."""
    end = time.time() + seconds
    while time.time() < end:
        if not any(cluster.client.processing().values()):
            return True
        time.sleep(0.1)
    return False


def test_full_bake_on_the_cluster_is_the_local_tree(cluster, st, local_full):
    calls = []
    tree = _within(lambda: bake(st, FULL, cluster=cluster,
                                progress=lambda f, m: calls.append((f, m))))
    assert tree.meta["cluster"]["shards"] >= 8            # the merge interleaved many shards
    assert tree.meta["cluster"]["worker_threads"] == 2
    assert_same_tree(local_full, tree)
    # the merge wrote into the buffers it touched while waiting (views of larger arrays)
    for a in (tree.dir_forest.child, tree.dir_forest.corner, tree.samples.out_d_q):
        assert a.base is not None and a.base.nbytes > a.nbytes
    # progress: shards and samples counted across the cluster, monotone, an ETA once one is done
    frac = [f for f, _ in calls]
    assert np.all(np.diff(frac) >= 0) and frac[-1] == pytest.approx(1.0)
    shard_msgs = [m for _, m in calls if m.startswith("shards ")]
    n = tree.meta["cluster"]["shards"]
    assert shard_msgs[0].startswith(f"shards 0/{n}") and "eta" not in shard_msgs[0]
    assert shard_msgs[-1].startswith(f"shards {n}/{n}, {tree.meta['samples']:,} samples")
    assert all("(eta " in m for m in shard_msgs[1:])
    assert tree.meta["bake_cpu_s"] > 0.5 * local_full.meta["bake_cpu_s"]   # workers' CPU counted


def test_camera_bake_with_refinement_passes_is_the_local_tree(cluster, st):
    local = bake(st, CAMS, _region(st), workers=1)
    tree = _within(lambda: bake(st, CAMS, _region(st), cluster=cluster))
    assert local.meta["refine_passes"] >= 1               # a second pass was merged after the first
    assert tree.meta["refine_passes"] == local.meta["refine_passes"]
    assert_same_tree(local, tree)
    np.testing.assert_allclose(local.vp_err, tree.vp_err, rtol=0, atol=1e-6, equal_nan=True)


def test_worker_killed_mid_shard_is_retried(cluster, st, local_full, tmp_path, monkeypatch):
    marker = str(tmp_path / "died")

    def dies_once(*args):                                  # pickled by value (a local function)
        if not os.path.exists(marker):
            open(marker, "w").close()
            os._exit(1)                                    # the worker process dies mid-shard
        return C.run_shard(*args)
    monkeypatch.setattr(C, "SHARD_TASK", dies_once)
    tree = _within(lambda: bake(st, FULL, cluster=cluster))
    assert os.path.exists(marker)
    assert_same_tree(local_full, tree)
    cluster.client.wait_for_workers(2, timeout=60)        # the nanny restarted it


def test_a_shards_own_error_fails_the_bake_with_its_message(cluster, st, monkeypatch):
    def bad_scene(scene):
        doc = json.loads(real(scene))
        doc["scene"]["object"]["material"]["ior"] = -1.0
        return json.dumps(doc)
    real = C.scene_payload
    monkeypatch.setattr(C, "scene_payload", bad_scene)
    with pytest.raises(ValueError, match=r"object\.material\.ior: must be >="):
        _within(lambda: bake(st, FULL, cluster=cluster), 120)
    assert _idle(cluster)                                  # the other shards were cancelled


def test_cancel_stops_the_shards(cluster, st):
    seen = []

    def cancel():
        return len(seen) >= 2
    with pytest.raises(BakeCancelled):
        _within(lambda: bake(st, FULL, cluster=cluster, cancel=cancel,
                             progress=lambda f, m: seen.append(m)))
    counts = [m.split()[1].rstrip(",").split("/") for m in seen if m.startswith("shards ")]
    assert max(int(done) for done, _ in counts) < int(counts[0][1])    # stopped early
    assert _idle(cluster, 5.0)


def test_ctrl_c_keeps_the_previous_cache(tmp_path, local_full, default_sigint):
    out = tmp_path / "tree.rit"
    ritree.save(local_full, out)
    before = out.read_bytes()
    proc = subprocess.Popen([sys.executable, "-m", "riray.cli", "bake", "glass_sphere", "--full",
                             "--viewpoint-depth", "3", "--direction-depth", "4", "--scheduler",
                             "local:2", "--out", str(out)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=default_sigint)
    line, t0 = "", time.time()
    while "bake:" not in line and time.time() - t0 < 120:   # the first progress of the shards
        line += proc.stderr.read(1)
    assert line.startswith("dask: scheduler tcp://127.0.0.1:"), line
    proc.send_signal(signal.SIGINT)
    try:
        # the workers end their running shard first: on a loaded 2-core machine that took
        # over a minute
        _, err = proc.communicate(timeout=LIMIT_S)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert err.rstrip().endswith("riray bake: interrupted") and "Traceback" not in err
    assert out.read_bytes() == before
    assert not list(tmp_path.glob("tree.rit.*"))         # no temporary file left


@pytest.mark.parametrize("spec, says", [
    ("tcp://127.0.0.1:9", "Dask scheduler tcp://127.0.0.1:9: cannot connect"),
    ("local:0", "--scheduler local:0: expected local:N with N >= 1"),
    ("local:two", "--scheduler local:two: expected local:N with N >= 1")])
def test_bad_scheduler_is_exit_2_one_line_before_slow_work(spec, says, tmp_path, capsys,
                                                           monkeypatch):
    # the scene file is read and its object checked first (cheap, and a bad --object must
    # not wait for a cluster); nothing slow - the tracer's build, the bake - comes before
    import riray.trace.scene_tracer as scene_tracer
    monkeypatch.setattr(scene_tracer, "SceneTracer",
                        lambda *a, **k: pytest.fail("built the tracer first"))
    t0 = time.time()
    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        rc = main(["bake", "glass_sphere", "--full", "--scheduler", spec, "--out",
                   str(tmp_path / "t.rit")])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and err.startswith(f"riray bake: error: {says}"), err
    assert time.time() - t0 < 20
    assert not (tmp_path / "t.rit").exists()


def test_workers_and_scheduler_exclude_each_other(tmp_path, capsys):
    rc = main(["bake", "glass_sphere", "--workers", "2", "--scheduler", "local:2", "--out",
               str(tmp_path / "t.rit")])
    assert rc == 2
    assert "--workers and --scheduler exclude each other" in capsys.readouterr().err


def test_without_dask_the_scheduler_option_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(C.ClusterError, match=r"pip install 'riray\[cluster\]'"):
        C.connect("local:2")


def test_local_bake_and_imports_never_load_dask():
    code = ("import sys, riray.cli, riray.cluster, riray.ritree.bake as b\n"
            "from riray.trace.scene_tracer import SceneTracer\n"
            "from riray.scene.samples import build\n"
            "from riray.ritree.tree import BakeParams\n"
            "b.bake(SceneTracer(build('glass_sphere')), BakeParams(viewpoint_depth=1, "
            "direction_depth=2, viewpoint_refine=0), workers=1)\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_shard_task_pickles_by_the_installed_name():
    f = pickle.loads(pickle.dumps(C.SHARD_TASK))
    assert f is C.run_shard and f.__module__ == "riray.cluster"


def test_shard_count():
    c = C.Cluster(client=None)
    assert c.shard_count(8262, threads=2) == 44            # SHARD_TREES per shard
    assert c.shard_count(8262, threads=64) == 512          # SHARDS_PER_WORKER per thread
    assert c.shard_count(100, threads=64) == 6             # MIN_SHARD_TREES per shard
    assert c.shard_count(3, threads=2) == 1


def test_the_dashboard_is_printed_when_there_is_one(capsys, monkeypatch):
    import riray.cli as cli
    monkeypatch.setattr(C.Cluster, "dashboard", property(lambda self: "http://127.0.0.1:1/status"))
    cli._connect("local:1").close()
    err = capsys.readouterr().err
    assert err.startswith("dask: scheduler tcp://127.0.0.1:") and err.count("\n") == 1
    assert err.rstrip().endswith(", 1 worker threads, dashboard http://127.0.0.1:1/status")


def test_a_lost_scheduler_fails_the_bake(st, tmp_path):
    """A scheduler and a worker of their own (``dask scheduler`` / ``dask worker``); the
    scheduler is killed after the first shard: the bake fails with a message, not a hang."""
    info = tmp_path / "scheduler.json"
    cli = [sys.executable, "-m", "distributed.cli."]
    common = ["--no-dashboard", "--scheduler-file", str(info)]
    procs = [subprocess.Popen(cli[:2] + [cli[2] + "dask_scheduler", "--host", "127.0.0.1",
                                         "--port", "0", *common], stderr=subprocess.DEVNULL)]
    try:
        assert _until_file(info, 60)
        procs.append(subprocess.Popen(cli[:2] + [cli[2] + "dask_worker", "--nthreads", "1",
                                                 *common], stderr=subprocess.DEVNULL))
        address = json.loads(info.read_text())["address"]
        with dask.config.set({"distributed.comm.timeouts.connect": "2s"}):
            c = C.connect(address)
            seen = []

            def progress(frac, msg):
                seen.append(msg)
                if len(seen) == 2:
                    procs[0].kill()                            # the scheduler dies mid-bake
            t0 = time.time()
            with pytest.raises(C.ClusterError, match="Dask scheduler"):
                _within(lambda: bake(st, BakeParams(viewpoint_depth=2, direction_depth=3,
                                                    viewpoint_refine=0), cluster=c,
                                     progress=progress), 120)
            assert time.time() - t0 < 60
            c.close()
    finally:
        for p in procs:
            p.kill()
            p.wait()


def _until_file(path, seconds):
    end = time.time() + seconds
    while not path.exists() and time.time() < end:
        time.sleep(0.1)
    time.sleep(0.2)                                            # written whole
    return path.exists()
