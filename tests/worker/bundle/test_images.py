"""Image headers and decoders: OpenCV and Pillow agree; nothing escapes as a foreign error."""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest
import tifffile

from worker.bundle.images import (
    ImageError,
    decode,
    decode_png_cv2,
    decode_png_pillow,
    png_info,
    sniff_format,
    tiff_info,
    value_problem,
)
from worker.bundle.writer import encode_image


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_png_decoders_agree_with_the_written_values(dtype) -> None:
    rng = np.random.default_rng(5)
    values = rng.integers(0, np.iinfo(dtype).max + 1, size=(31, 47), dtype=dtype)
    data = encode_image("x.png", values)
    info = png_info(data[:33])
    assert (info.format, info.width, info.height, info.dtype) == ("png", 47, 31, np.dtype(dtype))
    for decoder in (decode_png_cv2, decode_png_pillow):
        out = decoder(data)
        assert out.dtype == dtype
        np.testing.assert_array_equal(out, values)
    np.testing.assert_array_equal(decode(data, info), values)


def test_pillow_decompression_bomb_never_escapes() -> None:
    # (OpenCV is never handed such a file: the reader checks the header's size first.)
    def chunk(kind: bytes, body: bytes) -> bytes:
        return (
            struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
        )

    ihdr = struct.pack(">IIBBBBB", 30_000, 30_000, 8, 0, 0, 0, 0)  # 900 Mpx > Pillow's 2 × 89 Mpx
    data = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(bytes(99)))
    data += chunk(b"IEND", b"")
    with pytest.raises(ImageError, match="too large"):
        decode_png_pillow(data)


@pytest.mark.parametrize("byteorder", ["<", ">"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_tiff_headers_and_decoding(byteorder: str, dtype) -> None:
    values = (np.arange(6 * 5).reshape(6, 5) * 3).astype(dtype)
    buf = io.BytesIO()
    tifffile.imwrite(buf, values, byteorder=byteorder)
    data = buf.getvalue()
    assert sniff_format(data[:8]) == "tiff"
    info = tiff_info(data)
    assert (info.width, info.height, info.dtype) == (5, 6, np.dtype(dtype))
    assert info.is_float == (dtype == np.float32)
    out = decode(data, info)
    assert out.dtype == np.dtype(dtype) and out.dtype.isnative
    np.testing.assert_array_equal(out, values)


def test_tiff_of_other_sample_types_is_refused() -> None:
    for values in (np.zeros((4, 4), np.int16), np.zeros((4, 4), np.float64)):
        buf = io.BytesIO()
        tifffile.imwrite(buf, values)
        with pytest.raises(ImageError, match="sample type"):
            tiff_info(buf.getvalue())


def test_header_and_decoded_array_must_agree() -> None:
    data = encode_image("x.png", np.zeros((4, 6), np.uint16))
    lying = png_info(encode_image("y.png", np.zeros((4, 7), np.uint16))[:33])
    with pytest.raises(ImageError, match="not the header's"):
        decode(data, lying)


def test_value_problem() -> None:
    v = np.array([[0, 4095, 4096, 65535]], np.uint16)
    assert "2 values above 2^12 − 1 = 4095 (maximum 65535)" in value_problem(v, bit_depth=12)
    assert value_problem(v, bit_depth=16) is None
    assert value_problem(v[:, :2], bit_depth=12) is None
    assert value_problem(np.array([[255]], np.uint8), bit_depth=8) is None
    assert value_problem(np.array([[1.5, -2.0]], np.float32), bit_depth=12) is None
    assert "1 NaN" in value_problem(np.array([[np.nan, 0]], np.float32), bit_depth=12)


def test_without_opencv_pillow_reads_and_writes(monkeypatch) -> None:
    from worker.bundle import images, writer

    values = np.arange(20 * 9, dtype=np.uint16).reshape(20, 9) * 300
    with_cv2 = encode_image("x.png", values)
    monkeypatch.setattr(images, "cv2", None)
    monkeypatch.setattr(writer, "cv2", None)
    with_pillow = encode_image("x.png", values)
    for data in (with_cv2, with_pillow):
        np.testing.assert_array_equal(decode(data, png_info(data[:33])), values)
