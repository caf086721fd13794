"""Reading and validating a scan bundle: `open_bundle`, `validate_bundle`, `Bundle`.

Validation collects every problem at once. `open_bundle` checks the manifest and every
image's header (size, type) without decoding; pixel values are checked while each image is
decoded. `validate_bundle` also decodes every image once.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from worker.bundle.container import Container, ContainerError, Limits, open_container
from worker.bundle.errors import BundleError, Problem
from worker.bundle.images import (
    HEAD_BYTES,
    ImageError,
    ImageInfo,
    decode,
    png_info,
    sniff_format,
    tiff_info,
    value_problem,
)
from worker.bundle.manifest import (
    MANIFEST_NAME,
    Frame,
    Manifest,
    build_manifest,
    check_manifest,
    parse_manifest_json,
)
from worker.bundle.matching import check_frames, reference_map
from worker.bundle.paths import normalize_path, path_problem
from worker.bundle.radiometry import linearize, radiance, select_dark


class Bundle:
    """An open, valid bundle. Use as a context manager (a ZIP stays open until closed).

    Thread-safe for reading: `radiance_many` decodes in a thread pool.
    """

    def __init__(self, container: Container, manifest: Manifest, infos: dict[int, ImageInfo]):
        self._container = container
        self.manifest = manifest
        self.frames: tuple[Frame, ...] = manifest.frames
        self._infos = infos
        self._references = reference_map(self.frames)
        self._darks = self._match_darks()
        self._dark_cache: dict[int, np.ndarray] = {}
        self._lock = threading.Lock()

    def _match_darks(self) -> dict[int, int | None]:
        """Dark frame index per lit frame; only darks of the same encoding (integer/float)."""
        out: dict[int, int | None] = {}
        for frame in self.frames:
            if frame.kind == "dark":
                continue
            is_float = self._infos[frame.index].is_float
            darks = [
                (f.index, f.exposure)
                for f in self.frames
                if f.kind == "dark" and self._infos[f.index].is_float == is_float
            ]
            out[frame.index] = select_dark(frame.exposure, darks)
        return out

    def __enter__(self) -> Bundle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._container.close()

    def _frame(self, frame: Frame | int) -> Frame:
        index = frame if isinstance(frame, int) else frame.index
        if not 0 <= index < len(self.frames) or (
            isinstance(frame, Frame) and self.frames[index] != frame
        ):
            raise ValueError(f"frame: {frame!r} is not a frame of this bundle")
        return self.frames[index]

    def image_info(self, frame: Frame | int) -> ImageInfo:
        """Header of the frame's image: format, size, dtype."""
        return self._infos[self._frame(frame).index]

    def raw(self, frame: Frame | int) -> np.ndarray:
        """Stored values (H, W), uint8/uint16/float32; BundleError if the file is broken."""
        f = self._frame(frame)
        bit_depth = self.manifest.camera.bit_depth
        try:
            values = decode(self._container.read(f.file), self._infos[f.index])
        except (ContainerError, ImageError) as exc:
            raise BundleError([Problem(f.file, str(exc))]) from None
        message = value_problem(values, bit_depth=bit_depth)
        if message:
            raise BundleError([Problem(f.file, message)])
        return values

    def dark_of(self, frame: Frame | int) -> Frame | None:
        """The dark frame that corrects ``frame`` (None for darks and when there is none)."""
        index = self._darks.get(self._frame(frame).index)
        return None if index is None else self.frames[index]

    def _linear(self, frame: Frame) -> np.ndarray:
        cam = self.manifest.camera
        return linearize(self.raw(frame), bit_depth=cam.bit_depth, gamma=cam.response_gamma)

    def _dark_linear(self, dark: Frame) -> np.ndarray:
        with self._lock:  # darks are few and shared by many frames: decode each once
            cached = self._dark_cache.get(dark.index)
            if cached is None:
                cached = self._linear(dark)
                cached.flags.writeable = False
                self._dark_cache[dark.index] = cached
            return cached

    def radiance(self, frame: Frame | int, *, out: np.ndarray | None = None) -> np.ndarray:
        """L = (lin(v) − lin(v_dark)) / exposure, (H, W) float32 (SCAN_BUNDLE.md).

        For a dark frame itself: lin(v) / exposure (no dark is subtracted from a dark).
        ``out``: (H, W) float32 array to write L into (returned).
        """
        f = self._frame(frame)
        cam = self.manifest.camera
        dark = self.dark_of(f)
        return radiance(
            self.raw(f),
            None if dark is None else self._dark_linear(dark),
            bit_depth=cam.bit_depth,
            gamma=cam.response_gamma,
            exposure=f.exposure,
            out=out,
        )

    def radiance_many(
        self, frames: Iterable[Frame | int], *, max_workers: int | None = None
    ) -> np.ndarray:
        """Radiance of several frames, (N, H, W) float32, decoded in parallel threads.

        ``max_workers`` defaults to min(4, CPU count); OpenCV and zlib release the GIL.
        """
        chosen = [self._frame(f) for f in frames]
        cam = self.manifest.camera
        out = np.empty((len(chosen), cam.height, cam.width), dtype=np.float32)

        def fill(i: int) -> None:
            self.radiance(chosen[i], out=out[i])

        workers = max_workers or min(4, os.cpu_count() or 1)
        if workers <= 1 or len(chosen) <= 1:
            for i in range(len(chosen)):
                fill(i)
        else:
            with ThreadPoolExecutor(max_workers=workers) as pool:
                list(pool.map(fill, range(len(chosen))))
        return out

    def reference_of(self, frame: Frame | int) -> Frame | None:
        """The reference frame with the same kind, azimuth, polar angle, channel, period and
        phase (angles modulo 360°, numbers within 1e-6); None for reference frames or none."""
        return self._references.get(self._frame(frame).index)

    def frames_where(self, **fields: Any) -> tuple[Frame, ...]:
        """Frames whose attributes equal the given values, e.g. ``kind="fringe"``."""
        return tuple(f for f in self.frames if all(getattr(f, k) == v for k, v in fields.items()))


