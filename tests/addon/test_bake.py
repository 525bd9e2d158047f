"""Baking through the operator: a small bake in the worker process, the cache beside the .blend
(relative // path) reloaded with the file, staleness after edits, cancelling (the previous
cache survives), the estimate, and the render engine's reaction to a stale tree."""

import math
import os
import time

import pytest


def _setup(bl, tmp_path):
    bpy = bl.bpy
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=0.5)
    obj = bpy.context.active_object
    bpy.ops.object.camera_add(location=(0, -4, 0.5), rotation=(math.radians(85), 0, 0))
    bpy.context.scene.camera = bpy.context.active_object
    bpy.context.view_layer.objects.active = obj
    blend = tmp_path / "bake_test.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    return obj, blend


def test_bake_cancel_reload_stale(bl, tmp_path):
    bpy = bl.bpy
    ops = bl.operators
    obj, blend = _setup(bl, tmp_path)
    # -- a small blocking bake with options given to the operator
    res = bpy.ops.riray.bake(object=obj.name, viewpoint_depth=1, direction_depth=2,
                             tolerance_deg=1.0, bake_for_cameras=True)
    assert res == {"FINISHED"}
    assert obj.riray.viewpoint_depth == 1 and obj.riray.tolerance_deg == 1.0
    path = bl.cache.cache_path(obj)
    assert path == str(tmp_path / "bake_test.SurfSphere.rit")        # beside the .blend
    assert bl.cache.default_relpath(obj).startswith("//")
    doc = bl.backend.read_header(path)
    assert doc["meta"]["object"] == obj.name and doc["meta"]["params"]["viewpoint_depth"] == 1
    assert len(doc["meta"]["params"]["camera_positions"]) == 1      # a still camera, once
    dg = bpy.context.evaluated_depsgraph_get()
    assert bl.cache.tree_status(obj, dg)["state"] == "fresh"
    assert obj.riray.baked_fingerprint == doc["meta"]["fingerprint"]
    stat0 = os.stat(path)

    # -- cancel a long bake: the previous cache survives untouched
    res = bpy.ops.riray.bake(object=obj.name, viewpoint_depth=6, direction_depth=6, wait=False)
    assert res == {"FINISHED"}
    job = bl.jobs.JOBS[obj.name]
    assert job.running
    t0 = time.time()
    while job.poll() == "running" and job.fraction <= 0.02 and time.time() - t0 < 60:
        time.sleep(0.05)
    assert job.running and 0.0 < job.fraction < 1.0
    assert job.eta is not None
    assert bpy.ops.riray.bake_cancel(object=obj.name) == {"FINISHED"}
    t0 = time.time()
    while ops.poll_jobs() and time.time() - t0 < 30:
        time.sleep(0.05)
    assert job.state == "cancelled"
    st = os.stat(path)
    assert (st.st_mtime_ns, st.st_size) == (stat0.st_mtime_ns, stat0.st_size)
    assert not [f for f in os.listdir(tmp_path) if ".tmp" in f]
    assert not os.path.exists(job.job_dir)

    # -- reload with the file: still fresh
    bpy.ops.wm.save_mainfile()
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    obj = bpy.data.objects["SurfSphere"]
    dg = bpy.context.evaluated_depsgraph_get()
    assert bl.cache.tree_status(obj, dg)["state"] == "fresh"

    # -- a transform, geometry or material change makes it stale
    obj.location.x += 0.1
    bpy.context.view_layer.update()
    assert bl.cache.tree_status(obj, bpy.context.evaluated_depsgraph_get())["state"] == "stale"
    obj.location.x -= 0.1
    bpy.context.view_layer.update()
    assert bl.cache.tree_status(obj, bpy.context.evaluated_depsgraph_get())["state"] == "fresh"
    obj.data.splines[0].points[0].co.z += 0.05
    obj.data.update_tag()
    bpy.context.view_layer.update()
    assert bl.cache.tree_status(obj, bpy.context.evaluated_depsgraph_get())["state"] == "stale"

    # -- the engine tells the user and traces exactly (or refuses when asked to)
    scene = bpy.context.scene
    scene.render.engine = "RIRAY"
    scene.render.resolution_x = scene.render.resolution_y = 16
    scene.render.filepath = str(tmp_path / "stale.png")
    scene.riray.allow_tracing = False
    with pytest.raises(RuntimeError, match="stale"):
        bpy.ops.render.render(write_still=True)

    # -- clear removes the cache
    assert bpy.ops.riray.bake_clear(object=obj.name) == {"FINISHED"}
    assert not os.path.exists(path)
    assert bl.cache.tree_status(obj, bpy.context.evaluated_depsgraph_get())["state"] == "missing"


