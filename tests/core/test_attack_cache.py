"""Crafted and damaged RI-Tree files and trees that see nothing cannot hurt the reader.

Every hostile file here carries valid checksums (header crc32, per-array crc32, whole-file
sha256), so only the reader's own checks stand between it and the tree: a header nested
100,000 deep, header fields missing or of the wrong type, every index array pointing outside
what it indexes, declared lengths that disagree with the tree's counts (a 4 GiB error array),
unknown arrays, decompression bombs and truncated files. Each must be refused in one line that
says to re-bake, before any oversized array is decoded. A tree loaded into memory survives its
file being truncated, and a camera that does not see the object is refused before the bake.
"""

import hashlib
import json
import lzma
import mmap
import os
import re
import struct
import zlib

import numpy as np
import pytest

from riray.cli import main
from riray.ritree import cache, filters
from riray.ritree import tree as ritree
from riray.ritree.bake import bake
from riray.ritree.cache import TreeCacheError
from riray.ritree.query import TreeQuery
from riray.ritree.region import Region, region_for_cameras
from riray.ritree.tree import BakeParams, check_file
from riray.scene.io import look_at_matrix, save_scene
from riray.scene.model import Camera
from riray.scene.samples import build
from riray.trace.scene_tracer import SceneTracer

PARAMS = BakeParams(viewpoint_depth=1, viewpoint_refine=0, direction_depth=2)


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    """(scene, SceneTracer, path of a small camera tree of glass_sphere with extra samples)."""
    scene = build("glass_sphere")
    st = SceneTracer(scene)
    tree = bake(st, PARAMS, region_for_cameras(st, PARAMS, [scene.camera("close")], 12, 12),
                workers=1)
    assert len(tree.ex_node) and len(tree.samples)
    path = tmp_path_factory.mktemp("t") / "good.rit"
    ritree.save(tree, path)
    return scene, st, path


