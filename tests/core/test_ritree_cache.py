"""RI-Tree storage: bit-identical .rit round trips (every dtype, empty and 0-d arrays, read
into memory, never memory-mapped), every read error (foreign, truncated, corrupt, malformed, inconsistent, wrong
version, stale), atomic writes under failure, the geometry fingerprint, and the codecs' worst-case
error bounds on a million vectors / points including the octahedron's folds and poles."""

import copy
import json
import lzma
import os
import struct
import time
import zlib

import numpy as np
import pytest

from riray.geometry.primitives import sphere
from riray.ritree import cache, codec, filters
from riray.ritree.cache import StaleTreeError, TreeCacheError
from riray.imageio import encode_png
from riray.scene.model import ObjectMaterial, Patch, SpecularObject

RNG = np.random.default_rng(11)
DTYPES = [np.bool_, np.int8, np.int16, np.int32, np.int64, np.uint8, np.uint16, np.uint32,
          np.uint64, np.float32, np.float64]
SHAPES = [(), (0,), (3, 0, 2), (7,), (4, 5, 3)]
FP = "ab" * 32


def random_array(dtype, shape):
    if dtype is np.bool_:
        return RNG.random(shape) < 0.5
    if np.dtype(dtype).kind == "f":          # arbitrary bit patterns, NaN payloads included
        return RNG.integers(0, 256, size=(*shape, np.dtype(dtype).itemsize), dtype=np.uint8) \
            .view(dtype).reshape(shape)
    info = np.iinfo(dtype)
    return RNG.integers(info.min, info.max, size=shape, dtype=dtype, endpoint=True)


CHAINS = [(), ("lzma",), ("shuffle", "lzma"), ("delta", "shuffle", "lzma"), ("delta",),
          ("shuffle",), ("delta", "lzma")]


@pytest.fixture
def tree(tmp_path):
    """A small valid tree on disk: (path, header, arrays); array "c" is stored compressed."""
    arrays = {"a": np.arange(1000, dtype=np.float64), "b": np.arange(12, dtype=np.int32)
              .reshape(3, 4), "empty": np.zeros((0, 3), np.float32), "s": np.array(7, np.uint8),
              "c": np.tile(np.arange(50, dtype=np.uint16), (40, 3))}
    header = {"format": 1, "fingerprint": FP, "region": {"lo": [0, 0, 0], "hi": [1, 2, 3]},
              "note": "gl\u00e4ss"}
    path = tmp_path / "t.rit"
    cache.save_tree(path, header, arrays, {"c": ("delta", "shuffle", "lzma")})
    return path, header, arrays


def entry(path, name):
    return next(e for e in json.loads(layout(path)[2])["arrays"] if e["name"] == name)