def test_draft_estimate_within_30_percent(bl, tmp_path):
    """The Draft estimate of the cache size is within 30 % of what a Draft bake writes
    (glass_sphere's three cameras at 100 x 100 pixels). Time is too noisy on a shared machine
    for an assertion: docs/blender.md compares it per preset."""
    import importlib
    from pathlib import Path
    bpy = bl.bpy
    bpy.ops.surface.primitive_nurbs_surface_sphere_add()
    obj = bpy.context.active_object
    obj.riray.quality = "DRAFT"
    params = {**bl.properties.bake_params(obj), "width": 100, "height": 100}
    core_io = importlib.import_module(bl.addon.__name__.rpartition(".")[0] + ".core.scene.io")
    root = Path(__file__).resolve().parents[2]
    scene = core_io.load_scene(root / "sample_scenes" / "glass_sphere.json")
    est = bl.backend.estimate_bake(scene, params)
    tree = bl.backend.bake_tree(scene, params, lambda *a: None, lambda: False)
    size = bl.backend.save_tree(tree, str(tmp_path / "draft.rit"), {})
    assert 0.7 * size <= est["bytes"] <= 1.3 * size, (est["bytes"], size)


def test_draft_estimate_of_one_camera_within_30_percent(bl, tmp_path):
    """The same for a glass NURBS sphere seen by one camera at the factory render size (the
    estimate table's scene in docs/blender.md): what the operator hands the worker, baked."""
    bpy = bl.bpy
    obj, _ = _setup(bl, tmp_path)
    mat = bl.compat.new_material("Glass")
    nodes = mat.node_tree.nodes
    glass = nodes.new("ShaderNodeBsdfGlass")
    mat.node_tree.links.new(glass.outputs[0], nodes["Material Output"].inputs["Surface"])
    obj.data.materials.append(mat)
    obj.riray.quality = "DRAFT"
    scene, params, _ = bl.operators.prepare_bake(bpy.context, obj, bl.report.Report())
    est = bl.backend.estimate_bake(scene, params)
    tree = bl.backend.bake_tree(scene, params, lambda *a: None, lambda: False)
    size = bl.backend.save_tree(tree, str(tmp_path / "draft.rit"), {})
    assert est["kind"] == "glass"
    assert 0.7 * size <= est["bytes"] <= 1.3 * size, (est["bytes"], size)


def test_estimate_and_failed_bake(bl, tmp_path):
    bpy = bl.bpy
    obj, _ = _setup(bl, tmp_path)
    assert bpy.ops.riray.bake_estimate(object=obj.name) == {"FINISHED"}
    assert obj.riray.estimate_time_s > 0 and obj.riray.estimate_bytes > 0
    assert obj.riray.estimate_key == bl.operators.estimate_key(obj)
    # a worker that dies comes back as an operator error; the (absent) cache stays absent
    os.environ["RIRAY_PYTHON"] = "/bin/false"
    try:
        with pytest.raises(RuntimeError, match="failed: the worker exited with code 1"):
            bpy.ops.riray.bake(object=obj.name, viewpoint_depth=1, direction_depth=1)
    finally:
        del os.environ["RIRAY_PYTHON"]
    assert bl.jobs.JOBS[obj.name].state == "failed"
    assert not os.path.exists(bl.cache.cache_path(obj))


