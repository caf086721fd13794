"""`LocalStorage`: objects as files under a directory, written atomically (temp, fsync, rename)."""

from __future__ import annotations

import hashlib
import io
import json
import os
import secrets
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import BinaryIO

from backend.storage.base import (
    COPY_CHUNK_BYTES,
    ObjectNotFound,
    ObjectStat,
    Storage,
    _hash_stream,
    _verify,
    check_key,
    check_range,
    storage_error_from_os,
)


class LocalStorage(Storage):
    """Objects as files under ``root``; temp files in ``root/.tmp``, sha256 in ``root/.sha256``.

    Writes go to a temp file on the same filesystem, are fsynced and renamed into place, so a
    reader sees either the old object or the new one, never a partial one.
    """

    def __init__(self, root: Path):
        self.root = Path(root)
        self._tmp = self.root / ".tmp"
        self._meta = self.root / ".sha256"

    def _path(self, key: str) -> Path:
        return self.root.joinpath(*check_key(key).split("/"))

    def _meta_path(self, key: str) -> Path:
        return self._meta.joinpath(*key.split("/"))

    def _write(self, key: str, source: BinaryIO, expected: str | None) -> ObjectStat:
        path = self._path(key)
        tmp = self._tmp / f"{secrets.token_hex(8)}.part"
        digest = hashlib.sha256()
        try:
            self._tmp.mkdir(parents=True, exist_ok=True)
            with open(tmp, "wb") as out:
                while chunk := source.read(COPY_CHUNK_BYTES):
                    digest.update(chunk)
                    out.write(chunk)
                out.flush()
                os.fsync(out.fileno())
            actual = digest.hexdigest()
            _verify(key, expected, actual)
            size = tmp.stat().st_size
            self._write_meta(key, actual, size)
            path.parent.mkdir(parents=True, exist_ok=True)
            os.replace(tmp, path)
            _fsync_dir(path.parent)
        except OSError as exc:
            raise storage_error_from_os(exc, key) from exc
        finally:
            tmp.unlink(missing_ok=True)
        return self.stat(key)

    def _write_meta(self, key: str, sha256: str, size_bytes: int) -> None:
        meta = self._meta_path(key)
        meta.parent.mkdir(parents=True, exist_ok=True)
        tmp = self._tmp / f"{secrets.token_hex(8)}.meta"
        try:
            with open(tmp, "w") as fh:
                json.dump({"sha256": sha256, "size_bytes": size_bytes}, fh)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, meta)
        finally:
            tmp.unlink(missing_ok=True)

    def put_file(self, key: str, path: Path, *, sha256: str | None = None) -> ObjectStat:
        check_key(key)
        try:
            src = open(path, "rb")  # noqa: SIM115 - closed below, errors mapped
        except OSError as exc:
            raise ValueError(f"path {str(path)!r} cannot be read: {exc.strerror}") from exc
        with src:
            return self._write(key, src, sha256)

    def put_bytes(self, key: str, data: bytes, *, sha256: str | None = None) -> ObjectStat:
        check_key(key)
        return self._write(key, io.BytesIO(data), sha256)

    def stat(self, key: str) -> ObjectStat:
        path = self._path(key)
        try:
            st = path.stat()
        except FileNotFoundError:
            raise ObjectNotFound(key) from None
        except OSError as exc:
            raise storage_error_from_os(exc, key) from exc
        if not path.is_file():
            raise ObjectNotFound(key)
        sha = self._read_meta(key, st.st_size)
        if sha is None:
            # Written by someone else (or a crash between sidecar and rename): hash once.
            try:
                with open(path, "rb") as fh:
                    sha, _ = _hash_stream(fh)
                self._tmp.mkdir(parents=True, exist_ok=True)
                self._write_meta(key, sha, st.st_size)
            except OSError as exc:
                raise storage_error_from_os(exc, key) from exc
        mtime = datetime.fromtimestamp(st.st_mtime, tz=UTC)
        return ObjectStat(key=key, size_bytes=st.st_size, etag=sha, mtime=mtime)

    def _read_meta(self, key: str, size_bytes: int) -> str | None:
        try:
            meta = json.loads(self._meta_path(key).read_text())
        except (OSError, ValueError):
            return None
        if not isinstance(meta, dict) or meta.get("size_bytes") != size_bytes:
            return None
        return meta.get("sha256")

    def open_range(self, key: str, start: int = 0, end: int | None = None) -> Iterator[bytes]:
        size = self.stat(key).size_bytes
        stop = check_range(start, end, size, key)
        try:
            fh = open(self._path(key), "rb")  # noqa: SIM115 - closed by the generator
        except FileNotFoundError:
            raise ObjectNotFound(key) from None
        except OSError as exc:
            raise storage_error_from_os(exc, key) from exc
        fh.seek(start)
        return _iter_file(fh, stop - start)

    def delete(self, key: str) -> None:
        try:
            self._path(key).unlink(missing_ok=True)
            self._meta_path(key).unlink(missing_ok=True)
        except OSError as exc:
            raise storage_error_from_os(exc, key) from exc

    def list(self, prefix: str = "") -> list[str]:
        # Walk only the directory the prefix points into, not the whole store.
        head = prefix.rsplit("/", 1)[0] if "/" in prefix else ""
        base = self.root.joinpath(*head.split("/")) if head else self.root
        if not base.is_dir():
            return []
        keys = []
        for dirpath, dirnames, filenames in os.walk(base):
            dirnames[:] = [d for d in dirnames if not d.startswith(".")]
            rel_dir = Path(dirpath).relative_to(self.root).as_posix()
            for name in filenames:
                if name.startswith("."):
                    continue
                key = name if rel_dir == "." else f"{rel_dir}/{name}"
                if key.startswith(prefix):
                    keys.append(key)
        return sorted(keys)


def _iter_file(fh: BinaryIO, remaining: int) -> Iterator[bytes]:
    with fh:
        while remaining > 0:
            chunk = fh.read(min(COPY_CHUNK_BYTES, remaining))
            if not chunk:
                break
            remaining -= len(chunk)
            yield chunk


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