def _check_images(
    container: Container,
    manifest_value: Any,
    limits: Limits,
    *,
    decode_all: bool,
) -> tuple[dict[int, ImageInfo], list[Problem]]:
    """Header (and with ``decode_all`` pixel) checks of every image a frame names.

    Works on the raw manifest so that image problems are reported together with manifest
    problems; fields that are themselves invalid are simply not used.
    """
    frames = manifest_value.get("frames") if isinstance(manifest_value, dict) else None
    camera = manifest_value.get("camera") if isinstance(manifest_value, dict) else None
    camera = camera if isinstance(camera, dict) else {}
    camera_problems = check_manifest({"camera": camera})
    camera_ok = bool(camera) and not any(p.where.startswith("camera.") for p in camera_problems)
    size = (int(camera["width"]), int(camera["height"])) if camera_ok else None
    bit_depth = int(camera["bit_depth"]) if camera_ok else None
    infos: dict[int, ImageInfo] = {}
    found: list[tuple[int, Problem]] = []
    seen: set[str] = set()
    for i, frame in enumerate(frames if isinstance(frames, list) else []):
        if not isinstance(frame, dict) or path_problem(frame.get("file")) is not None:
            continue
        path = normalize_path(frame["file"])
        if path in seen:
            continue  # reported as a duplicate by the frame rules
        seen.add(path)
        try:
            info = _header(container, path, limits)
            if size is not None and (info.width, info.height) != size:
                raise ImageError(
                    f"is {info.width}×{info.height} pixels, not camera.width × camera.height "
                    f"= {size[0]}×{size[1]} (frames[{i}])"
                )
            infos[i] = info
        except (ContainerError, ImageError) as exc:
            found.append((i, Problem(path, str(exc))))
    if decode_all and bit_depth is not None:
        found += _decode_problems(container, frames, infos, bit_depth=bit_depth)
    return infos, [problem for _, problem in sorted(found, key=lambda item: item[0])]


def _decode_problems(
    container: Container, frames: list, infos: dict[int, ImageInfo], *, bit_depth: int
) -> list[tuple[int, Problem]]:
    """Decode every image once (in threads: OpenCV and zlib release the GIL); value checks."""

    def check(i: int) -> tuple[int, Problem] | None:
        path = normalize_path(frames[i]["file"])
        try:
            values = decode(container.read(path), infos[i])
        except (ContainerError, ImageError) as exc:
            return i, Problem(path, str(exc))
        message = value_problem(values, bit_depth=bit_depth)
        return (i, Problem(path, message)) if message else None

    with ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool:
        return [r for r in pool.map(check, sorted(infos)) if r is not None]