def layout(path):
    """(header_len, data_offset, JSON header bytes) of a file with a sound preamble."""
    raw = path.read_bytes()
    hlen = struct.unpack_from("<Q", raw, 16)[0]
    return hlen, -(-(32 + hlen) // 64) * 64, raw[32:32 + hlen]


def rewrite_header(path, doc=None, body=None):
    """Replace the JSON header (doc, or raw body bytes) keeping a valid header crc32."""
    raw = path.read_bytes()
    _, data_offset, _ = layout(path)
    body = json.dumps(doc).encode() if body is None else body
    head = raw[:16] + struct.pack("<QI4x", len(body), zlib.crc32(body)) + body
    path.write_bytes(head + bytes(-len(head) % 64) + raw[data_offset:])


def flip(path, offset):
    raw = bytearray(path.read_bytes())
    raw[offset] ^= 0x01
    path.write_bytes(bytes(raw))


def error(path, match, exc=TreeCacheError, **kw):
    with pytest.raises(exc, match=match) as info:
        cache.load_tree(path, **kw)
    assert str(path) in str(info.value)


# --------------------------------------------------------------------------- round trips
def compressible(dtype, shape):
    """Smooth integers (that the filters shrink) or repeated bytes."""
    if np.dtype(dtype).kind in "iu":          # a ramp that wraps around the type's range
        size = np.dtype(dtype).itemsize
        start = np.uint64(2 ** (8 * size) - 20)
        ramp = np.arange(int(np.prod(shape)), dtype=np.uint64) * np.uint64(7) + start
        return ramp.astype(f"<u{size}").view(dtype).reshape(shape)
    return np.resize(random_array(dtype, (5,)), shape)


@pytest.mark.parametrize("chain", CHAINS)
def test_round_trip_bit_identical(tmp_path, chain):
    """Every dtype and shape, random (incompressible: stored raw) and compressible arrays, each
    saved under ``chain`` where the dtype allows it."""
    arrays = {f"{np.dtype(t).name}_{i}_{kind}": make(t, s)
              for t in DTYPES for i, s in enumerate(SHAPES + [(300, 4)])
              for kind, make in (("random", random_array), ("smooth", compressible))}
    fits = {k: chain for k, a in arrays.items() if "delta" not in chain or a.dtype.kind in "iu"}
    header = {"fingerprint": FP, "counts": [1, 2], "nested": {"x": None, "y": 1.5, "z": "\u03c0"}}
    path = tmp_path / "all.rit"
    cache.save_tree(path, header, arrays, fits)
    got_header, got = cache.load_tree(path)
    assert got_header == header
    assert list(got) == list(arrays)
    table = {e["name"]: e for e in cache.describe(path)["arrays"]}
    for name, a in arrays.items():
        b = got[name]
        assert b.dtype == a.dtype and b.shape == a.shape and b.tobytes() == a.tobytes(), name
        assert b.flags.writeable and not isinstance(b, np.memmap)
        e = table[name]
        assert e["filters"] in ([], list(fits.get(name, ())))   # raw where it would not shrink
        assert (e["stored"] < e["nbytes"]) == bool(e["filters"])
    if "lzma" in chain:           # the smooth arrays of 1,200 elements do shrink
        assert table["int32_5_smooth"]["filters"] == list(fits["int32_5_smooth"])


def test_filters_match_plain_definitions():
    """delta, shuffle and lzma as the format defines them, against plain loops and the standard
    library's own xz decoder."""
    a = np.array([[65535, 2], [0, 7], [3, 65534]], np.uint16)
    d = np.frombuffer(filters.encode(a, ("delta",)), np.uint16)
    cols = [[65535, 0, 3], [2, 7, 65534]]
    want = [v if i == 0 else (v - c[i - 1]) % 65536 for c in cols for i, v in enumerate(c)]
    assert d.tolist() == want
    b = np.array([0x0102, 0x0304, 0x0506], np.int16)
    assert filters.encode(b, ("shuffle",)) == bytes([2, 4, 6, 1, 3, 5])
    x = np.arange(1000, dtype=np.int64)
    assert lzma.decompress(filters.encode(x, ("lzma",))) == x.tobytes()
    s = np.int32(-5).reshape(())
    assert filters.decode(filters.encode(s, ("delta",)), ("delta",), s.dtype, ()) == s


def test_filter_chains_are_checked():
    for chain in (("zip",), ("lzma", "delta"), ("shuffle", "shuffle"), (1,)):
        with pytest.raises(filters.FilterError, match="subsequence"):
            filters.check_chain(chain, np.dtype("<u2"))
    with pytest.raises(filters.FilterError, match="integer"):
        filters.check_chain(("delta",), np.dtype("<f4"))
    with pytest.raises(filters.FilterError, match="integer"):
        filters.check_chain(("delta",), np.dtype("|b1"))


def test_chunked_streams_round_trip(tmp_path, monkeypatch):
    """An array longer than a chunk is stored as several xz streams, compressed on several
    threads and decoded one after the other; a file cut after the first stream is refused."""
    monkeypatch.setattr(filters, "CHUNK", 4000)
    monkeypatch.setattr(filters, "MIN_STREAM", 4000)
    a = np.arange(30000, dtype=np.int32) // 7
    path = tmp_path / "c.rit"
    cache.save_tree(path, {}, {"a": a}, {"a": ("delta", "shuffle", "lzma")})
    assert np.array_equal(cache.load_tree(path)[1]["a"], a)
    e = entry(path, "a")
    stored = filters.encode(a, e["filters"])
    assert stored.count(b"\xfd7zXZ\x00") == 30 and len(stored) == e["stored"]
    first = filters.encode(a[:1000], ("lzma",))        # one stream of 4,000 bytes
    with pytest.raises(filters.FilterError, match="decode to 4000 bytes, the table says 8000"):
        filters.decode(first, ("lzma",), a.dtype, (2000,))
    assert np.array_equal(filters.decode(first + first, ("lzma",), a.dtype, (2000,)),
                          np.tile(a[:1000], 2))
    monkeypatch.setattr(filters, "MIN_STREAM", 4001)       # streams before the last: too short
    with pytest.raises(filters.FilterError, match="before the last decodes to 4000 bytes"):
        filters.decode(first + first, ("lzma",), a.dtype, (2000,))
    empty = filters.compress(b"")
    assert filters.decode(empty, ("lzma",), a.dtype, (0,)).shape == (0,)
    with pytest.raises(filters.FilterError, match="before the last decodes to 0 bytes"):
        filters.decode(empty * 50000, ("lzma",), a.dtype, (0,))   # refused at the first


@pytest.mark.parametrize("how", ["cancel", "interrupt", "cancel_first"])
def test_cancelled_save_stops_its_encoders_and_keeps_the_old_file(tree, monkeypatch, how):
    """cancel() turning true (or Ctrl-C) while the chunks are encoded: the running encoders see
    their stop flag, the queued chunks never start, and the previous file stays as it was."""
    path = tree[0]
    before = path.read_bytes()
    monkeypatch.setattr(filters, "CHUNK", 1000)
    started = []

    def endless(chunk, stop):                # an encoder that only ends when told to stop
        started.append(len(chunk))
        while not stop():
            time.sleep(0.005)
        raise filters.Stopped()

    monkeypatch.setattr(filters, "compress", endless)

    def cancel():                           # once an encoder runs ("cancel_first": at once)
        if how == "interrupt" and started:
            raise KeyboardInterrupt
        return bool(started) or how == "cancel_first"

    with pytest.raises(KeyboardInterrupt if how == "interrupt" else cache.SaveCancelled):
        cache.save_tree(path, {}, {"a": np.arange(20000, dtype=np.int64)}, {"a": ("lzma",)},
                        cancel=cancel)
    if how == "cancel_first":                # seen before the first array is even filtered
        assert started == []
    else:
        assert 1 <= len(started) <= filters.ENCODE_THREADS < 160      # 160 chunks queued
    assert path.read_bytes() == before and os.listdir(path.parent) == [path.name]


def test_save_progress_follows_the_chunks(tmp_path, monkeypatch):
    """progress hears fractions that never go back, below 1 while chunks remain, then 1.0."""
    monkeypatch.setattr(filters, "CHUNK", 1 << 20)
    monkeypatch.setattr(filters, "MIN_STREAM", 1 << 20)
    monkeypatch.setattr(cache, "POLL_S", 0.001)
    heard = []
    a = (np.arange(1 << 21, dtype=np.int64) * 2654435761) % 1000003   # 16 MiB: 16 chunks
    cache.save_tree(tmp_path / "p.rit", {}, {"a": a}, {"a": ("shuffle", "lzma")},
                    progress=heard.append)
    assert heard[-1] == 1.0 and all(0 <= f < 1 for f in heard[:-1])
    assert heard == sorted(heard) and len(set(heard)) >= 3
    assert np.array_equal(cache.load_tree(tmp_path / "p.rit")[1]["a"], a)


def test_compress_stops_between_pieces():
    data = bytes(3 * filters.PIECE)
    calls = []

    def stop():
        calls.append(1)
        return len(calls) > 2                # true before the third piece
    with pytest.raises(filters.Stopped):
        filters.compress(data, stop)
    assert len(calls) == 3
    assert lzma.decompress(filters.compress(data, lambda: False)) == data


def test_lzma_stream_longer_than_the_table_is_refused():
    """A stream that decodes to more bytes than the array's shape holds is stopped there."""
    big = lzma.compress(bytes(10**6), format=lzma.FORMAT_XZ, check=lzma.CHECK_NONE)
    with pytest.raises(filters.FilterError, match="decode to more than 100 bytes"):
        filters.decode(big, ("lzma",), np.dtype("<u1"), (100,))
    with pytest.raises(filters.FilterError, match="does not decode"):
        filters.decode(big[:-7], ("lzma",), np.dtype("<u1"), (10**6,))


def test_verified_and_unverified_loads_agree_and_inputs_normalised(tmp_path):
    big_endian = np.arange(10, dtype=">f8")
    strided = np.arange(60, dtype=np.int16).reshape(6, 10)[::2, ::3]
    path = tmp_path / "n.rit"
    cache.save_tree(path, {}, {"be": big_endian, "strided": strided})
    _, m = cache.load_tree(path)
    _, c = cache.load_tree(path, verify=False)
    for name, src in (("be", big_endian), ("strided", strided)):
        assert np.array_equal(m[name], src) and np.array_equal(c[name], src)
        assert m[name].dtype.byteorder in "<=|" and m[name].tobytes() == c[name].tobytes()


def test_empty_tree_and_describe(tree, tmp_path):
    path = tmp_path / "none.rit"
    cache.save_tree(path, {"k": 1}, {})
    assert cache.load_tree(path) == ({"k": 1}, {})
    tpath, header, arrays = tree
    flip(tpath, os.path.getsize(tpath) - 100)     # payload damage: describe reads the header only
    info = cache.describe(tpath)
    assert info["header"] == header and info["file_bytes"] == os.path.getsize(tpath)
    assert info["format_version"] == cache.FORMAT_VERSION
    assert [(a["name"], a["dtype"], tuple(a["shape"]), a["nbytes"]) for a in info["arrays"]] == \
        [(n, a.dtype.name, a.shape, a.nbytes) for n, a in arrays.items()]
    c = info["arrays"][-1]
    assert c["filters"] == ["delta", "shuffle", "lzma"] and c["stored"] < c["nbytes"] / 10


# --------------------------------------------------------------------------- read errors
def test_foreign_files(tmp_path):
    png = tmp_path / "img.png"
    png.write_bytes(encode_png(np.zeros((2, 2, 3), np.uint8)))
    error(png, "not a riray tree")
    empty = tmp_path / "empty.rit"
    empty.write_bytes(b"")
    error(empty, "not a riray tree.*empty")
    text = tmp_path / "x.rit"
    text.write_text("hello")
    error(text, "not a riray tree")


def test_wrong_magic_version_byte_order(tree):
    path = tree[0]
    flip(path, 0)
    error(path, "not a riray tree")
    flip(path, 0)
    raw = bytearray(path.read_bytes())
    for old in (1, 3):
        raw[12:16] = struct.pack("<I", old)
        path.write_bytes(bytes(raw))
        error(path, f"format version {old} is not supported.*reads version 2.*re-bake")
    raw[12:16] = struct.pack("<I", 2)
    raw[10:12] = b"\xfe\xff"
    path.write_bytes(bytes(raw))
    error(path, "byte-order mark")


def test_truncated_everywhere(tree):
    path = tree[0]
    raw = path.read_bytes()
    hlen, data_offset, _ = layout(path)
    for n in (5, 12, 20, 40, 32 + hlen - 1, data_offset + 10, len(raw) - 41, len(raw) - 1):
        path.write_bytes(raw[:n])
        error(path, "truncated", verify=False)
    path.write_bytes(raw + b"\0")
    error(path, "trailing bytes")


def test_corrupt_payload_names_array(tree):
    path, _, arrays = tree
    _, data_offset, body = layout(path)
    entry = next(e for e in json.loads(body)["arrays"] if e["name"] == "b")
    flip(path, data_offset + entry["offset"] + 5)
    error(path, "corrupt: array 'b' checksum")
    _, got = cache.load_tree(path, verify=False)     # unverified loads check no crc32
    assert not np.array_equal(got["b"], arrays["b"])


@pytest.mark.parametrize("where", ["stream", "content"])
def test_corrupt_filtered_array_names_it(tree, where):
    """Damage to a compressed array: a stream that fails to decode, or one that decodes to bytes
    of another crc32 (which a verified load catches and an unverified one returns)."""
    path, _, arrays = tree
    e = entry(path, "c")
    _, data_offset, _ = layout(path)
    if where == "stream":
        flip(path, data_offset + e["offset"] + e["stored"] // 2)
        for verify in (True, False):
            error(path, "corrupt: array 'c' (does not decode|checksum)", verify=verify)
        return
    doc = json.loads(layout(path)[2])           # the table's crc32 of "c" no longer fits
    next(x for x in doc["arrays"] if x["name"] == "c")["crc32"] ^= 1
    rewrite_header(path, doc=doc)
    error(path, "corrupt: array 'c' checksum")
    _, got = cache.load_tree(path, verify=False)
    assert np.array_equal(got["c"], arrays["c"])


def test_corrupt_header_padding_trailer(tree):
    path = tree[0]
    raw = path.read_bytes()
    hlen, data_offset, body = layout(path)
    flip(path, 40)
    error(path, "corrupt: header checksum", verify=False)
    b, empty = json.loads(body)["arrays"][1:3]
    gap = b["offset"] + b["nbytes"] + 3                     # zero padding after array "b"
    assert gap < empty["offset"]
    assert 32 + hlen < data_offset                          # header padding exists
    for offset in (32 + hlen, data_offset + gap, len(raw) - 1, len(raw) - 40):
        path.write_bytes(raw)
        flip(path, offset)
        error(path, "whole-file sha256")
        cache.load_tree(path, verify=False)


def test_malformed_header(tree):
    path = tree[0]
    rewrite_header(path, body=b"{not json")
    error(path, "malformed header JSON")
    rewrite_header(path, body=b"\xff\xfe")
    error(path, "malformed header JSON")
    rewrite_header(path, doc={"header": {}, "arrays": []})
    error(path, "malformed header JSON.*payload_bytes")


@pytest.mark.parametrize("change, message", [
    (lambda a: a[0].update(dtype="<c16"), "dtype '<c16'"),
    (lambda a: a[0].update(dtype="|O"), "dtype '\\|O'"),
    (lambda a: a[0].update(dtype=">f8"), "dtype '>f8'"),
    (lambda a: a[1].update(offset=a[0]["offset"] + 64), "overlap"),
    (lambda a: a[1].update(offset=10**9), "outside"),
    (lambda a: a[1].update(offset=8), "unaligned"),
    (lambda a: a[1].update(shape=[5, 4]), "nbytes"),
    (lambda a: a[1].update(shape=[-3, -4]), "non-negative"),
    (lambda a: a[1].update(name="a"), "duplicate"),
    (lambda a: a[1].pop("crc32"), "keys"),
    (lambda a: a[1].pop("filters"), "keys"),
    (lambda a: a[1].update(filters="lzma"), "must be a list"),
    (lambda a: a[1].update(filters=["zip"]), "subsequence"),
    (lambda a: a[0].update(filters=["delta"]), "integer dtype"),
    (lambda a: a[1].update(stored=4), "stored 4 != nbytes 48 without filters"),
    (lambda a: a[4].update(stored=10**9), "outside"),
    (lambda a: a[1].update(shape=[1] * 33), "at most 32 dimensions"),
    (lambda a: a[4].update(shape=[2**32, 2**32, 3], nbytes=3 * 2**65),
     "more than 65536 times its stored"),
])
def test_inconsistent_table(tree, change, message):
    path = tree[0]
    doc = json.loads(layout(path)[2])
    change(doc["arrays"])
    rewrite_header(path, doc=doc)
    error(path, "inconsistent array table: .*" + message, verify=False)


def test_stale(tree):
    path, header, _ = tree
    assert cache.load_tree(path, expect_fingerprint=FP)[0] == header
    error(path, "geometry or material changed since the bake.*re-bake", StaleTreeError,
          expect_fingerprint="cd" * 32)
    cache.save_tree(path, {}, {})
    error(path, "stale", StaleTreeError, expect_fingerprint=FP)


# --------------------------------------------------------------------------- writing
@pytest.mark.parametrize("header, arrays, message", [
    ([], {}, "header must be a dict"),
    ({}, [], "arrays must be a dict"),
    ({}, {1: np.zeros(2)}, "names must be non-empty str"),
    ({}, {"": np.zeros(2)}, "names must be non-empty str"),
    ({}, {"x": [1, 2]}, "not numpy"),
    ({}, {"x": np.zeros(2, np.complex128)}, "unsupported dtype"),
    ({}, {"x": np.zeros(2, np.float16)}, "unsupported dtype"),
    ({}, {"x": np.array(["s"])}, "unsupported dtype"),
    ({}, {"x": np.array([None])}, "unsupported dtype"),
    ({"n": np.int64(3)}, {}, "not JSON-serializable"),
    ({"n": float("nan")}, {}, "not JSON-serializable"),
    ({"n": {1, 2}}, {}, "not JSON-serializable"),
    ({}, {"x": np.zeros(2)}, "filters name arrays that are not saved: \\['y'\\]"),
    ({}, {"y": np.zeros(2)}, "array 'y': filter 'delta' needs an integer dtype"),
])
def test_save_validates_before_writing(tmp_path, header, arrays, message):
    with pytest.raises(TreeCacheError, match=message):
        cache.save_tree(tmp_path / "v.rit", header, arrays, {"y": ("delta", "lzma")})
    assert os.listdir(tmp_path) == []
    with pytest.raises(TreeCacheError, match="filters must be a dict"):
        cache.save_tree(tmp_path / "v.rit", {}, {}, [("lzma",)])


@pytest.mark.parametrize("fail", ["payload", "fsync", "replace"])
def test_atomic_write(tree, monkeypatch, fail):
    path = tree[0]
    before = path.read_bytes()

    def half_write(f, sha, views):
        f.write(b"partial")
        raise KeyboardInterrupt

    def broken(*args):
        raise OSError("disk on fire")

    target = {"payload": (cache, "_write_payload", half_write), "fsync": (os, "fsync", broken),
              "replace": (os, "replace", broken)}[fail]
    monkeypatch.setattr(*target)
    with pytest.raises((KeyboardInterrupt, OSError)):
        cache.save_tree(path, {"new": True}, {"z": np.ones(10**5)})
    assert path.read_bytes() == before
    assert os.listdir(path.parent) == [path.name]


# --------------------------------------------------------------------------- fingerprint
def make_object():
    tri = Patch("tri", 1, vertices=np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]),
                triangles=np.array([[0, 1, 2]]))
    return SpecularObject("obj", [Patch("ball", 0, surface=sphere((0, 0, 1), 0.5)), tri],
                          ObjectMaterial(kind="glass", ior=1.5))