def test_bad_settings_refused_before_the_bake(bl, tmp_path):
    """A cache path under a regular file, or parameters core's bake rejects, are refused at
    once with a message naming the problem: no worker is started."""
    bpy = bl.bpy
    obj, _ = _setup(bl, tmp_path)
    last_job = bl.jobs.JOBS.get(obj.name)
    (tmp_path / "afile").write_text("not a folder")
    obj.riray.cache_file = str(tmp_path / "afile" / "sub" / "x.rit")
    with pytest.raises(RuntimeError, match="afile is a file, not a folder"):
        bpy.ops.riray.bake(object=obj.name, viewpoint_depth=1, direction_depth=1)
    assert bl.jobs.JOBS.get(obj.name) is last_job
    obj.riray.cache_file = ""
    p = obj.riray
    p.bake_for_cameras, p.viewpoint_depth, p.viewpoint_refine = True, 9, 2   # both in range
    t0 = time.time()
    with pytest.raises(RuntimeError, match="Viewpoint depth 9 \\+ Viewpoint refine 2 is more "
                                           "than 10"):
        bpy.ops.riray.bake(object=obj.name)
    with pytest.raises(RuntimeError, match="Viewpoint depth 9 \\+ Viewpoint refine 2"):
        bpy.ops.riray.bake_estimate(object=obj.name)
    p.viewpoint_depth, p.min_direction_depth, p.direction_depth = 2, 5, 3
    with pytest.raises(RuntimeError, match="Min direction depth 5 is more than Direction "
                                           "depth 3"):
        bpy.ops.riray.bake(object=obj.name)
    assert time.time() - t0 < 10 and bl.jobs.JOBS.get(obj.name) is last_job
    # the finest-level rule reaches core's bake parameters on camera bakes
    p.viewpoint_depth, p.min_direction_depth, p.finest_min_traced = 3, 1, 20
    assert bl.backend.bake_params(bl.operators.checked_params(obj)).finest_min_traced == 20
    # refinement only applies to camera bakes: off, it is not held against the depth
    p.viewpoint_depth, p.min_direction_depth, p.bake_for_cameras = 9, 1, False
    params = bl.operators.checked_params(obj)
    assert params["viewpoint_refine"] == 0 and params["viewpoint_depth"] == 9
    assert params["finest_min_traced"] == 0


def _fresh(bl, obj):
    return bl.cache.tree_status(obj, bl.bpy.context.evaluated_depsgraph_get())["state"] == "fresh"


def test_cache_follows_the_file_and_the_object(bl, tmp_path):
    """A bake made before the first save moves beside the .blend on saving; renaming the
    object keeps the cache (renamed on the next save); Save As copies it beside the new file
    and leaves the old file's; a duplicate baked after moving gets its own cache."""
    bpy = bl.bpy
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=0.5)
    obj = bpy.context.active_object
    assert bpy.ops.riray.bake(object=obj.name, viewpoint_depth=1, direction_depth=1) == \
        {"FINISHED"}
    temp = bl.cache.cache_path(obj)
    assert os.path.isfile(temp) and not temp.startswith(str(tmp_path)) and _fresh(bl, obj)
    # -- first save: moved beside the .blend, nothing left in the temporary folder
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "a.blend"))
    beside = tmp_path / "a.SurfSphere.rit"
    assert bl.cache.cache_path(obj) == str(beside) and beside.is_file()
    assert not os.path.exists(temp) and _fresh(bl, obj)
    # -- rename: still found; the next save renames the file
    obj.name = "Ball"
    assert _fresh(bl, obj)
    bpy.ops.wm.save_mainfile()
    assert (tmp_path / "a.Ball.rit").is_file() and not beside.exists()
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "a.blend"))
    obj = bpy.data.objects["Ball"]
    assert bl.cache.cache_path(obj) == str(tmp_path / "a.Ball.rit") and _fresh(bl, obj)
    # -- Save As elsewhere: a copy beside the new file; the old file keeps its cache
    (tmp_path / "b").mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "b" / "b.blend"))
    assert bl.cache.cache_path(obj) == str(tmp_path / "b" / "b.Ball.rit") and _fresh(bl, obj)
    assert (tmp_path / "a.Ball.rit").is_file()
    # -- Save Copy: the copy gets a cache, the open file keeps pointing at its own
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "c.blend"), copy=True)
    assert (tmp_path / "c.Ball.rit").is_file()
    assert bl.cache.cache_path(obj) == str(tmp_path / "b" / "b.Ball.rit")
    for blend, rit in (("a.blend", "a.Ball.rit"), ("c.blend", "c.Ball.rit")):
        bpy.ops.wm.open_mainfile(filepath=str(tmp_path / blend))
        obj = bpy.data.objects["Ball"]
        assert bl.cache.cache_path(obj) == str(tmp_path / rit) and _fresh(bl, obj)
    # -- a duplicate shares the cache until it is baked, then it has its own
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    bpy.ops.object.duplicate()
    dup = bpy.context.active_object
    assert dup.name != "Ball" and bl.cache.cache_path(dup) == bl.cache.cache_path(obj)
    dup.location.x += 2.0
    bpy.context.view_layer.update()
    assert bpy.ops.riray.bake(object=dup.name, viewpoint_depth=1, direction_depth=1) == \
        {"FINISHED"}
    own = bl.cache.cache_path(dup)
    assert own != bl.cache.cache_path(obj) and own == str(tmp_path / "c.Ball_001.rit")
    assert _fresh(bl, dup) and _fresh(bl, obj)