def _header(container: Container, path: str, limits: Limits) -> ImageInfo:
    """Image header of ``path``: the first bytes of a PNG; a TIFF is read whole."""
    head = container.read(path, limit=HEAD_BYTES)
    fmt = sniff_format(head)
    if fmt == "png":
        info = png_info(head)
    elif fmt == "tiff":
        info = tiff_info(container.read(path))
    else:
        raise ImageError("is not a PNG or TIFF image")
    pixels = info.width * info.height
    if pixels > limits.max_image_pixels:
        raise ImageError(
            f"header claims {info.width}×{info.height} pixels, more than "
            f"max_image_pixels = {limits.max_image_pixels}"
        )
    return info


def _load(path: str | os.PathLike, limits: Limits, *, decode_all: bool):
    """(container, manifest or None, infos, problems); the container is None if unopenable."""
    container, problems = open_container(path, limits)
    if container is None:
        return None, None, {}, problems
    try:
        return (container, *_load_from(container, problems, limits, decode_all=decode_all))
    except BaseException:
        container.close()
        raise


def _load_from(container: Container, problems: list[Problem], limits: Limits, *, decode_all: bool):
    """(manifest or None, infos, problems) of an open container; ``problems`` so far."""
    try:
        # One byte over the cap is enough to know it is too large.
        data = container.read(MANIFEST_NAME, limit=limits.max_manifest_bytes + 1)
    except ContainerError as exc:
        return None, {}, [*problems, Problem(MANIFEST_NAME, str(exc))]
    value, parse_problems = parse_manifest_json(data, max_bytes=limits.max_manifest_bytes)
    if parse_problems:
        return None, {}, [*problems, *parse_problems]
    field_problems = check_manifest(value)
    problems += field_problems
    manifest = None
    if not field_problems:
        manifest = build_manifest(value)
        problems += check_frames(manifest.frames)
    camera = value.get("camera") if isinstance(value, dict) else None
    pixels_ok = _camera_pixels_ok(camera, limits, problems)
    infos, image_problems = (
        _check_images(container, value, limits, decode_all=decode_all) if pixels_ok else ({}, [])
    )
    problems += image_problems
    return manifest, infos, problems


def _camera_pixels_ok(camera: Any, limits: Limits, problems: list[Problem]) -> bool:
    """False (and a problem) when camera.width × camera.height exceeds the pixel cap."""
    if not isinstance(camera, dict):
        return True
    w, h = camera.get("width"), camera.get("height")
    if (
        isinstance(w, int | float)
        and isinstance(h, int | float)
        and w * h > limits.max_image_pixels
    ):
        problems.append(
            Problem(
                "camera", f"width × height exceeds max_image_pixels = {limits.max_image_pixels}"
            )
        )
        return False
    return True


def _limits(caps: dict[str, Any]) -> Limits:
    try:
        return Limits(**caps)
    except TypeError:
        known = ", ".join(Limits.__dataclass_fields__)
        raise TypeError(f"unknown cap in {sorted(caps)}; known caps: {known}") from None


def validate_bundle(path: str | os.PathLike, **caps: Any) -> list[Problem]:
    """Every problem of the bundle at ``path`` (folder or ZIP); [] when it is valid.

    Decodes every image once to check its values. Never raises on bad input. ``caps`` are
    the fields of `Limits` (``max_total_bytes``, ``max_ratio``, ...).
    """
    container, _, _, problems = _load(path, _limits(caps), decode_all=True)
    if container is not None:
        container.close()
    return problems


def open_bundle(path: str | os.PathLike, *, decode_all: bool = False, **caps: Any) -> Bundle:
    """Open the bundle at ``path`` (folder or ZIP); BundleError lists every problem.

    Checks the manifest and every image header; pixel values are checked as images are
    decoded (``decode_all=True`` decodes every image now, as `validate_bundle` does).
    """
    container, manifest, infos, problems = _load(path, _limits(caps), decode_all=decode_all)
    if problems or manifest is None:
        if container is not None:
            container.close()
        raise BundleError(problems or [Problem("bundle", "cannot be read")])
    return Bundle(container, manifest, infos)