def moved_point(obj):
    pts = obj.patches[0].surface.points
    old = pts[2, 3, 2]
    pts[2, 3, 2] = old * (1 + 1e-12)
    assert pts[2, 3, 2] != old


@pytest.mark.parametrize("change", [
    moved_point,
    lambda o: setattr(o.material, "ior", 1.5000001),
    lambda o: setattr(o.material, "kind", "mirror"),
    lambda o: setattr(o.material, "tint", (1.0, 1.0, 0.9)),
    lambda o: setattr(o.patches[0], "class_id", 5),
    lambda o: o.patches[0].surface.weights.__setitem__((1, 1), 0.7),
    lambda o: o.patches[0].surface.knots_u.__setitem__(-1, 1.0 + 1e-9),
    lambda o: setattr(o.patches[0].surface, "degree_v", 3),
    lambda o: o.patches[1].vertices.__setitem__((2, 2), 1e-15),
    lambda o: setattr(o.patches[1], "triangles", np.array([[0, 2, 1]])),
    lambda o: setattr(o.patches[1], "normals", np.tile([0.0, 0.0, 1.0], (1, 3, 1))),
    lambda o: o.patches.reverse(),
    lambda o: o.patches.pop(),
])
def test_fingerprint_changes(change):
    obj = make_object()
    base = cache.fingerprint(obj, 8)
    change(obj)
    assert cache.fingerprint(obj, 8) != base