def test_quality_presets(bl, tmp_path):
    """A new object bakes at the Default preset, for the scene cameras; choosing a preset
    writes its parameters, editing one makes the quality Custom; the operator applies a preset
    before the parameters given with it."""
    bpy = bl.bpy
    presets = bl.properties.QUALITY
    obj, _ = _setup(bl, tmp_path)
    p = obj.riray
    assert p.quality == "DEFAULT" and p.bake_for_cameras
    assert {k: getattr(p, k) for k in presets["DEFAULT"]} == presets["DEFAULT"]
    cost = [presets[q]["viewpoint_depth"] + presets[q]["direction_depth"]
            for q in ("DRAFT", "FAST", "DEFAULT")]
    assert cost == sorted(cost) and len(set(cost)) == 3
    p.quality = "FAST"
    assert (p.viewpoint_depth, p.direction_depth, p.quality) == (4, 5, "FAST")
    p.tolerance_deg = 0.25
    assert p.quality == "CUSTOM" and p.viewpoint_depth == 4
    assert bpy.ops.riray.bake(object=obj.name, quality="DRAFT", direction_depth=2) == \
        {"FINISHED"}
    assert (p.viewpoint_depth, p.direction_depth, p.viewpoint_refine) == (3, 2, 1)
    assert p.quality == "CUSTOM" and p.tolerance_deg == pytest.approx(1.0)
    doc = bl.backend.read_header(bl.cache.cache_path(obj))
    assert doc["meta"]["params"]["direction_depth"] == 2


def test_eta_is_the_bakes_own_estimate(bl, tmp_path):
    """The job's ETA is the worker's (core's work-weighted) estimate counted down, not the
    elapsed time extrapolated from the fraction."""
    import json
    from types import SimpleNamespace
    job = bl.jobs.BakeJob("x", str(tmp_path / "x.rit"))
    job.job_dir, job.state, job.proc = str(tmp_path), "running", SimpleNamespace(poll=lambda: None)
    job.started = time.time() - 10.0
    (tmp_path / "progress.json").write_text(json.dumps(
        {"fraction": 0.5, "message": "extra samples: 50% (eta 40 s)", "time": 8.0, "eta": 40.0}))
    assert job.poll() == "running" and job.fraction == 0.5
    assert job.eta == pytest.approx(38.0, abs=0.5)          # not 10 s from the fraction
    msg = "extra samples (pass 2 of up to 3): 61% (eta 12 s)"
    assert bl.worker.ETA_RE.search(msg)[1] == "12"


