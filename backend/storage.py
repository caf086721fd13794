"""One storage interface for bundles, model directories and assets, with two backends.

``LocalStorage`` keeps objects as files under a directory (the default, under the data dir);
``S3Storage`` keeps them in an S3-compatible bucket (AWS, MinIO, …). Both take the same POSIX
keys (``scans/12/bundle.zip``), write atomically and verify a SHA-256 checksum of what they
write, and report failures as :class:`StorageError` carrying the HTTP status the API should
answer with (507 when the disk or quota is full, 503 when the store is unreachable, 404 for a
missing object), so a failed write never leaves half an object behind.
"""

from __future__ import annotations

import base64
import contextlib
import errno
import hashlib
import io
import json
import os
import secrets
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO

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


class S3Storage(Storage):
    """Objects in an S3-compatible bucket; the SHA-256 travels as object metadata ``sha256``.

    Every put sends a SHA-256 checksum the server verifies before it makes the object
    visible (S3 puts are atomic), and the stored size is checked afterwards.
    """

    def __init__(
        self,
        *,
        bucket: str,
        endpoint_url: str | None = None,
        access_key_id: str | None = None,
        secret_access_key: str | None = None,
        region: str | None = None,
        client: Any = None,
        multipart_threshold_bytes: int = 64 << 20,
    ):
        if not bucket:
            raise ValueError("bucket must be a non-empty bucket name")
        if multipart_threshold_bytes < 5 << 20:
            raise ValueError("multipart_threshold_bytes must be at least 5 MiB (S3's part size)")
        self.bucket = bucket
        if client is None:
            import boto3
            from botocore.config import Config

            client = boto3.client(
                "s3",
                endpoint_url=endpoint_url,
                aws_access_key_id=access_key_id,
                aws_secret_access_key=secret_access_key,
                region_name=region or "us-east-1",
                config=Config(
                    retries={"max_attempts": 3, "mode": "standard"},
                    connect_timeout=5,
                    read_timeout=60,
                    s3={"addressing_style": "path"},
                ),
            )
        self.client = client
        self.multipart_threshold_bytes = multipart_threshold_bytes

    def _call(self, key: str | None, fn: Any, **kwargs: Any) -> Any:
        from botocore.exceptions import BotoCoreError, ClientError

        try:
            return fn(**kwargs)
        except ClientError as exc:
            code = str(exc.response.get("Error", {}).get("Code", ""))
            if code in {"NoSuchKey", "404", "NotFound"} and key is not None:
                raise ObjectNotFound(key) from None
            if code in {"EntityTooLarge", "QuotaExceeded", "XMinioStorageFull"}:
                raise StorageError(
                    "storage is full: nothing was stored", key=key, status_code=507
                ) from exc
            raise StorageError(f"object storage answered {code}", key=key) from exc
        except BotoCoreError as exc:
            raise StorageError(f"object storage unreachable: {exc}", key=key) from exc

    def ensure_bucket(self) -> None:
        """Create the bucket if it does not exist (for a fresh MinIO)."""
        from botocore.exceptions import ClientError

        try:
            self.client.head_bucket(Bucket=self.bucket)
        except ClientError:
            self._call(None, self.client.create_bucket, Bucket=self.bucket)

    def _put(self, key: str, body: Any, sha256_hex: str, size_bytes: int) -> ObjectStat:
        self._call(
            key,
            self.client.put_object,
            Bucket=self.bucket,
            Key=key,
            Body=body,
            ContentLength=size_bytes,
            ChecksumSHA256=base64.b64encode(bytes.fromhex(sha256_hex)).decode(),
            Metadata={"sha256": sha256_hex},
        )
        stat = self.stat(key)
        if stat.size_bytes != size_bytes:
            self.delete(key)
            raise StorageError(
                f"object storage kept {stat.size_bytes} of {size_bytes} bytes", key=key
            )
        return stat

    def put_file(self, key: str, path: Path, *, sha256: str | None = None) -> ObjectStat:
        check_key(key)
        try:
            with open(path, "rb") as fh:
                actual, size = _hash_stream(fh)
        except OSError as exc:
            raise ValueError(f"path {str(path)!r} cannot be read: {exc.strerror}") from exc
        _verify(key, sha256, actual)
        if size < self.multipart_threshold_bytes:
            with open(path, "rb") as fh:
                return self._put(key, fh, actual, size)
        return self._put_multipart(key, path, actual, size)

    def _put_multipart(self, key: str, path: Path, sha256_hex: str, size_bytes: int) -> ObjectStat:
        """Large files (a single S3 PUT stops at 5 GB): multipart, each part checksummed."""
        from boto3.exceptions import S3UploadFailedError
        from boto3.s3.transfer import TransferConfig

        config = TransferConfig(
            multipart_threshold=self.multipart_threshold_bytes,
            multipart_chunksize=self.multipart_threshold_bytes,  # S3 parts: 5 MiB or more
            use_threads=False,
        )
        extra = {"Metadata": {"sha256": sha256_hex}, "ChecksumAlgorithm": "SHA256"}
        try:
            self._call(
                key,
                self.client.upload_file,
                Filename=str(path),
                Bucket=self.bucket,
                Key=key,
                ExtraArgs=extra,
                Config=config,
            )
        except S3UploadFailedError as exc:
            raise StorageError(f"object storage refused the upload: {exc}", key=key) from exc
        stat = self.stat(key)
        if stat.size_bytes != size_bytes:
            self.delete(key)
            raise StorageError(
                f"object storage kept {stat.size_bytes} of {size_bytes} bytes", key=key
            )
        return stat

    def put_bytes(self, key: str, data: bytes, *, sha256: str | None = None) -> ObjectStat:
        check_key(key)
        actual = hashlib.sha256(data).hexdigest()
        _verify(key, sha256, actual)
        return self._put(key, data, actual, len(data))

    def stat(self, key: str) -> ObjectStat:
        head = self._call(key, self.client.head_object, Bucket=self.bucket, Key=check_key(key))
        etag = head.get("Metadata", {}).get("sha256") or head["ETag"].strip('"')
        return ObjectStat(
            key=key, size_bytes=int(head["ContentLength"]), etag=etag, mtime=head["LastModified"]
        )

    def open_range(self, key: str, start: int = 0, end: int | None = None) -> Iterator[bytes]:
        size = self.stat(key).size_bytes
        stop = check_range(start, end, size, key)
        if stop == start:
            return iter(())
        obj = self._call(
            key,
            self.client.get_object,
            Bucket=self.bucket,
            Key=key,
            Range=f"bytes={start}-{stop - 1}",
        )
        return _iter_body(obj["Body"], key)

    def delete(self, key: str) -> None:
        self._call(key, self.client.delete_object, Bucket=self.bucket, Key=check_key(key))

    def list(self, prefix: str = "") -> list[str]:
        keys: list[str] = []
        paginator = self.client.get_paginator("list_objects_v2")
        pages = self._call(
            None, lambda: list(paginator.paginate(Bucket=self.bucket, Prefix=prefix))
        )
        for page in pages:
            keys.extend(item["Key"] for item in page.get("Contents", []))
        return sorted(keys)


def _iter_body(body: Any, key: str) -> Iterator[bytes]:
    from botocore.exceptions import BotoCoreError

    try:
        yield from body.iter_chunks(COPY_CHUNK_BYTES)
    except BotoCoreError as exc:
        raise StorageError(f"object storage read failed: {exc}", key=key) from exc
    finally:
        body.close()


def storage_from_settings(settings: Any) -> Storage:
    """The storage the settings name (``storage_backend``: local or s3); workers use it too."""
    if settings.storage_backend == "s3":
        secret = settings.s3_secret_access_key
        return S3Storage(
            bucket=settings.s3_bucket,
            endpoint_url=settings.s3_endpoint_url,
            access_key_id=settings.s3_access_key_id,
            secret_access_key=secret.get_secret_value() if secret else None,
            region=settings.s3_region,
        )
    return LocalStorage(settings.resolved_storage_dir)