def test_fingerprint_stable():
    obj = make_object()
    base = cache.fingerprint(obj, 8)
    assert len(base) == 64 and cache.fingerprint(copy.deepcopy(obj), 8) == base
    assert cache.fingerprint(obj, 9) != base
    obj.name, obj.patches[0].name = "renamed", "other"
    obj.material.ior = 1.5                          # same value, any numeric type
    obj.patches[1].triangles = obj.patches[1].triangles.astype(np.int32)
    assert cache.fingerprint(obj, 8) == base


# --------------------------------------------------------------------------- codecs
def angle(a, b):
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.einsum("...i,...i", a, b))


def test_octahedral_bound_folds_poles_zero():
    v = RNG.normal(size=(1_000_000, 3))
    t = RNG.uniform(-1, 1, 20000)
    s = RNG.uniform(-1e-4, 1e-4, (20000, 2))
    special = np.concatenate([
        np.eye(3), -np.eye(3),                                   # poles and axes
        np.c_[np.cos(np.pi * t), np.sin(np.pi * t), 0 * t],      # equator: the fold line
        np.c_[t, 0 * t, -np.abs(t) - 0.1], np.c_[0 * t, t, -np.abs(t) - 0.1],   # sign folds
        np.c_[s, -np.ones(len(s))], np.c_[s, np.ones(len(s))],  # near the poles
        np.c_[s + 1 / 3, np.full(len(s), 1 / 3)],               # face centres: worst stretch
    ])
    v = np.concatenate([v, special])
    v[:100] *= 1e-200                                   # non-unit inputs encode their direction
    codes = codec.encode_unit_vectors(v)
    assert codes.dtype == np.int16 and codes.shape == (len(v), 2)
    back = codec.decode_unit_vectors(codes)
    assert np.allclose(np.linalg.norm(back, axis=1), 1.0, atol=1e-15)
    err = angle(v, back).max()
    assert 0.9 * codec.OCT_MAX_ERROR < err <= codec.OCT_MAX_ERROR * (1 + 1e-9)
    poles = codec.decode_unit_vectors(codec.encode_unit_vectors([[0, 0, 1.0], [0, 0, -1.0]]))
    assert np.array_equal(poles, [[0, 0, 1], [0, 0, -1]])


