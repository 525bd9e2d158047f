"""Baking on a Dask cluster from Blender: the add-on preference "Scheduler address" sends the
bake operator's work to it (local:2 here: two worker processes on loopback) and the cache
records the cluster's shards; cancelling stops the cluster's processes and keeps the previous
cache; a scheduler that does not answer fails the bake with its one-line message."""

import math
import os
import time

import pytest

pytest.importorskip("distributed")      # the cluster extra (not in the Blender 4.2 environment)
psutil = pytest.importorskip("psutil")  # installed with distributed


def _setup(bl, tmp_path):
    bpy = bl.bpy
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=0.5)
    obj = bpy.context.active_object
    bpy.ops.object.camera_add(location=(0, -4, 0.5), rotation=(math.radians(85), 0, 0))
    bpy.context.scene.camera = bpy.context.active_object
    bpy.context.view_layer.objects.active = obj
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "cluster_test.blend"))
    return obj


def _until(cond, seconds):
    end = time.time() + seconds
    while not cond() and time.time() < end:
        time.sleep(0.05)
    return cond()


def test_bake_on_a_cluster_and_cancel_it(bl, tmp_path, monkeypatch):
    bpy, ops = bl.bpy, bl.operators
    obj = _setup(bl, tmp_path)
    prefs = bpy.context.preferences.addons[bl.properties.ADDON_ID].preferences
    assert prefs.scheduler == ""                          # empty: bake on this machine
    prefs.scheduler = "local:2"
    try:
        res = bpy.ops.riray.bake(object=obj.name, viewpoint_depth=1, direction_depth=2,
                                 tolerance_deg=1.0, bake_for_cameras=True)
        assert res == {"FINISHED"}
        path = bl.cache.cache_path(obj)
        header = bl.backend.read_header(path)["tree"]
        assert header["cluster"]["worker_threads"] == 2 and header["cluster"]["shards"] >= 1
        stat0 = os.stat(path)

        # a long cluster bake, cancelled once its shards run: the cluster's processes end
        res = bpy.ops.riray.bake(object=obj.name, viewpoint_depth=5, direction_depth=6,
                                 wait=False)
        assert res == {"FINISHED"}
        job = bl.jobs.JOBS[obj.name]
        assert _until(lambda: job.poll() != "running" or job.message.startswith("shards "), 120)
        assert job.running, job.error
        cluster_procs = psutil.Process(job.proc.pid).children(recursive=True)
        assert len(cluster_procs) >= 2                    # the LocalCluster's worker processes
        assert bpy.ops.riray.bake_cancel(object=obj.name) == {"FINISHED"}
        assert _until(lambda: not ops.poll_jobs(), 60)
        assert job.state == "cancelled"
        assert _until(lambda: not any(p.is_running() and p.status() != psutil.STATUS_ZOMBIE
                                      for p in cluster_procs), 30)
        st = os.stat(path)
        assert (st.st_mtime_ns, st.st_size) == (stat0.st_mtime_ns, stat0.st_size)

        # a scheduler that does not answer: the bake fails with one line, the cache stays
        prefs.scheduler = "tcp://127.0.0.1:9"
        monkeypatch.setenv("DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT", "2s")
        with pytest.raises(RuntimeError, match=r"Dask scheduler tcp://127\.0\.0\.1:9: cannot "
                                               r"connect"):
            bpy.ops.riray.bake(object=obj.name, viewpoint_depth=1, direction_depth=2)
        assert "\n" not in bl.jobs.JOBS[obj.name].error
        st = os.stat(path)
        assert (st.st_mtime_ns, st.st_size) == (stat0.st_mtime_ns, stat0.st_size)
    finally:
        prefs.scheduler = ""
