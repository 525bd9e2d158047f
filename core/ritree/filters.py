"""Lossless array filters of the ``.rit`` file (format version 2, docs/tree-format.md).

A stored array may pass through a chain of filters, always in this order:
  delta    integer arrays only: the array as C-order rows (shape[0] rows, the rest flattened
           into columns), each column made contiguous and replaced by its first value and the
           differences of consecutive values, modulo 2^bits (wrap-around, exact)
  shuffle  byte planes: the first byte of every element, then every second byte, ...
  lzma     xz streams (LZMA2, no integrity check of their own: the table's crc32 covers the
           decoded array, the trailer's sha256 the file), one per ``CHUNK`` bytes of the
           filtered array, concatenated (as a concatenated .xz file is), so that one array's
           chunks compress on several threads; each stream's header names its dictionary;
           every stream but the last decodes to at least ``MIN_STREAM`` bytes
A chain is any subsequence of ``ORDER``; the empty chain stores the raw bytes. Decoding undoes
the chain in reverse order.
"""

from __future__ import annotations

import lzma
import math

import numpy as np

ORDER = ("delta", "shuffle", "lzma")
LZMA_PRESET = 6          # xz's default match finder and effort; its dictionary is set below
DICT_MAX = 64 << 20      # bytes: the longest repeats of a full tree's codes (the viewpoints of
                         # a symmetric object's faces) lie tens of MiB apart: on glass_sphere's
                         # 5/6 full tree a 32-128 MiB dictionary stores the hit points in 0.56
                         # bytes a sample, xz's default 8 MiB in 1.33 (and preset 1's 1 MiB
                         # made the whole 4/5 full tree 1.8x larger than the default's)
CHUNK = 256 << 20        # bytes of filtered data per xz stream (one thread each): long enough
                         # for the dictionary, short enough to spread a big array over cores
MIN_STREAM = 1 << 20     # bytes every stream but the last must decode to (the format's rule:
                         # it bounds the number of streams a reader walks)
ENCODE_THREADS = 4       # at most: each encoder takes about 11 dictionaries of memory (0.7 GB)
PIECE = 1 << 20          # bytes fed to an encoder between two looks at its stop flag (up to
                         # a few seconds: liblzma buffers its input and works unevenly)
FEED = 16 << 20          # bytes of input and of output per decoder call
MEMLIMIT = 1 << 30       # bytes of decoder memory a stream may ask for (64 MiB dictionaries
                         # need about 65 MiB; a crafted header could ask for 1.5 GiB)


class FilterError(ValueError):
    """A filter chain that is not allowed for the array, or stored bytes that do not decode."""


class Stopped(Exception):
    """An encoding given up because its ``stop`` callable turned true."""


def check_chain(chain, dtype: np.dtype) -> tuple[str, ...]:
    """``chain`` as a tuple; FilterError unless it is a subsequence of ORDER fit for dtype."""
    chain = tuple(chain)
    if any(not isinstance(f, str) or f not in ORDER for f in chain) \
            or list(chain) != sorted(chain, key=ORDER.index) or len(set(chain)) != len(chain):
        raise FilterError(f"filters {list(chain)} are not a subsequence of {list(ORDER)}")
    if "delta" in chain and dtype.kind not in "iu":
        raise FilterError(f"filter 'delta' needs an integer dtype, not {dtype}")
    return chain


def _columns(shape: tuple[int, ...]) -> tuple[int, int]:
    """(rows, columns) of the delta filter's view."""
    if len(shape) == 0:
        return 1, 1
    rows = shape[0]
    return rows, (math.prod(shape[1:]) if rows else 0)


def _unsigned(dtype: np.dtype) -> np.dtype:
    return np.dtype(f"<u{dtype.itemsize}")


def compress(data, stop=None) -> bytes:
    """One xz stream of ``data`` (bytes-like: one chunk), with a dictionary no longer than the
    data (a longer one costs memory and time and finds nothing more). Fed ``PIECE`` bytes at a
    time: Stopped as soon as ``stop()`` (if given) is true between two pieces."""
    enc = lzma.LZMACompressor(format=lzma.FORMAT_XZ, check=lzma.CHECK_NONE,
                              filters=[{"id": lzma.FILTER_LZMA2, "preset": LZMA_PRESET,
                                        "dict_size": min(DICT_MAX, max(len(data), 4096))}])
    view, out = memoryview(data), []
    for i in range(0, len(view), PIECE):
        if stop is not None and stop():
            raise Stopped()
        out.append(enc.compress(view[i:i + PIECE]))
    out.append(enc.flush())
    return b"".join(out)


