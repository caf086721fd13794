"""One storage interface for bundles, model directories and assets, with two backends.

``LocalStorage`` keeps objects as files under a directory (the default, under the data dir);
``S3Storage`` keeps them in an S3-compatible bucket (AWS, MinIO, …). Both take the same POSIX
keys (``scans/12/bundle.zip``), write atomically and verify a SHA-256 checksum of what they
write, and report failures as :class:`StorageError` carrying the HTTP status the API should
answer with (507 when the disk or quota is full, 503 when the store is unreachable, 404 for a
missing object), so a failed write never leaves half an object behind.
"""

from __future__ import annotations

from typing import Any

from backend.storage.base import (
    COPY_CHUNK_BYTES,
    ChecksumMismatch,
    ObjectNotFound,
    ObjectStat,
    Storage,
    StorageError,
    check_key,
    check_range,
    storage_error_from_os,
)
from backend.storage.local import LocalStorage
from backend.storage.s3 import S3Storage

__all__ = [
    "COPY_CHUNK_BYTES",
    "ChecksumMismatch",
    "LocalStorage",
    "ObjectNotFound",
    "ObjectStat",
    "S3Storage",
    "Storage",
    "StorageError",
    "check_key",
    "check_range",
    "storage_error_from_os",
    "storage_from_settings",
]


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