def test_octahedral_zero_shapes_errors():
    v = np.zeros((4, 5, 3))
    v[1, 2] = [0, -3, 0]
    back = codec.decode_unit_vectors(codec.encode_unit_vectors(v))
    assert back.shape == v.shape and np.array_equal(back[1, 2], [0, -1, 0])
    mask = np.ones((4, 5), bool)
    mask[1, 2] = False
    assert np.all(back[mask] == 0) and not np.signbit(back[mask]).any()
    assert np.array_equal(codec.encode_unit_vectors(np.zeros(3)), [codec.OCT_ZERO] * 2)
    with pytest.raises(ValueError, match="non-finite"):
        codec.encode_unit_vectors([[np.nan, 0, 1]])
    with pytest.raises(ValueError, match="shape"):
        codec.encode_unit_vectors(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="int16"):
        codec.decode_unit_vectors(np.zeros((3, 2), np.int32))


@pytest.mark.parametrize("bits", [16, 32])
def test_point_quantization_bound_and_clamping(bits):
    lo, hi = np.array([-2.0, 10.0, 5.0]), np.array([3.0, 10.5, 5.0])   # z axis degenerate
    p = lo + RNG.random((1_000_000, 3)) * (hi - lo)
    p[:8] = [[x, y, 5.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])] * 2   # box corners
    codes, clamped = codec.encode_points(p, lo, hi, bits)
    assert clamped == 0 and codes.dtype == codec.POINT_DTYPES[bits]
    back = codec.decode_points(codes, lo, hi)
    bound = codec.point_error_bound(lo, hi, bits)
    slack = 4 * np.finfo(float).eps * np.maximum(np.abs(lo), np.abs(hi))
    assert np.all(np.abs(back - p) <= bound + slack)
    assert bound[2] == 0 and np.all(back[:, 2] == 5.0)
    outside = np.array([[-3.0, 10.2, 5.0], [0.0, 11.0, 5.0], [4.0, 9.0, 4.0], [0.0, 10.2, 5.0]])
    codes, clamped = codec.encode_points(outside, lo, hi, bits)
    assert clamped == 3
    assert np.allclose(codec.decode_points(codes, lo, hi)[:3],
                       [[-2, 10.2, 5], [0, 10.5, 5], [3, 10, 5]], atol=bound.max() + 1e-12)


def test_point_errors():
    with pytest.raises(ValueError, match="lo <= hi"):
        codec.encode_points(np.zeros((1, 3)), [1, 0, 0], [0, 1, 1])
    with pytest.raises(ValueError, match="3-vectors"):
        codec.encode_points(np.zeros((1, 3)), [0, 0], [1, 1])
    with pytest.raises(ValueError, match="non-finite"):
        codec.encode_points([[np.inf, 0, 0]], 0, 1)
    with pytest.raises(ValueError, match="bits"):
        codec.encode_points(np.zeros((1, 3)), [0, 0, 0], [1, 1, 1], bits=8)
    with pytest.raises(ValueError, match="uint16 or uint32"):
        codec.decode_points(np.zeros((1, 3), np.int16), [0, 0, 0], [1, 1, 1])
