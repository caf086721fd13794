"""Writing a scan bundle: validate first, then write atomically (temp, fsync, rename).

Output is deterministic: the same manifest and images give byte-identical files (and ZIPs:
fixed timestamps, sorted entries, stored members).
"""

from __future__ import annotations

import io
import json
import os
import shutil
import uuid
import zipfile
from collections.abc import Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from worker.bundle.errors import BundleError, Problem
from worker.bundle.images import cv2, value_problem
from worker.bundle.manifest import (
    MANIFEST_NAME,
    build_manifest,
    check_manifest,
    parse_manifest_json,
)
from worker.bundle.matching import check_frames
from worker.bundle.paths import normalize_path, path_problem

PNG_COMPRESSION = 1  # zlib level: 16-bit camera noise barely compresses, so speed wins
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)
_TIFF_SUFFIXES = (".tif", ".tiff")


def _plain(value: Any) -> Any:
    """numpy scalars/arrays and tuples -> plain JSON values (the manifest dict is not modified)."""
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    return value


def _image_problems(value: dict, images: Mapping[str, np.ndarray]) -> list[Problem]:
    camera = value["camera"]
    shape = (int(camera["height"]), int(camera["width"]))
    bit_depth = int(camera["bit_depth"])
    named = {normalize_path(f["file"]): i for i, f in enumerate(value["frames"])}
    problems: list[Problem] = []
    given: set[str] = set()
    for key, array in images.items():
        where = f"images[{key!r}]"
        message = path_problem(key)
        if message:
            problems.append(Problem(where, message))
            continue
        path = normalize_path(key)
        if path in given:
            problems.append(Problem(where, "given twice (under two spellings)"))
        given.add(path)
        if path not in named:
            problems.append(Problem(where, "no frame names this file"))
        message = _array_problem(path, array, shape, bit_depth)
        if message:
            problems.append(Problem(where, message))
    for path, i in named.items():
        if path not in given:
            problems.append(Problem(f"frames[{i}].file", f"no image given for {path!r}"))
    return problems


def _array_problem(path: str, array: Any, shape: tuple[int, int], bit_depth: int) -> str | None:
    if not isinstance(array, np.ndarray):
        return f"must be a numpy array, not {type(array).__name__}"
    if array.dtype not in (np.uint8, np.uint16, np.float32):
        return f"dtype {array.dtype}: must be uint8, uint16 (PNG or TIFF) or float32 (TIFF)"
    if array.shape != shape:
        return f"shape {array.shape} is not (camera.height, camera.width) = {shape}"
    tiff = path.lower().endswith(_TIFF_SUFFIXES)
    if not tiff and not path.lower().endswith(".png"):
        return "file name must end in .png, .tif or .tiff"
    if array.dtype == np.float32 and not tiff:
        return "float32 images must be TIFF (.tif/.tiff): PNG holds integers only"
    return value_problem(array, bit_depth=bit_depth)


