"""Image files of a bundle: header sniffing (before any decoding) and decoding.

Single-channel PNG (8/16 bit) or TIFF (8/16 bit, float32), per SCAN_BUNDLE.md. Sizes are
read from the header and checked before a decoder allocates anything; PNGs are decoded with
OpenCV (several times faster than Pillow) when it is installed, else with Pillow.
"""

from __future__ import annotations

import io
import struct
import warnings
import zlib
from dataclasses import dataclass

import numpy as np

try:  # OpenCV is in the "worker" extra only; the backend validates uploads without it.
    import cv2
except ImportError:  # pragma: no cover - exercised by installs without the worker extra
    cv2 = None

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
TIFF_SIGNATURES = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
HEAD_BYTES = 33  # PNG signature + IHDR chunk


class ImageError(ValueError):
    """The file is not an image this spec accepts; the message says why."""


@dataclass(frozen=True)
class ImageInfo:
    """What the header says: ``format`` "png" or "tiff", size in pixels, numpy dtype."""

    format: str
    width: int
    height: int
    dtype: np.dtype

    @property
    def is_float(self) -> bool:
        return self.dtype == np.float32


def sniff_format(head: bytes) -> str | None:
    """ "png", "tiff" or None from the first bytes of a file."""
    if head.startswith(PNG_SIGNATURE):
        return "png"
    if head[:4] in TIFF_SIGNATURES:
        return "tiff"
    return None


def png_info(head: bytes) -> ImageInfo:
    """Parse the IHDR chunk from the first 33 bytes of a PNG (CRC checked)."""
    if len(head) < HEAD_BYTES:
        raise ImageError("is truncated (shorter than a PNG header)")
    length, chunk = struct.unpack(">I4s", head[8:16])
    if chunk != b"IHDR" or length != 13:
        raise ImageError("is a damaged PNG (no IHDR chunk first)")
    (crc,) = struct.unpack(">I", head[29:33])
    if zlib.crc32(head[12:29]) != crc:
        raise ImageError("is a damaged PNG (IHDR checksum mismatch)")
    width, height, depth, color_type = struct.unpack(">IIBB", head[16:26])
    if color_type != 0:
        names = {2: "RGB", 3: "palette", 4: "grey+alpha", 6: "RGBA"}
        raise ImageError(
            f"is a {names.get(color_type, 'non-grey')} PNG; must be single-channel grey"
        )
    if depth not in (8, 16):
        raise ImageError(f"is a {depth}-bit PNG; must be 8 or 16 bit")
    if width == 0 or height == 0:
        raise ImageError("is a PNG of zero size")
    return ImageInfo("png", width, height, np.dtype(np.uint8 if depth == 8 else np.uint16))


def tiff_info(data: bytes) -> ImageInfo:
    """Read the first IFD of a TIFF held in memory, without decoding pixel data."""
    import tifffile  # imported here: a few hundred ms that PNG-only readers do not pay

    try:
        with tifffile.TiffFile(io.BytesIO(data)) as tif:
            if len(tif.pages) != 1:
                raise ImageError(f"is a TIFF of {len(tif.pages)} pages; must hold one image")
            page = tif.pages.first
            samples = page.samplesperpixel
            width, height = page.imagewidth, page.imagelength
            dtype = page.dtype
    except ImageError:
        raise
    except Exception as exc:  # noqa: BLE001 - tifffile raises many types on hostile input
        raise ImageError(f"is not a readable TIFF ({type(exc).__name__}: {exc})") from None
    if samples != 1:
        raise ImageError(f"is a TIFF with {samples} samples per pixel; must be single-channel")
    if dtype is None or np.dtype(dtype) not in (np.uint8, np.uint16, np.float32):
        raise ImageError(f"is a TIFF of sample type {dtype}; must be uint8, uint16 or float32")
    if width == 0 or height == 0:
        raise ImageError("is a TIFF of zero size")
    return ImageInfo("tiff", width, height, np.dtype(dtype))


def decode(data: bytes, info: ImageInfo) -> np.ndarray:
    """Decode a file whose header gave ``info``; (height, width) array of ``info.dtype``.

    Call only after checking ``info``'s size against the caps: decoders allocate from it.
    """
    if info.format == "png":
        array = decode_png_cv2(data) if cv2 is not None else decode_png_pillow(data)
    else:
        array = decode_tiff(data)
    if array.shape != (info.height, info.width) or array.dtype != info.dtype:
        raise ImageError(
            f"decodes to {array.shape} {array.dtype}, not the header's "
            f"({info.height}, {info.width}) {info.dtype}"
        )
    return array


def decode_png_cv2(data: bytes) -> np.ndarray:
    """PNG bytes -> stored values via ``cv2.imdecode(IMREAD_UNCHANGED)`` (no conversions)."""
    try:
        array = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise ImageError(f"cannot be decoded as PNG ({exc})") from None
    if array is None:
        raise ImageError("cannot be decoded as PNG (truncated or corrupt)")
    return array


def decode_png_pillow(data: bytes) -> np.ndarray:
    """PNG bytes -> stored values via Pillow; its decompression-bomb guard never escapes."""
    from PIL import Image

    try:
        with warnings.catch_warnings():
            # Sizes were checked against our own caps before; Pillow's default is lower.
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data), formats=["PNG"]) as img:
                img.load()
                array = np.array(img)
    except Image.DecompressionBombError as exc:
        raise ImageError(f"is too large to decode ({exc})") from None
    except Image.UnidentifiedImageError:
        raise ImageError("cannot be decoded as PNG (not recognised)") from None
    except Exception as exc:  # noqa: BLE001 - Pillow raises OSError, SyntaxError, ValueError...
        raise ImageError(f"cannot be decoded as PNG ({type(exc).__name__}: {exc})") from None
    if array.dtype == np.int32:  # Pillow < 10 gave 16-bit grey as mode "I"
        array = array.astype(np.uint16)
    return array


def decode_tiff(data: bytes) -> np.ndarray:
    """TIFF bytes -> stored values via tifffile, native byte order."""
    import tifffile

    try:
        array = tifffile.imread(io.BytesIO(data), key=0)
    except Exception as exc:  # noqa: BLE001 - hostile input: codecs raise anything
        raise ImageError(f"cannot be decoded as TIFF ({type(exc).__name__}: {exc})") from None
    array = np.asarray(array)
    if array.ndim == 3 and array.shape[-1] == 1:
        array = array[..., 0]
    return array.astype(array.dtype.newbyteorder("="), copy=False)


def value_problem(values: np.ndarray, *, bit_depth: int) -> str | None:
    """Why stored values break the spec (above 2^bit_depth − 1, or non-finite), or None."""
    if values.dtype == np.float32:
        bad = int(np.count_nonzero(~np.isfinite(values)))
        return f"holds {bad} NaN or infinite values" if bad else None
    full_scale = 2**bit_depth - 1
    if full_scale >= np.iinfo(values.dtype).max:
        return None
    peak = int(values.max())
    if peak > full_scale:
        count = int(np.count_nonzero(values > full_scale))
        return (
            f"holds {count} values above 2^{bit_depth} − 1 = {full_scale} "
            f"(maximum {peak}); camera.bit_depth is {bit_depth}"
        )
    return None
