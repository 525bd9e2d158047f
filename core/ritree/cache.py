"""The ``.rit`` file: a baked RI-Tree (a JSON header + named numpy arrays) on disk.

Layout of format version 2 (docs/tree-format.md; all integers little-endian):
  preamble  32 bytes  magic b"RIRAYTREE\\0", byte-order mark b"\\xff\\xfe" (uint16 0xFEFF), format
                      version uint32, header length uint64, crc32 of the header uint32, 4 zero bytes
  header    UTF-8 JSON {"header": <user header>, "payload_bytes": P, "arrays": [{"name", "dtype",
                      "shape", "offset", "nbytes", "crc32", "filters", "stored"}, ...]}; zero
                      padding up to a multiple of 64
  payload   P bytes: each array's ``stored`` bytes at ``offset`` (relative to the payload start, a
                      multiple of 64), zero padding between arrays. With no ``filters`` they are its
                      C-order little-endian bytes (``nbytes`` of them); otherwise what the filter
                      chain made of them (filters.py: delta, shuffle, lzma). ``crc32`` is always
                      that of the array's own (decoded) bytes
  trailer   40 bytes  b"RIRAYEND" + sha256 of every byte before the trailer

Writes are atomic (riray.atomic: temporary file beside the target, fsync, os.replace). Reads check the
structure always (magic, version, header crc32, the array table, the file size) and, with
``verify``, every array's crc32 and the whole-file sha256, streaming in ``BLOCK`` byte blocks.
Filtered arrays are encoded on up to ``filters.ENCODE_THREADS`` and decoded on up to
``os.cpu_count()`` threads (lzma releases the GIL).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import struct
import zlib
import threading
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass, fields
from typing import BinaryIO

import numpy as np

from ..files import atomic_write, open_regular
from ..scene.model import SpecularObject
from . import filters as F

MAGIC = b"RIRAYTREE\x00"
BYTE_ORDER_MARK = b"\xff\xfe"          # uint16 0xFEFF written little-endian
FORMAT_VERSION = 2
# Fields after the version may change with the version; magic, mark and version never move.
_IDENT = struct.Struct("<10s2sI")      # magic, byte-order mark, version
_PREAMBLE = struct.Struct("<10s2sIQI4x")   # ... + header length, header crc32, reserved zeros
_TRAILER = struct.Struct("<8s32s")      # end mark, sha256
END_MARK = b"RIRAYEND"
ALIGN = 64                              # bytes; array offsets and the payload start
BLOCK = 4 << 20                         # bytes per streamed read/write/hash block
POLL_S = 0.2                            # seconds between looks at a save's cancel()
MAX_DIMS = 32                           # numpy's limit on an array's dimensions
MAX_RATIO = 1 << 16                     # a filtered array may claim at most this many times
                                        # its stored bytes (xz reaches about 7,000 on constant
                                        # data): a few stored bytes cannot ask for terabytes
MAX_HEADER_BYTES = 1 << 20              # a larger header length is corruption, not a tree
                                        # (a tree's header is about 5 KB)
MAX_HEADER_DEPTH = 32                   # deepest nesting of the JSON header (a tree's: 3)
# Dtypes a tree may hold (little-endian; bool and bytes have no byte order).
DTYPES = frozenset(["|b1", "|i1", "|u1", "<i2", "<u2", "<i4", "<u4", "<i8", "<u8", "<f4", "<f8"])
FINGERPRINT_TAG = b"riray-fingerprint-v1\x00"


class TreeCacheError(ValueError):
    """A ``.rit`` file that cannot be written or read; the message names the file and problem."""


class SaveCancelled(Exception):
    """save_tree gave up because its ``cancel()`` turned true; nothing was written."""


class StaleTreeError(TreeCacheError):
    """The tree was baked from a different object geometry/material (fingerprint mismatch)."""


@dataclass
class _Entry:
    name: str
    dtype: np.dtype
    shape: tuple[int, ...]
    offset: int          # relative to the payload start
    nbytes: int          # of the array
    crc32: int           # of the array's bytes
    filters: tuple[str, ...]
    stored: int          # bytes in the payload (nbytes without filters)


@dataclass
class _Layout:
    header: dict
    entries: list[_Entry]
    data_offset: int     # absolute offset of the payload
    payload_bytes: int
    file_bytes: int


def _align(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


# --------------------------------------------------------------------------- writing
def _threads(n: int) -> int:
    return max(1, min(n, os.cpu_count() or 1))


def _encode_all(views: list[np.ndarray], chains: list[tuple[str, ...]], cancel,
                progress) -> list:
    """Each array's stored bytes: the filtered encoding where it is smaller, else the raw view
    (whose chain becomes empty). Every array's xz chunks share one pool of up to
    os.cpu_count() threads (at most filters.ENCODE_THREADS: memory), largest arrays first.
    ``cancel()`` true (polled between arrays and every POLL_S), or an interrupt, stops every
    encoder within one piece and raises SaveCancelled (or the interrupt). ``progress(fraction)``
    hears, every POLL_S, the share of the chunks' bytes encoded, and 1.0 at the end."""
    todo = sorted((i for i, c in enumerate(chains) if c), key=lambda i: -views[i].nbytes)
    out: list = [v.reshape(-1).view(np.uint8) for v in views]
    if not todo:
        if progress is not None:
            progress(1.0)
        return out
    stop = threading.Event()
    threads = min(F.ENCODE_THREADS, _threads(len(todo) + sum(v.nbytes for v in views) // F.CHUNK))
    with ThreadPoolExecutor(threads) as pool:
        try:
            pending, jobs = {}, {}           # jobs: each chunk's future -> its bytes
            for i in todo:
                if cancel is not None and cancel():
                    raise SaveCancelled("save cancelled")
                data = F.prefilter(views[i], chains[i])
                if "lzma" not in chains[i]:
                    pending[i] = data
                    continue
                pending[i] = []
                for c in F.chunks(data):
                    pending[i].append(pool.submit(F.compress, c, stop.is_set))
                    jobs[pending[i][-1]] = len(c)
            total = max(sum(jobs.values()), 1)
            while True:
                done, not_done = wait(jobs, timeout=POLL_S)
                if progress is not None:
                    progress(min(sum(jobs[f] for f in done) / total, 0.999))
                if not not_done:
                    break
                if cancel is not None and cancel():
                    raise SaveCancelled("save cancelled")
            for i in todo:
                p = pending[i]
                data = b"".join(f.result() for f in p) if isinstance(p, list) else p
                if len(data) < views[i].nbytes:
                    out[i] = np.frombuffer(data, np.uint8)
                else:
                    chains[i] = ()
        except BaseException:
            stop.set()                       # running encoders give up within one piece
            pool.shutdown(wait=True, cancel_futures=True)
            raise
    if progress is not None:
        progress(1.0)
    return out


def _prepare(path: str, header, arrays, filters, cancel,
             progress) -> tuple[bytes, list[np.ndarray]]:
    """Validate the inputs, encode the filtered arrays; return the header bytes (preamble ..
    padding) and the stored bytes of each array."""
    if not isinstance(header, dict):
        raise TreeCacheError(f"{path}: header must be a dict, got {type(header).__name__}")
    if not isinstance(arrays, dict):
        raise TreeCacheError(f"{path}: arrays must be a dict, got {type(arrays).__name__}")
    filters = {} if filters is None else filters
    if not isinstance(filters, dict):
        raise TreeCacheError(f"{path}: filters must be a dict, got {type(filters).__name__}")
    table, views, chains = [], [], []
    for name, arr in arrays.items():
        if not isinstance(name, str) or not name:
            raise TreeCacheError(f"{path}: array names must be non-empty str, got {name!r}")
        if not isinstance(arr, (np.ndarray, np.generic)):     # a numpy scalar saves as 0-d
            raise TreeCacheError(f"{path}: array {name!r} is {type(arr).__name__}, not numpy")
        dtype = arr.dtype.newbyteorder("<")
        if dtype.str not in DTYPES:
            raise TreeCacheError(f"{path}: array {name!r} has unsupported dtype {arr.dtype} "
                                 f"(supported: {sorted(DTYPES)})")
        try:
            chains.append(F.check_chain(filters.get(name, ()), dtype))
        except F.FilterError as exc:
            raise TreeCacheError(f"{path}: array {name!r}: {exc}") from None
        view = np.asarray(arr, dtype=dtype, order="C")
        table.append({"name": name, "dtype": dtype.str, "shape": list(arr.shape),
                      "nbytes": view.nbytes,
                      "crc32": zlib.crc32(view.reshape(-1).view(np.uint8))})
        views.append(view)
    try:
        json.dumps(header, allow_nan=False)                  # fail before the slow encoding
    except (TypeError, ValueError) as exc:
        raise TreeCacheError(f"{path}: header is not JSON-serializable: {exc}") from None
    unknown = sorted(set(filters) - set(arrays), key=str)
    if unknown:
        raise TreeCacheError(f"{path}: filters name arrays that are not saved: {unknown}")
    views = _encode_all(views, chains, cancel, progress)
    offset = 0
    for entry, view, chain in zip(table, views, chains):
        entry.update(offset=offset, filters=list(chain), stored=view.size)
        offset = _align(offset + view.size)
    payload = table[-1]["offset"] + table[-1]["stored"] if table else 0
    text = json.dumps({"header": header, "payload_bytes": payload, "arrays": table},
                      allow_nan=False, ensure_ascii=False, separators=(",", ":"))
    body = text.encode("utf-8")
    pre = _PREAMBLE.pack(MAGIC, BYTE_ORDER_MARK, FORMAT_VERSION, len(body), zlib.crc32(body))
    head = pre + body
    return head + bytes(_align(len(head)) - len(head)), views


def _write_payload(f: BinaryIO, sha, views: list[np.ndarray]) -> None:
    """Write the arrays (64-byte aligned, zero padded) in blocks, hashing what is written."""
    pos = 0
    for view in views:
        pad = bytes(_align(pos) - pos)
        f.write(pad)
        sha.update(pad)
        pos += len(pad)
        for i in range(0, view.size, BLOCK):
            block = memoryview(view[i:i + BLOCK])
            f.write(block)
            sha.update(block)
        pos += view.size


def save_tree(path: str | os.PathLike, header: dict, arrays: dict[str, np.ndarray],
              filters: dict[str, tuple[str, ...]] | None = None, cancel=None,
              progress=None) -> None:
    """Write ``header`` (JSON-serializable dict) and ``arrays`` to the ``.rit`` file ``path``.

    ``filters`` maps array names to filter chains (filters.py); an array whose encoding is not
    smaller than its bytes, or that is not named, is stored raw. Everything is validated and
    encoded before anything is written; ``cancel()`` turning true while the arrays are encoded
    (or Ctrl-C) stops within a few seconds (SaveCancelled), leaving ``path`` untouched;
    ``progress(fraction)`` follows the encoding (bytes of chunks done). The file
    is written by riray.atomic.atomic_write (a temporary file beside ``path``, fsynced and moved
    into place with os.replace): on any error or interrupt the temporary file is removed and an
    existing file at ``path`` is untouched; an OSError is raised as atomic.WriteError, naming
    ``path`` and the cause (disk full).
    """
    path = os.fspath(path)
    head, views = _prepare(path, header, arrays, filters, cancel, progress)

    def write(f: BinaryIO) -> None:
        sha = hashlib.sha256(head)
        f.write(head)
        _write_payload(f, sha, views)
        f.write(_TRAILER.pack(END_MARK, sha.digest()))

    atomic_write(path, write)


# --------------------------------------------------------------------------- reading
def _read_exact(f: BinaryIO, n: int) -> bytes | None:
    """Exactly n bytes, or None when the file ends first."""
    data = f.read(n)
    return data if len(data) == n else None


_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.S)


def _nesting(body: bytes) -> int:
    """Deepest bracket nesting of the JSON text ``body`` (its strings skipped), counted
    without parsing it."""
    b = np.frombuffer(_JSON_STRING.sub(b'""', body), np.uint8)
    step = np.isin(b, (ord("["), ord("{"))).astype(np.int64) - np.isin(b, (ord("]"), ord("}")))
    return int(np.cumsum(step).max(initial=0))


def _entries(path: str, table, payload: int) -> list[_Entry]:
    """Parse and check the array table: names, whitelisted dtypes, sizes, aligned disjoint spans."""
    def bad(msg: str) -> TreeCacheError:
        return TreeCacheError(f"{path}: inconsistent array table: {msg}")

    if not isinstance(table, list):
        raise bad("'arrays' is not a list")
    entries, names = [], set()
    for i, e in enumerate(table):
        keys = {"name", "dtype", "shape", "offset", "nbytes", "crc32", "filters", "stored"}
        if not isinstance(e, dict) or set(e) != keys:
            raise bad(f"entry {i} must have exactly the keys {sorted(keys)}")
        name, dt, shape = e["name"], e["dtype"], e["shape"]
        ints = [e["offset"], e["nbytes"], e["stored"], e["crc32"],
                *(shape if isinstance(shape, list) else [])]
        if not isinstance(name, str) or not name or name in names:
            raise bad(f"entry {i}: missing or duplicate name {name!r}")
        if not isinstance(dt, str) or dt not in DTYPES:
            raise bad(f"array {name!r}: dtype {dt!r} is not one of {sorted(DTYPES)}")
        if not isinstance(shape, list) or len(shape) > MAX_DIMS \
                or any(type(x) is not int or x < 0 for x in ints):
            raise bad(f"array {name!r}: shape/offset/nbytes/stored/crc32 must be non-negative "
                      f"integers, at most {MAX_DIMS} dimensions")
        dtype = np.dtype(dt)
        if e["nbytes"] != math.prod(shape) * dtype.itemsize:
            raise bad(f"array {name!r}: nbytes {e['nbytes']} != shape {shape} x {dtype.itemsize}")
        try:
            if not isinstance(e["filters"], list):
                raise F.FilterError("filters must be a list")
            chain = F.check_chain(e["filters"], dtype)
        except F.FilterError as exc:
            raise bad(f"array {name!r}: {exc}") from None
        if not chain and e["stored"] != e["nbytes"]:
            raise bad(f"array {name!r}: stored {e['stored']} != nbytes {e['nbytes']} without "
                      "filters")
        if chain and e["nbytes"] > max(MAX_RATIO * e["stored"], 1 << 20):
            raise bad(f"array {name!r}: nbytes {e['nbytes']} is more than {MAX_RATIO} times "
                      f"its stored {e['stored']}")
        if e["offset"] % ALIGN or e["offset"] + e["stored"] > payload or e["crc32"] >> 32:
            raise bad(f"array {name!r}: offset {e['offset']} + stored {e['stored']} is unaligned "
                      f"or outside the {payload}-byte payload, or crc32 out of range")
        names.add(name)
        entries.append(_Entry(name, dtype, tuple(shape), e["offset"], e["nbytes"], e["crc32"],
                              chain, e["stored"]))
    spans = sorted((e.offset, e.offset + e.stored, e.name) for e in entries if e.stored)
    for (_, end, a), (start, _, b) in zip(spans, spans[1:]):
        if start < end:
            raise bad(f"arrays {a!r} and {b!r} overlap")
    return entries


def _read_layout(path: str, f: BinaryIO) -> tuple[_Layout, bytes]:
    """Read and check preamble, header and table; return the layout and the bytes read."""
    size = os.fstat(f.fileno()).st_size
    ident = f.read(_IDENT.size)
    if not ident:
        raise TreeCacheError(f"{path}: not a riray tree (empty file)")
    if not (MAGIC.startswith(ident) or ident.startswith(MAGIC)):
        raise TreeCacheError(f"{path}: not a riray tree (wrong magic bytes {ident[:10]!r})")
    if len(ident) < _IDENT.size:
        raise TreeCacheError(f"{path}: truncated: {size} bytes, shorter than the preamble")
    _, mark, version = _IDENT.unpack(ident)
    if mark != BYTE_ORDER_MARK:
        raise TreeCacheError(f"{path}: corrupt: byte-order mark {mark!r}, expected "
                             f"{BYTE_ORDER_MARK!r} (little-endian)")
    if version != FORMAT_VERSION:
        raise TreeCacheError(f"{path}: format version {version} is not supported: this riray "
                             f"reads version {FORMAT_VERSION}; re-bake the tree")
    rest = _read_exact(f, _PREAMBLE.size - _IDENT.size)
    if rest is None:
        raise TreeCacheError(f"{path}: truncated: {size} bytes, shorter than the preamble")
    pre = ident + rest
    _, _, _, header_len, header_crc = _PREAMBLE.unpack(pre)
    if header_len > MAX_HEADER_BYTES:
        raise TreeCacheError(f"{path}: corrupt: header length {header_len} is implausible")
    body = _read_exact(f, header_len)
    if body is None:
        raise TreeCacheError(f"{path}: truncated: {size} bytes, the header alone needs "
                             f"{_PREAMBLE.size + header_len}")
    if zlib.crc32(body) != header_crc:
        raise TreeCacheError(f"{path}: corrupt: header checksum (crc32) mismatch")
    if _nesting(body) > MAX_HEADER_DEPTH:
        raise TreeCacheError(f"{path}: malformed header JSON: nested more than "
                             f"{MAX_HEADER_DEPTH} levels deep")
    try:
        doc = json.loads(body.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise TreeCacheError(f"{path}: malformed header JSON: {exc}") from None
    if (not isinstance(doc, dict) or set(doc) != {"header", "payload_bytes", "arrays"}
            or not isinstance(doc["header"], dict) or type(doc["payload_bytes"]) is not int
            or doc["payload_bytes"] < 0):
        raise TreeCacheError(f"{path}: malformed header JSON: expected an object with 'header' "
                             "(object), 'payload_bytes' (int >= 0) and 'arrays'")
    payload = doc["payload_bytes"]
    entries = _entries(path, doc["arrays"], payload)
    data_offset = _align(_PREAMBLE.size + header_len)
    expected = data_offset + payload + _TRAILER.size
    if size < expected:
        raise TreeCacheError(f"{path}: truncated: {size} bytes, the header says {expected}")
    if size > expected:
        raise TreeCacheError(f"{path}: corrupt: {size} bytes, the header says {expected} "
                             f"({size - expected} trailing bytes)")
    return _Layout(doc["header"], entries, data_offset, payload, size), pre + body


def _scan(path: str, f: BinaryIO, layout: _Layout, head: bytes,
          dest: dict[str, np.ndarray] | None, verify: bool) -> tuple[dict[str, bytearray], bool]:
    """Stream the file after ``head`` in BLOCK-sized reads: fill ``dest`` buffers (when given) and,
    with ``verify``, check every raw array's crc32, then read the trailer. Returns the stored
    bytes of the filtered arrays (whose crc32 is checked once decoded, so that a damaged one is
    named) and whether the whole-file sha256 matched (True without ``verify``)."""
    sha = hashlib.sha256(head) if verify else None
    scratch = memoryview(bytearray(BLOCK))
    pos = len(head)                                  # absolute file position
    stored: dict[str, bytearray] = {}

    def pump(n: int, out: memoryview | None) -> int:
        """Read the next n bytes (into ``out`` or the scratch block); their crc32 if verifying."""
        nonlocal pos
        crc = 0
        for i in range(0, n, BLOCK):
            buf = out[i:i + BLOCK] if out is not None else scratch[:min(BLOCK, n - i)]
            if f.readinto(buf) != len(buf):
                raise TreeCacheError(f"{path}: truncated: file ended while reading")
            if verify:
                sha.update(buf)
                crc = zlib.crc32(buf, crc)
        pos += n
        return crc

    for e in sorted(layout.entries, key=lambda e: e.offset):
        pump(max(layout.data_offset + e.offset - pos, 0), None)   # < 0: an empty array
        if e.filters:
            stored[e.name] = bytearray(e.stored)
            pump(e.stored, memoryview(stored[e.name]))
            continue
        out = None
        if dest is not None:
            out = memoryview(dest[e.name].reshape(-1).view(np.uint8))
        if pump(e.nbytes, out) != e.crc32 and verify:
            raise TreeCacheError(f"{path}: corrupt: array {e.name!r} checksum (crc32) mismatch")
    if not verify:
        return stored, True
    pump(layout.data_offset + layout.payload_bytes - pos, None)
    mark, digest = _TRAILER.unpack(f.read(_TRAILER.size))
    return stored, mark == END_MARK and digest == sha.digest()


def _decode_all(path: str, layout: _Layout, stored: dict, verify: bool) -> dict[str, np.ndarray]:
    """The filtered arrays decoded, on up to os.cpu_count() threads; their crc32 checked with
    ``verify``."""
    entries = sorted((e for e in layout.entries if e.filters), key=lambda e: -e.nbytes)

    def one(e: _Entry) -> np.ndarray:
        try:
            arr = F.decode(stored[e.name], e.filters, e.dtype, e.shape)
        except F.FilterError as exc:
            raise TreeCacheError(f"{path}: corrupt: array {e.name!r} does not decode "
                                 f"({exc})") from None
        except MemoryError:
            raise TreeCacheError(f"{path}: array {e.name!r} ({e.nbytes} bytes) does not fit in "
                                 "memory") from None
        if verify and zlib.crc32(arr.reshape(-1).view(np.uint8)) != e.crc32:
            raise TreeCacheError(f"{path}: corrupt: array {e.name!r} checksum (crc32) mismatch")
        return arr

    if not entries:
        return {}
    with ThreadPoolExecutor(_threads(len(entries))) as pool:
        return dict(zip((e.name for e in entries), pool.map(one, entries)))


def load_tree(path: str | os.PathLike, *, verify: bool = True,
              expect_fingerprint: str | None = None,
              check=None) -> tuple[dict, dict[str, np.ndarray]]:
    """Read a ``.rit`` file: (header, arrays) in the order they were saved, as writeable
    in-memory arrays (the file is read, never memory-mapped: one truncated under a reader
    is an error, not a SIGBUS).

    verify=True checks each array's crc32 and the whole-file sha256 as the file streams past
    (memory: the arrays plus BLOCK plus the filtered arrays' stored bytes). With
    expect_fingerprint, a tree whose header["fingerprint"] differs raises StaleTreeError.
    ``check(header, table, file_bytes)``, with table {name: (dtype, shape)}, runs after the
    structure is read and before any array is: a ValueError from it refuses the file. Every
    problem raises TreeCacheError naming the file.
    """
    path = os.fspath(path)
    with open_regular(path) as f:
        layout, head = _read_layout(path, f)
        have = layout.header.get("fingerprint")
        if expect_fingerprint is not None and have != expect_fingerprint:
            raise StaleTreeError(
                f"{path}: stale tree: the object's geometry or material changed since the bake "
                f"(tree fingerprint {str(have)[:80]!r}, scene {expect_fingerprint!r}); re-bake "
                "the RI-Tree")
        if check is not None:
            try:
                check(layout.header, {e.name: (e.dtype, e.shape) for e in layout.entries},
                      layout.file_bytes)
            except ValueError as exc:
                raise TreeCacheError(f"{path}: {exc}") from None
        arrays = {e.name: np.empty(e.shape, e.dtype) for e in layout.entries if not e.filters}
        stored, sha_ok = _scan(path, f, layout, head, arrays, verify)
    arrays.update(_decode_all(path, layout, stored, verify))
    if not sha_ok:
        raise TreeCacheError(f"{path}: corrupt: whole-file sha256 mismatch (trailer, header "
                             "padding or padding between arrays)")
    return layout.header, {e.name: arrays[e.name] for e in layout.entries}


def describe(path: str | os.PathLike) -> dict:
    """Summary for ``riray info``, reading only the preamble and header (no payload)."""
    path = os.fspath(path)
    with open_regular(path) as f:
        layout, _ = _read_layout(path, f)
    return {"path": path, "format_version": FORMAT_VERSION, "file_bytes": layout.file_bytes,
            "payload_bytes": layout.payload_bytes, "header": layout.header,
            "arrays": [{"name": e.name, "dtype": e.dtype.name, "shape": list(e.shape),
                        "nbytes": e.nbytes, "stored": e.stored, "filters": list(e.filters)}
                       for e in layout.entries]}


# --------------------------------------------------------------------------- fingerprint
def _feed(h, tag: bytes, data: bytes) -> None:
    """Append one length-prefixed, tagged field (the encoding is injective)."""
    h.update(tag + struct.pack("<Q", len(data)) + data)


def _feed_array(h, tag: bytes, arr, dtype: str) -> None:
    a = np.asarray(arr, dtype=dtype, order="C")
    _feed(h, tag, struct.pack(f"<{a.ndim}q", *a.shape) + a.tobytes())


def fingerprint(obj: SpecularObject, max_events: int) -> str:
    """sha256 hex of everything of the specular object that a bake depends on.

    Covers max_events, every ObjectMaterial field (numbers as float64, strings as UTF-8) and, per
    patch in order, its class_id and either the NURBS degrees, knots, points and weights (float64)
    or the mesh vertices (float64), triangles (int64) and corner normals where it has them
    (float64), with their shapes. Names are excluded.
    """
    h = hashlib.sha256(FINGERPRINT_TAG)
    _feed(h, b"E", struct.pack("<q", int(max_events)))
    for field in fields(obj.material):
        value = getattr(obj.material, field.name)
        _feed(h, b"K", field.name.encode())
        if isinstance(value, str):
            _feed(h, b"S", value.encode("utf-8"))
        else:
            _feed_array(h, b"F", value, "<f8")
    _feed(h, b"N", struct.pack("<q", len(obj.patches)))
    for patch in obj.patches:
        _feed(h, b"C", struct.pack("<q", int(patch.class_id)))
        surf = patch.surface
        if surf is None:
            _feed_array(h, b"V", patch.vertices, "<f8")
            _feed_array(h, b"T", patch.triangles, "<i8")
            if patch.normals is not None:
                _feed_array(h, b"M", patch.normals, "<f8")
        else:
            _feed(h, b"D", struct.pack("<qq", surf.degree_u, surf.degree_v))
            _feed_array(h, b"U", surf.knots_u, "<f8")
            _feed_array(h, b"W", surf.knots_v, "<f8")
            _feed_array(h, b"P", surf.points, "<f8")
            _feed_array(h, b"R", surf.weights, "<f8")
    return h.hexdigest()
