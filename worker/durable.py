"""Durable file writes: a crash or power cut leaves either the old state or the new one.

The one implementation for the worker side and the rig agent: model directories, simulator
ground truth, derived assets, registration output and the rig's spool all write through it.
A file is written to a temporary name, fsynced and renamed; a directory is filled under a
temporary sibling name, fsynced and renamed; the parent directory is fsynced after a rename so
that the rename itself survives a power cut.
"""

from __future__ import annotations

import io
import os
import shutil
import tempfile
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np

__all__ = [
    "fsync_dir",
    "npy_bytes",
    "replace_dir_atomic",
    "write_file_atomic",
    "write_new_file",
]


def fsync_dir(path: str | os.PathLike) -> None:
    """Flush a directory's entries (new names, renames) to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_new_file(path: str | os.PathLike, data: bytes) -> None:
    """Create ``path`` (it must not exist) with ``data`` and fsync it.

    For files inside a temporary directory that is renamed into place as a whole.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    with open(target, "xb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def npy_bytes(array: np.ndarray) -> bytes:
    """The .npy encoding of ``array`` (so it can be written durably like any other bytes)."""
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


def write_file_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write or replace ``path`` atomically: temp file in the same folder, fsync, rename."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    fsync_dir(target.parent)


def replace_dir_atomic(target: str | os.PathLike, fill: Callable[[Path], None]) -> Path:
    """Build a directory with ``fill(tmp_dir)`` and rename it to ``target`` once complete.

    An existing ``target`` is swapped out only after the new one is whole (and then removed);
    if ``fill`` raises, the temporary directory is removed and ``target`` is untouched.
    """
    out = Path(target)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp-{uuid.uuid4().hex}")
    tmp.mkdir()
    try:
        fill(tmp)
        for folder, _dirs, _files in os.walk(tmp):
            fsync_dir(folder)
        if out.exists():
            trash = out.with_name(f".{out.name}.old-{uuid.uuid4().hex}")
            os.rename(out, trash)
            os.rename(tmp, out)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.rename(tmp, out)
        fsync_dir(out.parent)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
