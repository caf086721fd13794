"""Resumable uploads of scan bundles: the part file, the received ranges, and completion.

An upload is a DB row (``uploads``: size, received ``ranges``, state) plus a part file
``<data_dir>/uploads/<id>.part`` preallocated to the full size. Chunks are written straight
into the part file at their offset (``pwrite`` + fsync) and only then is their range merged
into the row, so after a crash of the client or the server the row never claims bytes that
are not on disk; the client asks ``GET /uploads/{id}`` what is missing and sends it again.
Concurrent chunk requests merge their ranges with optimistic locking (``uploads.revision``).

Completion checks the SHA-256, validates the bundle with :func:`worker.bundle.validate_bundle`
(every problem is reported), stores the ZIP in :mod:`backend.storage`, and creates the scan
and its job. Nothing is kept of a bundle that is refused.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import time
import uuid
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.orm.exc import StaleDataError

from backend import jobs
from backend.errors import ApiError
from backend.storage import Storage, StorageError, storage_error_from_os
from backend.tables import Job, Scan, Tablet, Upload, UploadState, User

HASH_CHUNK_BYTES = 4 << 20
FACES = ("obverse", "reverse", "top", "bottom", "left", "right", "other")


# --- ranges: pure functions on sorted lists of half-open [start, end) ------------------------


def merge_range(ranges: list[list[int]], start: int, end: int) -> list[list[int]]:
    """``ranges`` (sorted, disjoint, non-adjacent) with ``[start, end)`` added; input unchanged."""
    if not 0 <= start <= end:
        raise ValueError(f"range [{start}, {end}) must satisfy 0 <= start <= end")
    if start == end:
        return [list(r) for r in ranges]
    out: list[list[int]] = []
    placed = False
    for lo, hi in ranges:
        if hi < start:
            out.append([lo, hi])
        elif lo > end:
            if not placed:
                out.append([start, end])
                placed = True
            out.append([lo, hi])
        else:  # overlapping or touching: absorb
            start, end = min(lo, start), max(hi, end)
    if not placed:
        out.append([start, end])
    return out


def missing_ranges(ranges: list[list[int]], size_bytes: int) -> list[list[int]]:
    """The gaps of ``ranges`` in ``[0, size_bytes)``."""
    gaps = []
    pos = 0
    for lo, hi in ranges:
        if lo > pos:
            gaps.append([pos, lo])
        pos = max(pos, hi)
    if pos < size_bytes:
        gaps.append([pos, size_bytes])
    return gaps


def received_bytes(ranges: list[list[int]]) -> int:
    return sum(hi - lo for lo, hi in ranges)


# --- the part file ---------------------------------------------------------------------------


def part_path(uploads_dir: Path, upload_id: str) -> Path:
    return Path(uploads_dir) / f"{uuid.UUID(upload_id)}.part"


def create_part_file(path: Path, size_bytes: int) -> None:
    """Preallocate ``size_bytes`` so a full disk is found now (507), not half way through."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as exc:
        raise storage_error_from_os(exc, None) from exc
    try:
        try:
            os.posix_fallocate(fd, 0, size_bytes)
        except OSError as exc:
            if exc.errno not in (95, 22):  # EOPNOTSUPP/EINVAL: filesystem cannot preallocate
                raise
            os.ftruncate(fd, size_bytes)
        os.fsync(fd)
    except OSError as exc:
        os.close(fd)
        path.unlink(missing_ok=True)
        raise storage_error_from_os(exc, None) from exc
    os.close(fd)


def write_at(path: Path, offset: int, data: bytes) -> None:
    """Write ``data`` at ``offset`` of the part file and make it durable."""
    try:
        fd = os.open(path, os.O_WRONLY)
    except FileNotFoundError:
        raise ApiError(409, "the upload's data is gone; create a new upload") from None
    except OSError as exc:
        raise storage_error_from_os(exc, None) from exc
    try:
        view = memoryview(data)
        while view:
            written = os.pwrite(fd, view, offset)
            view = view[written:]
            offset += written
        os.fsync(fd)
    except OSError as exc:
        raise storage_error_from_os(exc, None) from exc
    finally:
        os.close(fd)


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(HASH_CHUNK_BYTES):
            digest.update(chunk)
    return digest.hexdigest()


# --- state in the database -------------------------------------------------------------------