# --------------------------------------------------------------------------- crafting
def parse(path):
    """(JSON header document, {name: stored bytes}) of a .rit file."""
    raw = path.read_bytes()
    hlen = struct.unpack_from("<Q", raw, 16)[0]
    doc = json.loads(raw[32:32 + hlen])
    start = -(-(32 + hlen) // 64) * 64
    return doc, {e["name"]: raw[start + e["offset"]:start + e["offset"] + e["stored"]]
                 for e in doc["arrays"]}


def write(path, doc, stored, body=None):
    """A .rit file of ``doc`` (offsets and payload size laid out anew) and the ``stored``
    bytes, every checksum valid; ``body``: raw JSON header bytes instead of ``doc``'s."""
    payload, offset = b"", 0
    for e in doc["arrays"]:
        data = stored[e["name"]]
        payload += bytes(offset - len(payload)) + data
        e.update(offset=offset, stored=len(data))
        offset = -(-(offset + len(data)) // 64) * 64
    doc["payload_bytes"] = len(payload)
    body = json.dumps(doc).encode() if body is None else body
    head = cache.MAGIC + b"\xff\xfe" + struct.pack("<IQI4x", 2, len(body), zlib.crc32(body))
    head += body + bytes(-(len(head) + len(body)) % 64)
    data = head + payload
    path.write_bytes(data + b"RIRAYEND" + hashlib.sha256(data).digest())
    return path


def replace_array(doc, stored, name, arr, chain=("lzma",)):
    """Store ``arr`` as array ``name`` (new dtype and shape, valid crc32) under ``chain``."""
    arr = np.ascontiguousarray(arr)
    e = next(x for x in doc["arrays"] if x["name"] == name)
    e.update(dtype=arr.dtype.str, shape=list(arr.shape), nbytes=arr.nbytes,
             crc32=zlib.crc32(arr.reshape(-1).view(np.uint8)), filters=list(chain))
    stored[name] = filters.encode(arr, chain) if chain else arr.tobytes()


def arrays_of(path):
    return cache.load_tree(path)[1]


def refused(path, scene, match):
    """The file is refused with one TreeCacheError naming it, saying to re-bake."""
    with pytest.raises(TreeCacheError, match=match) as info:
        ritree.load(path, scene)
    msg = str(info.value)
    assert str(path) in msg and "\n" not in msg
    return msg


def cli_refuses(capsys, argv, match):
    """The command exits 2 with one line on stderr matching ``match``."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"riray {argv[0]}: error: "), err
    assert re.search(match, err[0]), err[0]


# --------------------------------------------------------------------------- the header
def test_deep_header_is_refused_without_parsing(baked, tmp_path, capsys):
    _, _, good = baked
    doc, stored = parse(good)
    doc["header"]["deep"] = "@"
    body = json.dumps(doc).encode().replace(b'"@"', b"[" * 100_000 + b"]" * 100_000)
    path = write(tmp_path / "deep.rit", doc, stored, body=body)
    with pytest.raises(TreeCacheError, match="nested more than 32 levels"):
        cache.describe(path)
    cli_refuses(capsys, ["info", str(path)], "nested more than 32 levels")
    # brackets inside strings are text, not nesting
    doc["header"]["deep"] = "[{" * 1000
    text = write(tmp_path / "text.rit", doc, stored)
    assert cache.describe(text)["header"]["deep"] == "[{" * 1000


def test_oversized_header_is_refused_before_it_is_read(baked, tmp_path):
    _, _, good = baked
    doc, stored = parse(good)
    doc["header"]["pad"] = "x" * cache.MAX_HEADER_BYTES
    with pytest.raises(TreeCacheError, match="header length .* implausible"):
        cache.describe(write(tmp_path / "big.rit", doc, stored))


BAD_HEADERS = [
    (lambda h: h.pop("diag"), "'diag' must be a positive finite number"),
    (lambda h: h.update(diag="0.5"), "'diag' must be a positive finite number"),
    (lambda h: h.update(diag=-1.0), "'diag' must be a positive finite number"),
    (lambda h: h.update(diag=True), "'diag' must be a positive finite number"),
    (lambda h: h.update(diag=float("nan")), "'diag' must be a positive finite number"),
    (lambda h: h.pop("params"), "'params' must hold exactly"),
    (lambda h: h.update(params=[1, 2]), "'params' must hold exactly"),
    (lambda h: h["params"].pop("pad"), "'params' must hold exactly"),
    (lambda h: h["params"].update(extra=1), "'params' must hold exactly"),
    (lambda h: h["params"].update(viewpoint_depth="1"), "'params' must hold exactly"),
    (lambda h: h["params"].update(viewpoint_depth=1.0), "'params' must hold exactly"),
    (lambda h: h["params"].update(search_steps=False), "'params' must hold exactly"),
    (lambda h: h["params"].update(viewpoint_depth=99), "viewpoint_depth must be in 1..9"),
    (lambda h: h["params"].update(pad=float("inf")), "pad must be in"),
    (lambda h: h.pop("layout"), "layout None is not supported"),
    (lambda h: h.update(layout="5"), "layout '5' is not supported"),
]


@pytest.mark.parametrize("change, message", BAD_HEADERS)
def test_missing_or_ill_typed_header_fields(baked, tmp_path, change, message):
    scene, _, good = baked
    doc, stored = parse(good)
    change(doc["header"])
    path = write(tmp_path / "h.rit", doc, stored)
    assert "re-bake" in refused(path, scene, message)


# --------------------------------------------------------------------------- the arrays
BAD_INDICES = [   # (array, new values from the good arrays, message)
    ("vp.leaf_corner", lambda a: a["vp.leaf_corner"] + len(a["vp_pos"]), "vp.leaf_corner holds"),
    ("dir.leaf_corner", lambda a: np.where(a["dir.leaf_corner"] >= 0, len(a["s.patch"]), -1),
     "dir.leaf_corner holds"),
    ("dir.leaf_corner", lambda a: np.full_like(a["dir.leaf_corner"], -2), "dir.leaf_corner holds"),
    ("vp_face", lambda a: np.full_like(a["vp_face"], 6), "vp_face holds"),
    ("s.patch", lambda a: np.where(a["s.patch"] >= 0, len(a["class_of"]), -1).astype(np.int16),
     "s.patch holds"),
    ("ex_node", lambda a: a["ex_node"] + len(a["dir.child"]), "ex_node holds"),
    ("ex_node", lambda a: a["ex_node"][::-1].copy(), "ex_node is not a sorted list"),
    ("ex_node", lambda a: np.full_like(a["ex_node"], a["dir.root"][a["dir.root"] >= 0][0]),
     "ex_node is not a sorted list"),
    ("ex_ids", lambda a: a["ex_ids"] + len(a["s.patch"]), "ex_ids holds"),
    ("ex_kind", lambda a: np.full_like(a["ex_kind"], 3), "ex_kind holds"),
    ("ex_corner", lambda a: np.full_like(a["ex_corner"], 4), "ex_corner holds"),
    ("ex_pos", lambda a: np.full_like(a["ex_pos"], 40000), "ex_pos holds"),
    ("vp.root", lambda a: np.full_like(a["vp.root"], len(a["vp.child"])), "vp forest"),
    ("dir.child", lambda a: np.where(a["dir.child"] >= 0, len(a["dir.child"]) - 2, -1)
     .astype(a["dir.child"].dtype), "dir forest"),
    ("s.tree_code", lambda a: np.full_like(a["s.tree_code"], 200), "disagree in length"),
    ("s.geom", lambda a: np.full_like(a["s.geom"], 3), "geometry codes"),
    ("box_hi", lambda a: a["box_lo"].copy(), "not finite boxes"),
    ("dir.domain", lambda a: np.full_like(a["dir.domain"], np.nan), "not finite boxes"),
]


@pytest.mark.parametrize("name, values, message", BAD_INDICES,
                         ids=[f"{n}-{i}" for i, (n, _, _) in enumerate(BAD_INDICES)])
def test_out_of_range_indices_are_refused(baked, tmp_path, name, values, message):
    scene, _, good = baked
    doc, stored = parse(good)
    a = arrays_of(good)
    replace_array(doc, stored, name, values(a).astype(a[name].dtype))
    path = write(tmp_path / "i.rit", doc, stored)
    assert "re-bake" in refused(path, scene, message)


def test_deep_forest_is_refused(baked, tmp_path):
    """A chain of inner nodes deeper than the bake's direction depth."""
    scene, _, good = baked
    a = arrays_of(good)
    doc, stored = parse(good)
    depth = PARAMS.direction_depth + 3
    child = np.full(1 + 4 * depth, -1, np.int32)
    child[0] = 1
    child[1 + 4 * np.arange(depth - 1)] = 5 + 4 * np.arange(depth - 1)
    trees = len(a["dir.root"])
    root = np.full(trees, -1, np.int32)
    root[0] = 0
    replace_array(doc, stored, "dir.child", child)
    replace_array(doc, stored, "dir.root", root)
    replace_array(doc, stored, "dir.leaf_corner", np.zeros((int((child < 0).sum()), 4), np.int32))
    replace_array(doc, stored, "dir_err", np.zeros(len(child), np.float32))
    replace_array(doc, stored, "dir_flags", np.zeros(len(child), np.uint8))
    replace_array(doc, stored, "ex_node", np.zeros(0, np.int32))
    for k, shape in (("ex_kind", (0,)), ("ex_ids", (0, 4)), ("ex_corner", (0, 4))):
        replace_array(doc, stored, k, np.zeros(shape, a[k].dtype))
    replace_array(doc, stored, "ex_pos", np.zeros((0, 4, 2), np.uint16))
    refused(write(tmp_path / "deep.rit", doc, stored), scene, "deeper than 2 levels")


def test_error_array_bomb_is_refused_before_decoding(baked, tmp_path, monkeypatch):
    """The reproducer: an error array of 4,096 xz streams of 1 MiB of zeros each (a file of
    about a megabyte; the per-array ratio allows it) that would decode to 4 GiB, refused from
    its declared shape alone: nothing of that size is ever decoded."""
    scene, _, good = baked
    doc, stored = parse(good)
    n = 1 << 30                                   # float32: 4 GiB
    stored["dir_err"] = lzma.compress(bytes(1 << 20), format=lzma.FORMAT_XZ,
                                      check=lzma.CHECK_NONE) * 4096
    next(x for x in doc["arrays"] if x["name"] == "dir_err").update(
        shape=[n], nbytes=4 * n, filters=["lzma"])
    path = write(tmp_path / "bomb.rit", doc, stored)
    assert os.path.getsize(path) < 2 << 20
    real = filters.decode

    def decode(data, chain, dtype, shape):
        assert shape != (n,), "the bomb was decoded"
        return real(data, chain, dtype, shape)

    monkeypatch.setattr(filters, "decode", decode)
    refused(path, scene, r"array 'dir_err' is <f4 \[1073741824\], expected <f4 \[\d+\]")


def test_unknown_and_missing_arrays_are_refused(baked, tmp_path):
    scene, _, good = baked
    doc, stored = parse(good)
    doc["arrays"].append(dict(doc["arrays"][0], name="zzz"))
    stored["zzz"] = stored[doc["arrays"][0]["name"]]
    refused(write(tmp_path / "u.rit", doc, stored), scene, r"unknown arrays \['zzz'\]")
    doc, stored = parse(good)
    doc["arrays"] = [x for x in doc["arrays"] if x["name"] != "s.geom"]
    refused(write(tmp_path / "m.rit", doc, stored), scene, r"arrays \['s.geom'\] missing")


@pytest.mark.parametrize("name, dtype", [("dir_err", np.float64), ("s.patch", np.int64),
                                         ("dir.leaf_corner", np.uint32), ("s.geom", np.int8)])
def test_wrong_dtypes_are_refused(baked, tmp_path, name, dtype):
    scene, _, good = baked
    doc, stored = parse(good)
    replace_array(doc, stored, name, arrays_of(good)[name].astype(dtype))
    refused(write(tmp_path / "d.rit", doc, stored), scene, f"array '{name}' is")


def test_consistent_but_inflated_tree_is_refused_by_its_claim(baked):
    """Counts that agree with each other but claim far more than the file holds."""
    _, _, good = baked
    info = cache.describe(good)
    header = info["header"]
    table = {a["name"]: (np.dtype(a["dtype"]), tuple(a["shape"])) for a in info["arrays"]}
    check_file(header, table, info["file_bytes"])
    inner = table["dir.child"][1][0] - table["dir.leaf_corner"][1][0]
    grow = 1 << 22                                  # 2^22 more inner nodes, 3 more leaves each
    k = table["dir.child"][1][0] + 4 * grow
    big = dict(table, **{"dir.child": (np.dtype("<i4"), (k,)), "dir_err": (np.dtype("<f4"), (k,)),
                         "dir_flags": (np.dtype("|u1"), (k,)),
                         "dir.leaf_corner": (np.dtype("<i4"), (k - inner - grow, 4))})
    check_file(header, big)                          # a consistent tree ...
    with pytest.raises(TreeCacheError, match="claim .* bytes, more than 32 times"):
        check_file(header, big, info["file_bytes"])  # ... that this file cannot hold
    with pytest.raises(TreeCacheError, match="not quadtrees"):
        check_file(header, dict(big, **{"dir.leaf_corner": (np.dtype("<i4"), (k - 1, 4))}))


def test_samples_that_would_need_too_much_memory_are_refused(baked):
    """Samples that all miss compress to almost nothing: a consistent table whose arrays stay
    within the claim limit but whose samples would need gigabytes once loaded is refused."""
    _, _, good = baked
    info = cache.describe(good)
    header = info["header"]
    table = {a["name"]: (np.dtype(a["dtype"]), tuple(a["shape"])) for a in info["arrays"]}
    n = 1 << 22                                      # 4 M samples: 2 GiB once loaded
    wide = dict(table, **{"s.patch": (np.dtype("<i2"), (n,)),
                          "s.null_bits": (np.dtype("|u1"), ((n + 7) // 8,)),
                          "s.tree_code": (np.dtype("|u1"), (n,))})
    claimed = sum(int(np.prod(shape)) * dt.itemsize for dt, shape in wide.values())
    assert claimed < ritree.MIN_EXPANSION_BYTES and table["s.patch"][1][0] < n  # within claims
    check_file(header, wide)                          # a consistent tree ...
    with pytest.raises(TreeCacheError, match="would need about .* MiB loaded"):
        check_file(header, wide, info["file_bytes"])  # ... too big to load from this file
    check_file(header, table, info["file_bytes"])     # the real one loads


def test_stream_longer_than_its_array_is_stopped(baked, tmp_path):
    """A valid-length table entry whose xz stream decodes to 64 MiB: stopped at the array's size."""
    scene, _, good = baked
    doc, stored = parse(good)
    stored["s.patch"] = lzma.compress(bytes(64 << 20), format=lzma.FORMAT_XZ,
                                      check=lzma.CHECK_NONE)
    e = next(x for x in doc["arrays"] if x["name"] == "s.patch")
    e["filters"] = ["lzma"]
    refused(write(tmp_path / "s.rit", doc, stored), scene, "'s.patch' does not decode")


def test_patch_classes_must_be_the_objects(baked, tmp_path):
    scene, _, good = baked
    doc, stored = parse(good)
    replace_array(doc, stored, "class_of", np.array([3], np.int64))
    refused(write(tmp_path / "c.rit", doc, stored), scene, "patch classes are not its object's")


def test_cli_refuses_crafted_trees_in_one_line(baked, tmp_path, capsys):
    scene, _, good = baked
    scene_path = tmp_path / "scene.json"
    save_scene(scene, scene_path)
    doc, stored = parse(good)
    doc["header"].pop("diag")
    no_diag = write(tmp_path / "nodiag.rit", doc, stored)
    doc, stored = parse(good)
    replace_array(doc, stored, "ex_ids", arrays_of(good)["ex_ids"] + 10**6)
    far = write(tmp_path / "far.rit", doc, stored)
    rays = tmp_path / "rays.npy"
    np.save(rays, np.array([[0.0, -1.0, 0.9, 0.0, 1.0, 0.0]]))
    for tree, match in ((no_diag, "'diag'"), (far, "ex_ids holds")):
        cli_refuses(capsys, ["render", str(scene_path), "--tree", str(tree), "--width", "8",
                             "--height", "8", "--out", str(tmp_path / "r")], match)
        cli_refuses(capsys, ["trace-rays", str(scene_path), "--rays", str(rays), "--tree",
                             str(tree), "--out", str(tmp_path / "o.npz")], match)


# --------------------------------------------------------------------------- truncation
def test_truncated_tree_is_refused_in_one_line(baked, tmp_path):
    scene, _, good = baked
    raw = good.read_bytes()
    path = tmp_path / "t.rit"
    for n in (len(raw) // 2, len(raw) - 41, len(raw) - 1):
        path.write_bytes(raw[:n])
        refused(path, scene, "truncated")


def test_loaded_tree_holds_no_map_of_its_file(baked, tmp_path):
    """A tree is read into memory: truncating its file afterwards changes nothing (a memory
    map would have turned the next read of it into SIGBUS)."""
    scene, st, good = baked
    path = tmp_path / "t.rit"
    path.write_bytes(good.read_bytes())
    tree = ritree.load(path, scene)
    for k, a in cache.load_tree(path)[1].items():
        while a is not None:                         # the array and every base it views
            assert not isinstance(a, (np.memmap, mmap.mmap)), k
            a = getattr(a, "base", None)
    os.truncate(path, 0)
    rng = np.random.default_rng(1)
    o = np.tile([0.0, -1.2, 0.9], (500, 1))
    d = np.array([0.0, 1.0, 0.0]) + rng.normal(0, 0.05, (500, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    res, ans, _, _ = TreeQuery(tree, st)(o, d)
    ref, ref_ans, _, _ = TreeQuery(ritree.load(good, scene), st)(o, d)
    assert np.array_equal(ans, ref_ans) and np.array_equal(res.out_dir, ref.out_dir)


# --------------------------------------------------------------------------- cameras
def scene_with(*cameras, size=16):
    """glass_sphere (sphere of radius 0.15 at (0, 0, 0.901)) seen by ``cameras`` (name,
    location, target) at ``size`` pixels square."""
    scene = build("glass_sphere")
    scene.cameras = [Camera(name=n, matrix_world=look_at_matrix(o, t), lens=50.0)
                     for n, o, t in cameras]
    scene.render.width = scene.render.height = size
    return scene


AWAY = ("away", (0.0, -1.0, 0.9), (0.0, -2.0, 0.9))      # the reproducer: looks away
CLOSE = ("near", (0.0, -1.0, 0.9), (0.0, 0.0, 0.9))


def test_camera_that_does_not_see_the_object_is_refused_before_baking(tmp_path, capsys,
                                                                       monkeypatch):
    scene = scene_with(AWAY)
    st = SceneTracer(scene)
    with pytest.raises(ValueError, match="camera 'away' does not see the object "
                                         "'glass_sphere'.*nothing to bake"):
        region_for_cameras(st, PARAMS, scene.cameras, 16, 16)
    path = tmp_path / "away.json"
    save_scene(scene, path)
    monkeypatch.setattr("riray.ritree.bake.bake", lambda *a, **k: pytest.fail("baked"))
    cli_refuses(capsys, ["bake", str(path), "--viewpoint-refine", "0", "--out",
                         str(tmp_path / "a.rit")], "camera 'away' does not see the object")
    assert not (tmp_path / "a.rit").exists()


def test_cameras_that_see_the_object_are_baked_the_others_named(tmp_path, capsys):
    scene = scene_with(AWAY, CLOSE)
    region = region_for_cameras(SceneTracer(scene), PARAMS, scene.cameras, 16, 16)
    assert region.unseen == ["away"] and [c.name for c, _, _ in region.cameras] == ["near"]
    path = tmp_path / "two.json"
    save_scene(scene, path)
    out = tmp_path / "two.rit"
    assert main(["bake", str(path), "--viewpoint-depth", "1", "--direction-depth", "2",
                 "--viewpoint-refine", "0", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "riray bake: warning: camera 'away' does not see the object 'glass_sphere'" in err
    assert ritree.load(out, scene).meta["samples"] > 0


def test_object_of_zero_size_is_refused():
    scene = build("glass_sphere")
    surf = scene.object.patches[0].surface
    surf.points[...] = 0.0
    st = SceneTracer(scene)
    for call in (lambda: region_for_cameras(st, PARAMS, scene.cameras, 8, 8),
                 lambda: bake(st, PARAMS, workers=1)):
        with pytest.raises(ValueError, match="'glass_sphere' has a bounding box of size zero"):
            call()


def test_tree_without_samples_traces_every_ray(tmp_path, capsys):
    """A tree baked over no viewpoint cell (what a camera that saw nothing used to leave):
    render and trace-rays answer every ray exactly, with one warning."""
    scene = scene_with(CLOSE)
    st = SceneTracer(scene)
    tree = bake(st, PARAMS, Region(cells=np.zeros((6, 2, 2), bool)), workers=1)
    assert len(tree.samples) == 0 and len(tree.vp_pos) == 0
    path, scene_path, rays = tmp_path / "e.rit", tmp_path / "s.json", tmp_path / "r.npy"
    ritree.save(tree, path)
    save_scene(scene, scene_path)
    rng = np.random.default_rng(2)
    d = np.array([0.0, 1.0, 0.0]) + rng.normal(0, 0.1, (300, 3))
    o = np.tile([0.0, -1.0, 0.9], (300, 1))
    np.save(rays, np.concatenate([o, d / np.linalg.norm(d, axis=1)[:, None]], axis=1))
    assert main(["trace-rays", str(scene_path), "--rays", str(rays), "--tree", str(path),
                 "--out", str(tmp_path / "o.npz")]) == 0
    assert main(["render", str(scene_path), "--camera", "near", "--tree", str(path),
                 "--quiet", "--out", str(tmp_path / "img")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"riray {c}: warning: {path}: the RI-Tree holds no samples; every ray is "
                   "traced exactly" for c in ("trace-rays", "render")]
    got = np.load(tmp_path / "o.npz")
    u = np.load(rays)
    ex = st.object_function(u[:, :3], u[:, 3:])          # (trace-rays renormalizes: ulps)
    assert got["hit"].sum() > 100 and np.array_equal(got["hit"], ex.hit)
    assert np.array_equal(got["null"], ex.null)
    for k in ("out_dir", "out_origin"):
        assert np.allclose(got[k], getattr(ex, k), rtol=0, atol=1e-9), k
