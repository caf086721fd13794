"""The storage interface: keys, errors, object metadata and the `Storage` base class."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import secrets
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import BinaryIO

COPY_CHUNK_BYTES = 1 << 20
_FULL_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}


class StorageError(Exception):
    """A storage operation failed; ``status_code`` is what the API answers (507, 503, 404)."""

    def __init__(self, message: str, *, key: str | None = None, status_code: int = 503):
        super().__init__(message)
        self.message = message
        self.key = key
        self.status_code = status_code


class ObjectNotFound(StorageError):
    """The key names no stored object."""

    def __init__(self, key: str):
        super().__init__(f"no stored object {key!r}", key=key, status_code=404)


class ChecksumMismatch(StorageError):
    """What was written does not have the SHA-256 the caller expected; nothing was kept."""

    def __init__(self, key: str, *, expected: str, actual: str):
        super().__init__(
            f"sha256 of {key!r} is {actual}, expected {expected}", key=key, status_code=422
        )
        self.expected = expected
        self.actual = actual


@dataclass(frozen=True)
class ObjectStat:
    """What a store knows about one object. ``etag`` is its SHA-256 (hex) when known."""

    key: str
    size_bytes: int
    etag: str
    mtime: datetime


def check_key(key: str) -> str:
    """Return ``key`` if it is a relative POSIX key without ``..``/hidden parts, else ValueError."""
    if not isinstance(key, str) or not key:
        raise ValueError(f"key must be a non-empty string, got {key!r}")
    if key.startswith("/") or "\\" in key or "\x00" in key or key.endswith("/"):
        raise ValueError(f"key {key!r} must be a relative POSIX path")
    for part in key.split("/"):
        if not part or part.startswith("."):
            raise ValueError(f"key {key!r} has an empty, '.' or hidden component")
    return key


def check_range(start: int, end: int | None, size_bytes: int, key: str) -> int:
    """Validate the half-open byte range [start, end) of an object; return the resolved end."""
    stop = size_bytes if end is None else end
    if not 0 <= start <= stop <= size_bytes:
        raise ValueError(f"range [{start}, {end}) is outside {key!r} ({size_bytes} bytes)")
    return stop


def _hash_stream(fh: BinaryIO) -> tuple[str, int]:
    digest = hashlib.sha256()
    size = 0
    while chunk := fh.read(COPY_CHUNK_BYTES):
        digest.update(chunk)
        size += len(chunk)
    return digest.hexdigest(), size


def _verify(key: str, expected: str | None, actual: str) -> None:
    if expected is not None and expected.lower() != actual:
        raise ChecksumMismatch(key, expected=expected.lower(), actual=actual)


class Storage(ABC):
    """Keyed object store. Ranges are half-open ``[start, end)`` byte offsets."""

    @abstractmethod
    def put_file(self, key: str, path: Path, *, sha256: str | None = None) -> ObjectStat:
        """Store the file at ``path`` under ``key`` atomically; verify ``sha256`` if given."""

    @abstractmethod
    def put_bytes(self, key: str, data: bytes, *, sha256: str | None = None) -> ObjectStat:
        """Store ``data`` under ``key`` atomically; verify ``sha256`` if given."""

    @abstractmethod
    def open_range(self, key: str, start: int = 0, end: int | None = None) -> Iterator[bytes]:
        """Stream bytes ``[start, end)`` of ``key``; errors are raised before the first chunk."""

    @abstractmethod
    def stat(self, key: str) -> ObjectStat:
        """Size, etag (sha256) and modification time of ``key``; ObjectNotFound if absent."""

    @abstractmethod
    def delete(self, key: str) -> None:
        """Remove ``key``; removing an absent key is not an error."""

    @abstractmethod
    def list(self, prefix: str = "") -> list[str]:
        """Sorted keys that start with ``prefix`` (a plain string prefix, as in S3)."""

    def exists(self, key: str) -> bool:
        try:
            self.stat(key)
        except ObjectNotFound:
            return False
        return True

    def read_bytes(self, key: str) -> bytes:
        return b"".join(self.open_range(key))

    def get_file(self, key: str, dest: Path) -> Path:
        """Copy ``key`` to the local file ``dest`` atomically (for workers); return ``dest``."""
        dest = Path(dest)
        tmp = dest.with_name(f".{dest.name}.tmp-{secrets.token_hex(4)}")
        try:
            with open(tmp, "wb") as fh:
                for chunk in self.open_range(key):
                    fh.write(chunk)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, dest)
        except OSError as exc:
            raise storage_error_from_os(exc, key) from exc
        finally:
            tmp.unlink(missing_ok=True)
        return dest

    def put_tree(self, prefix: str, directory: Path) -> list[ObjectStat]:
        """Store every regular file under ``directory`` as ``prefix/<relative path>``.

        On any failure the objects already written by this call are deleted again, so a
        model version is either stored whole or not at all.
        """
        prefix = check_key(prefix.rstrip("/"))
        directory = Path(directory)
        if not directory.is_dir():
            raise ValueError(f"directory {str(directory)!r} is not a directory")
        files = sorted(p for p in directory.rglob("*") if p.is_file() and not p.is_symlink())
        written: list[ObjectStat] = []
        try:
            for path in files:
                rel = path.relative_to(directory).as_posix()
                written.append(self.put_file(f"{prefix}/{rel}", path))
        except BaseException:
            for stat in written:
                with contextlib.suppress(StorageError):
                    self.delete(stat.key)
            raise
        return written

    def delete_prefix(self, prefix: str) -> int:
        """Delete every key under ``prefix/``; return how many were deleted."""
        keys = self.list(check_key(prefix.rstrip("/")) + "/")
        for key in keys:
            self.delete(key)
        return len(keys)


def storage_error_from_os(exc: OSError, key: str | None) -> StorageError:
    if exc.errno in _FULL_ERRNOS:
        return StorageError("storage is full: nothing was stored", key=key, status_code=507)
    return StorageError(f"storage failed: {exc.strerror or exc}", key=key, status_code=503)