def encode_image(path: str, array: np.ndarray) -> bytes:
    """PNG (uint8/uint16) or, for .tif/.tiff or float32, uncompressed TIFF bytes."""
    if path.lower().endswith(_TIFF_SUFFIXES) or array.dtype == np.float32:
        import tifffile

        buf = io.BytesIO()
        tifffile.imwrite(buf, array, photometric="minisblack", metadata=None, software=False)
        return buf.getvalue()
    array = np.ascontiguousarray(array)
    if cv2 is not None:
        ok, encoded = cv2.imencode(".png", array, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
        if not ok:  # pragma: no cover - OpenCV fails only on unsupported dtypes, excluded above
            raise RuntimeError(f"OpenCV could not encode {path}")
        return encoded.tobytes()
    from PIL import Image  # installs without the worker extra

    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG", compress_level=PNG_COMPRESSION)
    return buf.getvalue()


def write_bundle(
    out: str | os.PathLike,
    manifest: Mapping[str, Any],
    images: Mapping[str, np.ndarray],
    *,
    as_zip: bool = False,
    overwrite: bool = False,
) -> Path:
    """Validate ``manifest`` and ``images`` (keyed by frame file path), then write the bundle.

    Writes a folder, or with ``as_zip`` a ZIP (stored members, manifest at the root), into a
    temporary name next to ``out``, fsyncs files and folders, and renames it into place: a
    reader never sees a half-written bundle. Raises BundleError listing every problem, and
    FileExistsError if ``out`` exists and not ``overwrite``. Returns ``Path(out)``.
    """
    out = Path(out)
    value = _plain(manifest)
    problems = check_manifest(value)
    if not problems:
        problems += check_frames(build_manifest(value).frames)
        problems += _image_problems(value, images)
    if not problems:
        try:
            text = json.dumps(value, indent=2, ensure_ascii=False, allow_nan=False)
            manifest_bytes = (text + "\n").encode("utf-8")
        except (TypeError, ValueError) as exc:  # UnicodeEncodeError is a ValueError
            problems.append(Problem("manifest", f"cannot be written as strict JSON: {exc}"))
        else:  # e.g. keys 1 and "1" both become "1": read it back as the reader will
            problems += parse_manifest_json(manifest_bytes)[1]
    if problems:
        raise BundleError(problems)
    if (out.exists() or out.is_symlink()) and not overwrite:
        raise FileExistsError(f"out: {out} exists (pass overwrite=True to replace it)")
    items = sorted(((normalize_path(k), a) for k, a in images.items()), key=lambda item: item[0])
    tmp = out.with_name(f".{out.name}.tmp-{uuid.uuid4().hex}")
    try:
        (_write_zip if as_zip else _write_dir)(tmp, manifest_bytes, _encoded(items))
        _replace(tmp, out)
    except BaseException:
        _remove(tmp)
        raise
    return out


def _encoded(items: list[tuple[str, np.ndarray]]) -> Iterator[tuple[str, bytes]]:
    """``(path, file bytes)`` in the order of ``items``, encoded a few at a time in threads
    (the encoders release the GIL); at most one batch of encoded files is held in memory."""
    workers = min(4, os.cpu_count() or 1)
    batch = 2 * workers
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for start in range(0, len(items), batch):
            chunk = items[start : start + batch]
            yield from zip(
                (path for path, _ in chunk),
                pool.map(lambda item: encode_image(*item), chunk),
                strict=True,
            )


def _write_dir(tmp: Path, manifest: bytes, files: Iterator[tuple[str, bytes]]) -> None:
    tmp.mkdir(parents=False)
    _write_file(tmp / MANIFEST_NAME, manifest)
    for path, data in files:
        target = tmp / path
        target.parent.mkdir(parents=True, exist_ok=True)
        _write_file(target, data)
    for folder, _, _ in os.walk(tmp, topdown=False):
        _fsync_dir(Path(folder))


def _write_zip(tmp: Path, manifest: bytes, files: Iterator[tuple[str, bytes]]) -> None:
    with open(tmp, "xb") as fh:
        with zipfile.ZipFile(fh, "w", compression=zipfile.ZIP_STORED) as archive:
            archive.writestr(_zip_info(MANIFEST_NAME, zipfile.ZIP_DEFLATED), manifest)
            for path, data in files:
                archive.writestr(_zip_info(path, zipfile.ZIP_STORED), data)
        fh.flush()
        os.fsync(fh.fileno())


def _zip_info(name: str, compress_type: int) -> zipfile.ZipInfo:
    """Fixed time stamp and mode, so that the same input gives the same bytes."""
    info = zipfile.ZipInfo(name, date_time=_ZIP_TIME)
    info.create_system = 3
    info.external_attr = 0o100644 << 16
    info.compress_type = compress_type
    return info


def _write_file(path: Path, data: bytes) -> None:
    with open(path, "xb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _replace(tmp: Path, out: Path) -> None:
    """Rename ``tmp`` to ``out``; an existing ``out`` is moved aside first, then deleted."""
    old = None
    if out.exists() or out.is_symlink():
        old = out.with_name(f".{out.name}.old-{uuid.uuid4().hex}")
        os.rename(out, old)
    os.rename(tmp, out)
    _fsync_dir(out.parent)
    if old is not None:
        _remove(old)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists() or path.is_symlink():
        path.unlink()