def test_refused_setting_is_not_kept(bl, tmp_path):
    """Settings given to the operator and refused are not stored on the object (nor
    remembered by Blender for the next call): a later bake with valid settings runs. The
    message names the settings as the panel labels them, and the limit."""
    bpy = bl.bpy
    obj, _ = _setup(bl, tmp_path)
    with pytest.raises(RuntimeError) as err:
        bpy.ops.riray.bake(object=obj.name, viewpoint_depth=9, viewpoint_refine=4)
    msg = str(err.value)
    assert "SurfSphere: Viewpoint depth 9 + Viewpoint refine 4 is more than 10" in msg
    assert "pad" not in msg and "viewpoint_tolerance_deg" not in msg and "{" not in msg
    p = obj.riray
    assert (p.viewpoint_depth, p.viewpoint_refine, p.quality) == (5, 2, "DEFAULT")
    assert bpy.ops.riray.bake(object=obj.name, direction_depth=1, viewpoint_refine=0,
                              quality="DRAFT") == {"FINISHED"}
    assert (p.viewpoint_depth, p.direction_depth, p.viewpoint_refine) == (3, 1, 0)


def test_core_refusals_use_the_panels_labels(bl, tmp_path):
    """A bake setting core refuses by a rule the add-on does not check itself (a script can
    pass values the panel's limits would stop) is named as the panel labels it, without core's
    dump of its parameters."""
    obj, _ = _setup(bl, tmp_path)
    for option, words in (({"tolerance_deg": 0.0}, "Angle tolerance (degrees) must be > 0"),
                          ({"search_steps": 40}, "Search steps must be in 0..30")):
        with pytest.raises(bl.report.ExportError) as err:
            bl.operators.checked_params(obj, option)
        assert str(err.value) == f"SurfSphere: the bake settings are refused: {words}"


def test_degenerate_object_refused(bl, tmp_path):
    """A NURBS surface whose control points all coincide (away from the origin), or lie on one
    line (scaled to zero in two axes, or edited so), is refused by Bake, Estimate and F12 before
    any work, naming the object and what is wrong; no worker starts, no temporary folder is
    left."""
    import glob
    import tempfile
    bpy = bl.bpy
    obj, _ = _setup(bl, tmp_path)
    obj.riray.specular = True           # a specular object for F12 (no glass material here)
    points = [tuple(pt.co) for pt in obj.data.splines[0].points]
    bpy.context.scene.render.resolution_x = bpy.context.scene.render.resolution_y = 8
    pattern = os.path.join(tempfile.gettempdir(), "riray_bake_*")
    before = set(glob.glob(pattern))
    last_job = bl.jobs.JOBS.get(obj.name)

    def refused(words):
        bpy.context.view_layer.update()
        for op in (bpy.ops.riray.bake, bpy.ops.riray.bake_estimate):
            with pytest.raises(RuntimeError) as err:
                op(object=obj.name)
            assert f"SurfSphere: the object is degenerate (all its control points {words}" \
                in str(err.value) and "origin" not in str(err.value)
        with pytest.raises(RuntimeError, match="SurfSphere: the object is degenerate"):
            bpy.ops.render.render()
        assert set(glob.glob(pattern)) == before and bl.jobs.JOBS.get(obj.name) is last_job

    obj.location = (2, 0, 0)
    for pt in obj.data.splines[0].points:
        pt.co = (0.3, 0.2, 0.1, 1.0)
    refused("coincide")
    for i, pt in enumerate(obj.data.splines[0].points):
        pt.co = (0.01 * i, -0.02 * i, 0.0, 1.0)
    refused("lie on one line")
    for pt, co in zip(obj.data.splines[0].points, points):
        pt.co = co
    obj.rotation_euler, obj.scale = (0.3, 0.5, 0.7), (1.0, 0.0, 0.0)
    refused("lie on one line")


