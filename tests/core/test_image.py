"""PNG / float image I/O: exact 8-bit round trips, the sRGB formula, every filter type decoded from
PNGs built here by hand (independently of the module's encoder), and clear errors."""

import struct
import zlib

import numpy as np
import pytest

from riray.imageio import (ImageError, decode_png, encode_png, linear_to_srgb,
                                linear_to_u8, read_float_image, read_png, read_png_samples,
                                srgb_to_linear, write_float_image, write_png, write_png_u8)

RNG = np.random.default_rng(7)


def chunk(kind, data):
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def paeth(a, b, c):
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    return a if pa <= pb and pa <= pc else (b if pb <= pc else c)


def hand_png(rows, width, ctype, depth, filters, palette=None, interlace=0):
    """PNG bytes from raw scanline bytes, filtering row y with filters[y] by the spec, scalar."""
    nchan = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}[ctype]
    bpp = max(1, depth * nchan // 8)
    out, prev = bytearray(), bytes(len(rows[0]))
    for y, row in enumerate(rows):
        f = filters[y % len(filters)]
        out.append(f)
        for x in range(len(row)):
            a = row[x - bpp] if x >= bpp else 0
            b = prev[x]
            c = prev[x - bpp] if x >= bpp else 0
            pred = [0, a, b, (a + b) // 2, paeth(a, b, c)][f]
            out.append((row[x] - pred) % 256)
        prev = row
    ihdr = struct.pack(">IIBBBBB", width, len(rows), depth, ctype, 0, 0, interlace)
    body = chunk(b"IHDR", ihdr) + (chunk(b"PLTE", palette) if palette else b"")
    return (b"\x89PNG\r\n\x1a\n" + body + chunk(b"tEXt", b"k\x00v")
            + chunk(b"IDAT", zlib.compress(bytes(out))) + chunk(b"IEND", b""))


@pytest.mark.parametrize("ftype", [0, 1, 2, 3, 4])
def test_each_filter_type_rgb8(ftype):
    img = RNG.integers(0, 256, (5, 4, 3), dtype=np.uint8)
    data = hand_png([bytes(r) for r in img.reshape(5, 12)], 4, 2, 8, [ftype])
    s, maxcode = decode_png(data)
    assert maxcode == 255
    np.testing.assert_array_equal(s, img)


def test_mixed_filters_rgba16_grey_alpha_and_palette():
    img = RNG.integers(0, 65536, (4, 3, 4), dtype=np.uint16)
    rows = [img[y].astype(">u2").tobytes() for y in range(4)]
    s, maxcode = decode_png(hand_png(rows, 3, 6, 16, [4, 3, 1, 2]))
    assert s.dtype == np.uint16 and maxcode == 65535
    np.testing.assert_array_equal(s, img)
    ga = RNG.integers(0, 256, (3, 5, 2), dtype=np.uint8)
    s, _ = decode_png(hand_png([bytes(r) for r in ga.reshape(3, 10)], 5, 4, 8, [3, 4, 1]))
    np.testing.assert_array_equal(s, ga)
    pal = bytes([0, 0, 0, 255, 0, 0, 0, 255, 0, 10, 20, 30])
    # 2-bit palette indices, 5 pixels per row -> 2 bytes per row (last padded)
    idx = [[0, 1, 2, 3, 1], [3, 3, 0, 2, 1]]
    rows = [bytes([(r[0] << 6) | (r[1] << 4) | (r[2] << 2) | r[3], r[4] << 6]) for r in idx]
    s, maxcode = decode_png(hand_png(rows, 5, 3, 2, [0, 4], palette=pal))
    np.testing.assert_array_equal(s, np.frombuffer(pal, np.uint8).reshape(4, 3)[np.array(idx)])
    assert maxcode == 255


def test_low_bit_grey_scales_to_full_range(tmp_path):
    p = tmp_path / "g.png"
    p.write_bytes(hand_png([bytes([0b00011011])], 4, 0, 2, [1]))     # 2-bit codes 0,1,2,3
    rgb = read_png(p)
    assert rgb.shape == (1, 4, 3)
    np.testing.assert_allclose(rgb[0, :, 1], srgb_to_linear(np.array([0, 1, 2, 3]) / 3))


def test_u8_round_trip_and_linear_write(tmp_path):
    img = RNG.integers(0, 256, (7, 9, 3), dtype=np.uint8)
    p = tmp_path / "a.png"
    write_png_u8(p, img)
    np.testing.assert_array_equal(read_png_samples(p)[0], img)
    np.testing.assert_array_equal(linear_to_u8(read_png(p)), img)     # float read is exact too
    mask = (RNG.random((6, 5)) > 0.5).astype(np.uint8) * 255
    write_png_u8(p, mask)
    np.testing.assert_array_equal(read_png_samples(p)[0][:, :, 0], mask)
    lin = np.array([[[0.0, 0.5, 1.0], [np.nan, -3.0, 7.0]]])
    write_png(p, lin)
    got = read_png_samples(p)[0]
    want = [[[0, round(255 * (1.055 * 0.5 ** (1 / 2.4) - 0.055)), 255], [0, 0, 255]]]
    np.testing.assert_array_equal(got, want)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.png"]


def test_srgb_transfer_matches_formula():
    x = np.array([0.0, 0.001, 0.0031308, 0.01, 0.18, 0.5, 1.0])
    want = [12.92 * v if v <= 0.0031308 else 1.055 * v ** (1 / 2.4) - 0.055 for v in x]
    np.testing.assert_allclose(linear_to_srgb(x), want, rtol=0, atol=1e-15)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, rtol=1e-12, atol=1e-15)
    assert abs(linear_to_srgb(0.18) - 0.4613561295) < 1e-9


def test_encoder_output_is_valid_for_smooth_and_noisy_images():
    ramp = np.tile(np.arange(0, 250, 10, dtype=np.uint8)[None, :, None], (6, 1, 3))
    for img in (ramp, RNG.integers(0, 256, (6, 25, 3), dtype=np.uint8)):
        np.testing.assert_array_equal(decode_png(encode_png(img))[0], img)


@pytest.mark.parametrize("mangle,pattern", [
    (lambda d: d[:20], "truncated"),
    (lambda d: d[:-12], "no IEND"),
    (lambda d: b"GIF89a" + d[6:], "not a PNG"),
    (lambda d: d[:40] + bytes([d[40] ^ 0xFF]) + d[41:], "CRC mismatch"),
    (lambda d: d[:8] + d[33:], "missing IHDR"),
])
def test_corrupt_png_raises_clear_error(tmp_path, mangle, pattern):
    p = tmp_path / "bad.png"
    p.write_bytes(mangle(encode_png(np.zeros((4, 4, 3), np.uint8))))
    with pytest.raises(ImageError, match=pattern) as e:
        read_png(p)
    assert "bad.png" in str(e.value)


def test_interlaced_and_bad_filter_and_short_data_rejected():
    with pytest.raises(ImageError, match="interlaced"):
        decode_png(hand_png([bytes(3)], 1, 2, 8, [0], interlace=1))
    with pytest.raises(ImageError, match="unknown filter type 5"):
        decode_png(_with_idat(bytes([5, 0, 0, 0])))
    with pytest.raises(ImageError, match="truncated image data"):
        decode_png(_with_idat(bytes([0, 0, 0])))


def _with_idat(raw):
    ihdr = struct.pack(">IIBBBBB", 1, 1, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw))
            + chunk(b"IEND", b""))


def test_float_image_round_trip(tmp_path):
    img = RNG.random((3, 4, 3)) * 10
    p = tmp_path / "f.npy"
    write_float_image(p, img)
    assert np.load(p).dtype == np.float32
    np.testing.assert_array_equal(read_float_image(p), img.astype(np.float32).astype(np.float64))
    write_float_image(p, img[:, :, 0])
    assert read_float_image(p).shape == (3, 4, 3)
    p.write_bytes(b"junk")
    with pytest.raises(ImageError, match="f.npy"):
        read_float_image(p)
