"""`S3Storage`: objects in an S3-compatible bucket, checksummed by the server before they appear."""

from __future__ import annotations

import base64
import hashlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from backend.storage.base import (
    COPY_CHUNK_BYTES,
    ObjectNotFound,
    ObjectStat,
    Storage,
    StorageError,
    _hash_stream,
    _verify,
    check_key,
    check_range,
)


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
        return self._stat_of_full_object(key, size_bytes)

    def _stat_of_full_object(self, key: str, size_bytes: int) -> ObjectStat:
        """The stored object's stat; an object shorter or longer than sent is deleted."""
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
        return self._stat_of_full_object(key, size_bytes)

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