def test_bake_failure_reads_as_the_panel_speaks(bl, tmp_path):
    """A bake core refuses in the worker (the camera looks away from the object) fails with
    core's own sentence, the camera named as the scene has it and the frame in words: no
    exception type, no internal camera name."""
    bpy = bl.bpy
    obj, _ = _setup(bl, tmp_path)
    scene = bpy.context.scene
    scene.render.resolution_x = scene.render.resolution_y = 16
    scene.camera.rotation_euler = (math.radians(85), 0, math.radians(180))
    with pytest.raises(RuntimeError) as err:
        bpy.ops.riray.bake(object=obj.name, viewpoint_depth=1, direction_depth=1)
    msg = str(err.value).strip()
    assert msg == ("Error: bake of SurfSphere failed: camera 'Camera (frame 1)' does not see the "
                   "object 'SurfSphere' (none of its 16 x 16 pixel rays reaches the object's "
                   "bounding box); nothing to bake"), msg
    job = bl.jobs.JOBS[obj.name]
    assert "Traceback" in job.traceback and not os.path.exists(job.job_dir)


def test_an_animation_bake_covers_each_camera_position_once(bl):
    """Bake for scene cameras with Frame range on: every frame of the range is visited and a
    camera position is kept once however many frames hold it (a move over frames 1-4, then
    still to frame 40: four positions; every second frame with a frame step of 2)."""
    bpy = bl.bpy
    scene = bpy.context.scene
    bpy.ops.object.camera_add(location=(0, -4, 0.5), rotation=(math.radians(85), 0, 0))
    cam = bpy.context.active_object
    scene.camera = cam
    cam.keyframe_insert("location", frame=1)
    cam.location.x = 1.5
    cam.keyframe_insert("location", frame=4)
    scene.frame_start, scene.frame_end, scene.frame_current = 1, 40, 7
    report = bl.report.Report()
    views = bl.operators.camera_views(bpy.context, {"use_frame_range": True}, report)
    xs = [round(float(v.matrix_world[0][3]), 6) for v in views]
    assert len(views) == 4 and len(set(xs)) == 4 and xs[0] == 0.0 and xs[-1] == 1.5
    assert scene.frame_current == 7                       # the current frame is left as it was
    scene.frame_step = 2
    views = bl.operators.camera_views(bpy.context, {"use_frame_range": True}, report)
    assert len(views) == 3                                # frames 1, 3 and 5 onwards
    one = bl.operators.camera_views(bpy.context, {"use_frame_range": False}, report)
    assert len(one) == 1 and round(float(one[0].matrix_world[0][3]), 6) == 1.5


def test_bake_preparation_skips_the_environment_and_still_frames(bl, tmp_path):
    """What the operator does on Blender's main thread before the worker starts stays small
    however heavy the scene: the environment (here a mesh whose modifier changes every frame)
    is not exported, and with Frame range on the frames are visited only when a camera moves
    (each frame change evaluates the whole scene). A keyed camera is still followed."""
    bpy = bl.bpy
    obj, _ = _setup(bl, tmp_path)
    bpy.ops.mesh.primitive_uv_sphere_add(radius=8)
    bpy.context.active_object.modifiers.new("wave", "WAVE")
    bpy.context.view_layer.objects.active = obj
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 30
    visited = []

    def count(sc, *_args):
        visited.append(sc.frame_current)
    bpy.app.handlers.frame_change_pre.append(count)
    try:
        core_scene, params, _ = bl.operators.prepare_bake(bpy.context, obj, bl.report.Report())
        assert params["use_frame_range"] and visited == []
        assert core_scene.meshes == [] and len(core_scene.cameras) == 1
        cam = scene.camera
        cam.keyframe_insert("location", frame=1)
        cam.location.x += 1.0
        cam.keyframe_insert("location", frame=30)
        scene.frame_set(15)
        visited.clear()
        core_scene, _, _ = bl.operators.prepare_bake(bpy.context, obj, bl.report.Report())
        assert set(visited) == set(range(1, 31)) and len(core_scene.cameras) == 30
    finally:
        bpy.app.handlers.frame_change_pre.remove(count)
