"""Image files: 8-bit sRGB PNG (stdlib zlib/struct only) and float images (.npy).

Conventions: arrays are row-major, top row first, shape (H, W, 3); float images hold linear RGB.
PNG files are assumed to be sRGB-encoded (gAMA/iCCP/sRGB chunks are ignored); alpha is dropped.
Every write goes through riray.atomic.atomic_write (temporary file beside the target, fsync,
os.replace; an OSError names the file and its cause).
"""

from __future__ import annotations

import os
import struct
import zlib
from typing import BinaryIO

import numpy as np

from .files import atomic_write, open_regular, read_regular

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# colour type -> samples per pixel; allowed bit depths
_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
# Largest image read (and rendered), pixels on a side: bounds decoded memory; checked from the
# PNG's IHDR or the .npy header before any pixel is decoded.
MAX_IMAGE_SIDE = 16384
# Largest image file read, bytes: a 16384 x 16384 float32 RGB .npy (3.2 GB) fits.
MAX_IMAGE_BYTES = 1 << 32


class ImageError(ValueError):
    """An image file that cannot be read or an array that cannot be written; names the file."""


# --------------------------------------------------------------------------- helpers
def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) for linear values in [0, 1]."""
    x = np.asarray(x, dtype=np.float64)
    curve = 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055
    return np.where(x <= 0.0031308, 12.92 * x, curve)


def srgb_to_linear(s: np.ndarray) -> np.ndarray:
    """Inverse of :func:`linear_to_srgb` for encoded values in [0, 1]."""
    s = np.asarray(s, dtype=np.float64)
    curve = np.power((np.maximum(s, 0.04045) + 0.055) / 1.055, 2.4)
    return np.where(s <= 0.04045, s / 12.92, curve)


def linear_to_u8(rgb: np.ndarray) -> np.ndarray:
    """Linear float -> 8-bit sRGB: NaN -> 0, clamp to [0, 1], sRGB transfer, round half up."""
    x = np.nan_to_num(np.asarray(rgb, dtype=np.float64), nan=0.0, posinf=1.0, neginf=0.0)
    return np.floor(linear_to_srgb(np.clip(x, 0.0, 1.0)) * 255.0 + 0.5).astype(np.uint8)


# --------------------------------------------------------------------------- PNG writing
def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _paeth(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    p = a + b - c
    pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
    return np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))


def _filter_rows(raw: np.ndarray, bpp: int) -> bytes:
    """Filter each scanline with the type (0-4) of least sum |signed residual| (libpng's)."""
    x = raw.astype(np.int16)
    a = np.zeros_like(x)
    a[:, bpp:] = x[:, :-bpp]
    b = np.zeros_like(x)
    b[1:] = x[:-1]
    c = np.zeros_like(x)
    c[1:, bpp:] = x[:-1, :-bpp]
    cand = np.stack([x, x - a, x - b, x - (a + b) // 2, x - _paeth(a, b, c)])
    cand = (cand & 0xFF).astype(np.uint8)
    score = np.abs(cand.view(np.int8).astype(np.int32)).sum(axis=2)   # (5, H)
    best = score.argmin(axis=0)
    rows = cand[best, np.arange(raw.shape[0])]
    return np.concatenate([best[:, None].astype(np.uint8), rows], axis=1).tobytes()


def encode_png(img: np.ndarray) -> bytes:
    """PNG bytes for a uint8 image (H, W) grey or (H, W, 3) RGB, bit depth 8, non-interlaced."""
    img = np.asarray(img)
    if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
        raise ImageError(f"PNG needs a uint8 (H, W) or (H, W, 3) array "
                         f"(got {img.dtype} {img.shape})")
    h, w = img.shape[:2]
    if h < 1 or w < 1:
        raise ImageError(f"PNG needs at least one pixel (got shape {img.shape})")
    bpp = 1 if img.ndim == 2 else 3
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0 if bpp == 1 else 2, 0, 0, 0)
    idat = zlib.compress(_filter_rows(img.reshape(h, w * bpp), bpp), 6)
    return _PNG_SIGNATURE + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")


def write_png_u8(path: str | os.PathLike, img: np.ndarray) -> None:
    """Write a uint8 (H, W, 3) RGB or (H, W) grey image (e.g. a mask) as is, atomically."""
    data = encode_png(img)
    atomic_write(path, lambda f: f.write(data))


def write_png(path: str | os.PathLike, rgb_linear: np.ndarray) -> None:
    """Write linear RGB (H, W, 3) float as an 8-bit sRGB PNG (NaN -> 0, clamped to [0, 1])."""
    rgb = np.asarray(rgb_linear)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ImageError(f"{os.fspath(path)}: expected an (H, W, 3) image (got shape {rgb.shape})")
    write_png_u8(path, linear_to_u8(rgb))


# --------------------------------------------------------------------------- PNG reading
def _unfilter(data: bytes, h: int, rowbytes: int, bpp: int) -> np.ndarray:
    """Undo the scanline filters of ``data`` (h * (1 + rowbytes) bytes) -> (h, rowbytes) uint8."""
    out = np.zeros((h, rowbytes), dtype=np.uint8)
    prev = np.zeros(rowbytes, dtype=np.uint8)
    stride = 1 + rowbytes
    for y in range(h):  # rows depend on the previous decoded row; they are not rays
        ftype = data[y * stride]
        cur = np.frombuffer(data, dtype=np.uint8, count=rowbytes, offset=y * stride + 1)
        if ftype == 0:
            row = cur.copy()
        elif ftype == 1:
            row = np.cumsum(cur.reshape(-1, bpp), axis=0, dtype=np.uint8).reshape(-1)
        elif ftype == 2:
            row = cur + prev
        elif ftype in (3, 4):
            row = bytearray(cur.tobytes())
            up = prev.tobytes()
            for x in range(rowbytes):  # sequential: each byte predicts from its decoded left
                a = row[x - bpp] if x >= bpp else 0
                b = up[x]
                if ftype == 3:
                    pred = (a + b) >> 1
                else:
                    c = up[x - bpp] if x >= bpp else 0
                    p = a + b - c
                    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                    pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
                row[x] = (row[x] + pred) & 0xFF
            row = np.frombuffer(bytes(row), dtype=np.uint8)
        else:
            raise ImageError(f"scanline {y} has unknown filter type {ftype}")
        out[y] = row
        prev = out[y]
    return out


def decode_png(data: bytes) -> tuple[np.ndarray, int]:
    """Decode PNG bytes to (samples, maxcode): samples uint8 or uint16 (H, W, C), C = 1 grey,
    2 grey+alpha, 3 RGB (palette images are expanded), 4 RGBA; maxcode = 2**depth - 1 (255 for
    palette images). Raises ImageError for anything malformed."""
    if data[:8] != _PNG_SIGNATURE:
        raise ImageError("not a PNG file (bad signature)")
    pos, ihdr, palette, idat, ended = 8, None, None, [], False
    while pos < len(data):
        if pos + 8 > len(data):
            raise ImageError("truncated chunk header")
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        kind = data[pos + 4:pos + 8]
        body = data[pos + 8:pos + 8 + length]
        if len(body) != length or pos + 12 + length > len(data):
            raise ImageError(f"truncated {kind!r} chunk")
        (crc,) = struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])
        if zlib.crc32(kind + body) != crc:
            raise ImageError(f"CRC mismatch in {kind!r} chunk (corrupt file)")
        pos += 12 + length
        if kind == b"IHDR":
            if length != 13:
                raise ImageError("IHDR chunk has the wrong length")
            ihdr = struct.unpack(">IIBBBBB", body)
        elif kind == b"PLTE":
            if length % 3 or length == 0:
                raise ImageError("PLTE chunk length is not a positive multiple of 3")
            palette = np.frombuffer(body, dtype=np.uint8).reshape(-1, 3)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            ended = True
            break
        elif not kind[0] & 0x20:  # upper-case first letter: a critical chunk we do not know
            raise ImageError(f"unsupported critical chunk {kind!r}")
    if ihdr is None:
        raise ImageError("missing IHDR chunk")
    if not ended:
        raise ImageError("truncated file (no IEND chunk)")
    w, h, depth, ctype, comp, filt, interlace = ihdr
    if ctype not in _CHANNELS or depth not in _DEPTHS[ctype]:
        raise ImageError(f"invalid colour type {ctype} / bit depth {depth}")
    if w == 0 or h == 0 or comp != 0 or filt != 0:
        raise ImageError("invalid IHDR (zero size or unknown compression/filter method)")
    if max(w, h) > MAX_IMAGE_SIDE:
        raise ImageError(f"{w} x {h} pixels: larger than {MAX_IMAGE_SIDE} on a side")
    if interlace:
        raise ImageError("interlaced (Adam7) PNG is not supported; re-save it without interlacing")
    if ctype == 3 and palette is None:
        raise ImageError("palette image without a PLTE chunk")
    if not idat:
        raise ImageError("missing IDAT chunk")
    nchan = _CHANNELS[ctype]
    bits = depth * nchan
    rowbytes, bpp = (w * bits + 7) // 8, max(1, bits // 8)
    need = h * (1 + rowbytes)
    dec = zlib.decompressobj()
    try:   # inflate no further than the IHDR's size (+1 byte: surplus data is ignored)
        raw = dec.decompress(b"".join(idat), need + 1)
    except zlib.error as e:
        raise ImageError(f"corrupt compressed image data ({e})") from None
    if len(raw) < need or (len(raw) == need and not dec.eof):
        raise ImageError("truncated image data")
    rows = _unfilter(raw, h, rowbytes, bpp)
    if depth == 16:
        samples = rows.view(">u2").astype(np.uint16).reshape(h, w, nchan)
    elif depth == 8:
        samples = rows.reshape(h, w, nchan)
    else:
        vals = np.unpackbits(rows, axis=1).reshape(h, -1, depth)
        weights = (1 << np.arange(depth - 1, -1, -1)).astype(np.uint8)
        samples = (vals * weights).sum(axis=2, dtype=np.uint8)[:, :w, None]
    if ctype == 3:
        idx = samples[:, :, 0]
        if idx.max() >= len(palette):
            raise ImageError("palette index out of range")
        return palette[idx], 255
    return samples, (1 << depth) - 1