def create_upload(
    session: Session,
    *,
    tablet: Tablet,
    user: User,
    filename: str,
    size_bytes: int,
    uploads_dir: Path,
    max_bytes: int,
) -> Upload:
    """A new open upload with its preallocated part file (flushed; the caller commits)."""
    if size_bytes > max_bytes:
        raise ApiError(
            413,
            f"size_bytes {size_bytes} exceeds the limit of {max_bytes} bytes",
            where="size_bytes",
        )
    upload_id = str(uuid.uuid4())
    path = part_path(uploads_dir, upload_id)
    create_part_file(path, size_bytes)
    try:
        upload = Upload(
            id=upload_id,
            tablet_id=tablet.id,
            user_id=user.id,
            filename=filename,
            size_bytes=size_bytes,
            ranges=[],
            state=UploadState.open,
        )
        session.add(upload)
        session.flush()
    except BaseException:
        path.unlink(missing_ok=True)
        raise
    return upload


def record_range(factory: sessionmaker[Session], *, upload_id: str, start: int, end: int) -> Upload:
    """Merge ``[start, end)`` into the row in its own short transaction; retry on a race."""
    for attempt in range(20):
        session = factory()
        try:
            upload = session.get(Upload, upload_id)
            if upload is None:
                raise ApiError(404, f"upload {upload_id} not found", where="upload_id")
            upload.ranges = merge_range(upload.ranges or [], start, end)
            session.commit()
            return upload
        except StaleDataError:
            # Another chunk of this upload committed first: merge into its ranges instead.
            session.rollback()
            time.sleep(0.005 * (attempt + 1))
        finally:
            session.close()
    raise ApiError(503, "too many concurrent chunks for one upload; try again", where="offset")


@dataclass(frozen=True)
class Completion:
    scan: Scan
    job: Job
    created: bool  # False: the same scan was uploaded before (idempotent on scan.id)


def latest_job(session: Session, *, scan_id: int) -> Job | None:
    return session.scalars(
        select(Job).where(Job.scan_id == scan_id).order_by(Job.id.desc()).limit(1)
    ).first()


def _refuse(session: Session, upload: Upload, path: Path, error: ApiError) -> ApiError:
    """Nothing kept of a refused bundle: part file gone, upload marked failed (committed)."""
    path.unlink(missing_ok=True)
    upload.state = UploadState.failed
    upload.ranges = []
    session.commit()
    return error


def complete_upload(
    session: Session,
    *,
    upload: Upload,
    sha256: str,
    uploads_dir: Path,
    storage: Storage,
    user: User,
) -> Completion:
    """Check, validate and store the bundle; create scan + job. COMMITS (its own transaction).

    Raises ApiError: 409 (bytes missing, upload refused before), 422 (checksum or bundle
    problems: nothing kept); StorageError (507/503) leaves the upload open to try again.
    """
    upload_id = upload.id
    try:
        return _complete(
            session,
            upload=upload,
            sha256=sha256,
            uploads_dir=uploads_dir,
            storage=storage,
            user=user,
        )
    except (StaleDataError, FileNotFoundError):
        # A concurrent completion of this very upload won the race: answer with its result.
        session.rollback()
        upload = session.get(Upload, upload_id, populate_existing=True)
        if upload is not None and upload.state == UploadState.complete:
            return _existing(session, upload)
        raise ApiError(
            409, f"upload {upload_id} was completed or refused at the same time; see its state"
        ) from None


def _complete(
    session: Session,
    *,
    upload: Upload,
    sha256: str,
    uploads_dir: Path,
    storage: Storage,
    user: User,
) -> Completion:
    from worker.bundle import BundleError, open_bundle, validate_bundle

    if upload.state == UploadState.complete:
        return _existing(session, upload)
    if upload.state == UploadState.failed:
        raise ApiError(409, f"upload {upload.id} was refused; create a new upload")
    gaps = missing_ranges(upload.ranges or [], upload.size_bytes)
    if gaps:
        missing = upload.size_bytes - received_bytes(upload.ranges or [])
        raise ApiError(
            409,
            f"{missing} bytes are still missing (first gap: bytes {gaps[0][0]}-{gaps[0][1] - 1})",
            where="ranges",
        )
    path = part_path(uploads_dir, upload.id)
    actual = sha256_of(path)
    if actual != sha256.lower():
        raise _refuse(
            session,
            upload,
            path,
            ApiError(
                422,
                f"sha256 mismatch: the received bytes have sha256 {actual}, "
                f"the client sent {sha256.lower()}; nothing was kept",
                where="sha256",
            ),
        )
    problems = validate_bundle(path)
    if problems and not path.exists():
        raise FileNotFoundError(path)  # completed concurrently, which removed the part file
    if problems:
        shown = [
            {"where": p.where, "message": p.message.replace(str(path), upload.filename)}
            for p in problems
        ]
        error = ApiError(
            422,
            f"the bundle is invalid ({len(shown)} problem(s)); nothing was kept",
            where=shown[0]["where"],
            problems=shown,
        )
        raise _refuse(session, upload, path, error)
    try:
        with open_bundle(path) as bundle:
            scan_meta = bundle.manifest.scan
    except BundleError:
        if not path.exists():
            raise FileNotFoundError(path) from None
        raise
    if scan_meta.id:
        existing = session.scalar(select(Scan).where(Scan.scan_uid == scan_meta.id))
        if existing is not None:
            return _same_scan(session, upload, path, existing)
    return _create_scan(session, upload, path, storage, user, sha=actual, scan_meta=scan_meta)