def chunks(data) -> list:
    """``data`` (bytes-like) cut into the chunks that ``lzma`` compresses one by one (every one
    but the last at least MIN_STREAM bytes)."""
    view = memoryview(data)
    return [view[i:i + CHUNK] for i in range(0, len(view), CHUNK)] or [view]


def encode(arr: np.ndarray, chain) -> bytes:
    """The stored bytes of C-order little-endian ``arr`` under ``chain``, on this thread (the
    cache's writer runs ``prefilter`` and each chunk's ``compress`` on a pool instead)."""
    data = prefilter(arr, chain)
    if "lzma" in chain:
        data = b"".join(compress(c) for c in chunks(data))
    return data


def prefilter(arr: np.ndarray, chain) -> bytes:
    """``arr``'s bytes after the chain's delta and shuffle filters (before lzma)."""
    chain = check_chain(chain, arr.dtype)
    a = np.ascontiguousarray(arr)
    if "delta" in chain:
        rows, cols = _columns(a.shape)
        cm = a.view(_unsigned(a.dtype)).reshape(rows, cols).T.copy()   # never the caller's
        cm[:, 1:] = np.diff(cm, axis=1)                       # unsigned: wraps modulo 2^bits
        a = cm
    if "shuffle" in chain:
        a = np.ascontiguousarray(a.reshape(-1).view(np.uint8).reshape(-1, arr.dtype.itemsize).T)
    return a.tobytes()


def decode(data, chain, dtype: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    """The array that ``encode`` stored as ``data`` (bytes-like); FilterError when it cannot be
    (a damaged stream, or one that decodes to the wrong number of bytes). Peak memory is about
    twice the array (plus ``FEED`` bytes)."""
    chain = check_chain(chain, dtype)
    size = math.prod(shape) * dtype.itemsize
    if "lzma" in chain:
        buf = _decompress(data, size)
    else:
        buf = np.frombuffer(data, np.uint8)
        if len(buf) != size:
            raise FilterError(f"{len(buf)} stored bytes, the table says {size}")
        buf = buf.copy()                                      # writeable, owned
    if "shuffle" in chain:
        buf = np.ascontiguousarray(buf.reshape(dtype.itemsize, -1).T)   # the planes freed
    out = buf.reshape(-1).view(dtype if "delta" not in chain else _unsigned(dtype))
    del buf
    if "delta" in chain:
        rows, cols = _columns(shape)
        cm = out.reshape(cols, rows)
        np.cumsum(cm, axis=1, dtype=cm.dtype, out=cm)            # in place; wraps as it goes
        out = (np.ascontiguousarray(cm.T) if cols > 1 else cm.reshape(-1)).view(dtype)
    out = out.reshape(shape)
    return out if out.flags.writeable and out.flags.c_contiguous else out.copy()


def _decompress(data, size: int) -> np.ndarray:
    """The ``size`` bytes (uint8) that the concatenated xz streams ``data`` decode to, written
    into one buffer; FilterError if they decode to more (stopped at size + 1), to fewer, or not
    at all, or if a stream before the last decodes to fewer than MIN_STREAM bytes. A stream may
    not ask for more than MEMLIMIT of decoder memory."""
    out = np.empty(size, np.uint8)
    view, pos, n = memoryview(data).cast("B"), 0, 0
    while True:
        start = n
        dec = lzma.LZMADecompressor(format=lzma.FORMAT_XZ, memlimit=MEMLIMIT)
        piece = b""
        try:
            while not dec.eof:
                if dec.needs_input:
                    if pos >= len(view):
                        raise FilterError("lzma stream does not decode (it ends early)")
                    piece = view[pos:pos + FEED]
                    pos += len(piece)
                else:
                    piece = b""
                got = dec.decompress(piece, max_length=min(FEED, size + 1 - n))
                if n + len(got) > size:
                    raise FilterError(f"lzma streams decode to more than {size} bytes, the "
                                      "table's size")
                out[n:n + len(got)] = np.frombuffer(got, np.uint8)
                n += len(got)
        except lzma.LZMAError as exc:
            raise FilterError(f"lzma stream does not decode ({exc})") from None
        pos -= len(dec.unused_data)
        if pos >= len(view):
            break
        if n - start < MIN_STREAM:
            raise FilterError(f"an lzma stream before the last decodes to {n - start} bytes, "
                              f"fewer than {MIN_STREAM}")
    if n != size:
        raise FilterError(f"lzma streams decode to {n} bytes, the table says {size}")
    return out