def read_png_samples(path: str | os.PathLike) -> tuple[np.ndarray, int]:
    """(samples, maxcode) of a PNG file (see :func:`decode_png`) of at most MAX_IMAGE_BYTES."""
    try:
        data = read_regular(path, MAX_IMAGE_BYTES)
    except ValueError as e:
        raise ImageError(str(e)) from None
    try:
        return decode_png(data)
    except ImageError as e:
        raise ImageError(f"{os.fspath(path)}: {e}") from None


def read_png(path: str | os.PathLike) -> np.ndarray:
    """Read a PNG (grey, grey+alpha, RGB, RGBA, palette; 1-16 bit) as linear RGB float64 (H, W, 3).

    Samples are taken as sRGB-encoded and decoded with :func:`srgb_to_linear`; alpha is dropped.
    """
    s, maxcode = read_png_samples(path)
    rgb = s[:, :, :3] if s.shape[2] >= 3 else np.repeat(s[:, :, :1], 3, axis=2)
    return srgb_to_linear(rgb.astype(np.float64) / maxcode)


# --------------------------------------------------------------------------- float images
def write_float_image(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """Write a float image (H, W, 3) or (H, W) as a float32 .npy file, atomically."""
    arr = np.asarray(rgb)
    if not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] == 3)) or arr.dtype.kind not in "fiu":
        raise ImageError(f"{os.fspath(path)}: expected a numeric (H, W, 3) or (H, W) array "
                         f"(got {arr.dtype} {arr.shape})")
    atomic_write(path, lambda f: np.save(f, arr.astype(np.float32), allow_pickle=False))