def _existing(session: Session, upload: Upload) -> Completion:
    scan = session.scalar(select(Scan).where(Scan.bundle_key == upload.storage_key))
    job = latest_job(session, scan_id=scan.id) if scan is not None else None
    if scan is None or job is None:
        raise ApiError(409, f"upload {upload.id} is complete but its scan is gone")
    return Completion(scan=scan, job=job, created=False)


def _same_scan(session: Session, upload: Upload, path: Path, existing: Scan) -> Completion:
    if existing.tablet_id != upload.tablet_id:
        raise _refuse(
            session,
            upload,
            path,
            ApiError(
                409,
                f"scan.id {existing.scan_uid!r} is already a scan of another tablet; "
                "nothing was kept",
                where="manifest.scan.id",
            ),
        )
    upload.state = UploadState.complete
    upload.storage_key = existing.bundle_key
    upload.ranges = []
    session.commit()
    path.unlink(missing_ok=True)
    return _existing(session, upload)


def _create_scan(
    session: Session,
    upload: Upload,
    path: Path,
    storage: Storage,
    user: User,
    *,
    sha: str,
    scan_meta,
) -> Completion:
    upload_id = upload.id
    # A fresh key per attempt: a concurrent completion of the same upload never deletes
    # the object that the winning attempt committed.
    key = f"scans/{upload.tablet_id}/{upload.id}/{uuid.uuid4().hex[:12]}/bundle.zip"
    scan = Scan(
        tablet_id=upload.tablet_id,
        face=scan_meta.face,
        scan_uid=scan_meta.id,
        bundle_key=key,
        bundle_sha256=sha,
        size_bytes=upload.size_bytes,
        manifest={
            "scan": {
                "id": scan_meta.id,
                "face": scan_meta.face,
                "captured_at": scan_meta.captured_at,
                "tablet": dict(scan_meta.tablet),
            }
        },
        user_id=user.id,
    )
    session.add(scan)
    try:
        session.flush()
    except IntegrityError:
        # The same scan.id was completed concurrently: that scan wins, and this is it.
        session.rollback()
        existing = session.scalar(select(Scan).where(Scan.scan_uid == scan_meta.id))
        if existing is None:
            raise
        return _same_scan(session, session.get(Upload, upload_id), path, existing)
    try:
        storage.put_file(key, path, sha256=sha)
        job = jobs.create(session, scan=scan)
        upload.state = UploadState.complete
        upload.sha256 = sha
        upload.storage_key = key
        session.commit()
    except ValueError:
        session.rollback()
        if not path.exists():  # completed concurrently, which removed the part file
            raise FileNotFoundError(path) from None
        raise
    except StaleDataError:
        # The same upload was completed concurrently and that attempt committed first.
        session.rollback()
        with contextlib.suppress(StorageError):
            storage.delete(key)
        return _existing(session, session.get(Upload, upload_id))
    except BaseException:
        session.rollback()
        with contextlib.suppress(StorageError):
            storage.delete(key)
        raise
    path.unlink(missing_ok=True)
    return Completion(scan=scan, job=job, created=True)


def expire_uploads(
    session: Session, *, uploads_dir: Path, older_than: timedelta, now: datetime | None = None
) -> int:
    """Delete uploads left open (or refused) for ``older_than``, with their part files.

    Also removes part files that no upload row names (a crash between preallocating and
    committing). Flushes; the caller commits. Returns how many uploads were deleted.
    """
    if older_than.total_seconds() <= 0:
        raise ValueError(f"older_than must be positive, got {older_than}")
    cutoff = (now or datetime.now(UTC)) - older_than
    stale = session.scalars(
        select(Upload).where(Upload.state != UploadState.complete, Upload.updated_at < cutoff)
    ).all()
    for upload in stale:
        part_path(uploads_dir, upload.id).unlink(missing_ok=True)
        session.delete(upload)
    session.flush()
    uploads_dir = Path(uploads_dir)
    if uploads_dir.is_dir():
        known = set(session.scalars(select(Upload.id)))
        for part in uploads_dir.glob("*.part"):
            orphan = part.stem not in known
            if orphan and datetime.fromtimestamp(part.stat().st_mtime, tz=UTC) < cutoff:
                part.unlink(missing_ok=True)
    return len(stale)