def npy_header(f: BinaryIO, path: str) -> tuple[tuple, np.dtype, int]:
    """(shape, dtype, bytes of data after the header) of the .npy file ``f`` (at its start),
    read from its header alone; ImageError (a ValueError) naming ``path`` unless it is one."""
    if f.read(4) == b"PK\x03\x04":
        raise ImageError(f"{path}: expected a .npy file holding one array (got an .npz "
                         "archive)")
    f.seek(0)
    fmt = np.lib.format
    try:
        version = fmt.read_magic(f)
        read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, _, dtype = read(f)
    except (ValueError, EOFError) as e:
        raise ImageError(f"{path}: not a readable .npy array ({e})") from None
    return shape, dtype, os.fstat(f.fileno()).st_size - f.tell()


def _image_npy_header(f: BinaryIO, path: str) -> tuple[tuple, np.dtype]:
    """(shape, dtype) of the .npy file ``f``, read from its header alone; ImageError unless it
    is a numeric (H, W[, 1|3|4]) image of 1..MAX_IMAGE_SIDE pixels a side whose data ``f``
    holds."""
    shape, dtype, held = npy_header(f, path)
    if dtype.kind not in "fiu" or not (len(shape) == 2 or (len(shape) == 3
                                                           and shape[2] in (1, 3, 4))):
        raise ImageError(f"{path}: expected a numeric (H, W[, 1|3|4]) array "
                         f"(got {dtype} {shape})")
    if not 1 <= min(shape[:2]) <= max(shape[:2]) <= MAX_IMAGE_SIDE:
        raise ImageError(f"{path}: {shape[0]} x {shape[1]} pixels: an image needs 1.."
                         f"{MAX_IMAGE_SIDE} on a side")
    if held < int(np.prod(shape)) * dtype.itemsize:
        raise ImageError(f"{path}: truncated: the header says {shape} {dtype}, the file holds "
                         f"{held} bytes of data")
    return shape, dtype


def read_float_image(path: str | os.PathLike) -> np.ndarray:
    """Read a .npy image as float64 (H, W, 3): (H, W) grey is replicated, a 4th channel dropped.
    The header is checked (:func:`_image_npy_header`) before any pixel is read."""
    try:
        f = open_regular(path, MAX_IMAGE_BYTES)
    except ValueError as e:
        raise ImageError(str(e)) from None
    with f:
        _image_npy_header(f, os.fspath(path))
        f.seek(0)
        try:
            arr = np.lib.format.read_array(f, allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            raise ImageError(f"{os.fspath(path)}: not a readable .npy array ({e})") from None
    arr = arr.astype(np.float64)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    return np.ascontiguousarray(np.repeat(arr, 3, axis=2) if arr.shape[2] == 1 else arr[:, :, :3])
