"""Resumable uploads of scan bundles: the part file, the received ranges, limits, completion.

An upload is a DB row (``uploads``: size, received ``ranges``, state) plus a part file
``<data_dir>/uploads/<id>.part``. The part file starts empty and grows only as bytes arrive
(chunks are written at their offset, ``pwrite`` + fsync, into a sparse file): a declared
``size_bytes`` reserves nothing, so a client cannot fill the disk by announcing a huge file.
Only after a chunk is on disk is its range merged into the row, so after a crash of the
client or the server the row never claims bytes that are not on disk; the client asks
``GET /uploads/{id}`` what is missing and sends it again. Concurrent chunk requests merge
their ranges with optimistic locking (``uploads.revision``).

Limits (:class:`UploadLimits`, from the settings; docs/admin.md "Upload limits and quotas"):
a maximum ``size_bytes`` per upload, a quota per institution counted as the bytes of its
stored scans plus the bytes its open uploads have received, checked when an upload is
created and again as each chunk arrives, and a margin of free disk that no chunk may eat.

Completion checks the SHA-256, validates the bundle with :func:`worker.bundle.validate_bundle`
(every problem is reported), stores the ZIP in :mod:`backend.storage`, and creates the scan
and its job. Nothing is kept of a bundle that is refused. A manifest ``scan.id`` that names
an existing scan is idempotent only for the same bytes (same SHA-256, same tablet); anything
else is a 409 naming that scan, and the upload stays open with its bytes until the client
deletes it (or it expires).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import time
import uuid
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

from sqlalchemy import delete, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.orm.exc import StaleDataError

from backend import crud, jobs
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


def new_bytes(ranges: list[list[int]], start: int, end: int) -> int:
    """How many bytes of ``[start, end)`` are not in ``ranges`` yet (what a chunk adds)."""
    if not 0 <= start <= end:
        raise ValueError(f"range [{start}, {end}) must satisfy 0 <= start <= end")
    overlap = sum(max(0, min(hi, end) - max(lo, start)) for lo, hi in ranges)
    return end - start - overlap


# --- the part file ---------------------------------------------------------------------------


def part_path(uploads_dir: Path, upload_id: str) -> Path:
    return Path(uploads_dir) / f"{uuid.UUID(upload_id)}.part"


def create_part_file(path: Path) -> None:
    """Create the empty part file; it grows only as chunks arrive (nothing reserved)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as exc:
        raise storage_error_from_os(exc, None) from exc
    os.close(fd)


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(HASH_CHUNK_BYTES):
            digest.update(chunk)
    return digest.hexdigest()


# --- state in the database -------------------------------------------------------------------


@dataclass(frozen=True)
class UploadLimits:
    """What one upload and one institution may hold (settings ``upload_*``; 0: no quota)."""

    max_bytes: int
    quota_bytes: int
    min_free_bytes: int

    @classmethod
    def of(cls, settings) -> UploadLimits:
        return cls(
            max_bytes=settings.upload_max_bytes,
            quota_bytes=settings.upload_quota_bytes,
            min_free_bytes=settings.upload_min_free_bytes,
        )


def institution_usage_bytes(session: Session, *, institution_id: int) -> int:
    """Bytes an institution holds: its stored scans plus what its open uploads received.

    A declared ``size_bytes`` counts for nothing until the bytes arrive; an upload that is
    deleted or expires gives its bytes back.
    """
    stored = session.scalar(
        select(func.coalesce(func.sum(Scan.size_bytes), 0))
        .join(Tablet, Tablet.id == Scan.tablet_id)
        .where(Tablet.institution_id == institution_id)
    )
    receiving = session.scalars(
        select(Upload.ranges)
        .join(Tablet, Tablet.id == Upload.tablet_id)
        .where(Tablet.institution_id == institution_id, Upload.state == UploadState.open)
    )
    return int(stored or 0) + sum(received_bytes(r or []) for r in receiving)


@dataclass(frozen=True)
class Budget:
    """How many more bytes the institution of an upload may receive (None: no quota)."""

    institution: str | None
    used_bytes: int
    quota_bytes: int | None

    @property
    def remaining_bytes(self) -> int | None:
        if self.quota_bytes is None:
            return None
        return max(0, self.quota_bytes - self.used_bytes)

    def fitting_prefix(self, ranges: list[list[int]], start: int, pos: int, length: int) -> int:
        """The most bytes of ``[pos, pos + length)`` a chunk that began at ``start`` may write.

        Counts, like the quota, only bytes outside ``ranges``; a binary search, since the new
        bytes grow monotonically with the length.
        """
        if self.quota_bytes is None:
            return length
        lo, hi = 0, length
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if self.used_bytes + new_bytes(ranges, start, pos + mid) <= self.quota_bytes:
                lo = mid
            else:
                hi = mid - 1
        return lo

    def refusal(self, adding_bytes: int, *, where: str) -> ApiError | None:
        """A 413 naming used / quota when ``adding_bytes`` more would pass the quota."""
        if self.quota_bytes is None or self.used_bytes + adding_bytes <= self.quota_bytes:
            return None
        return ApiError(
            413,
            f"upload quota of {self.institution} exceeded: {self.used_bytes} of "
            f"{self.quota_bytes} bytes used (stored scans + open uploads), "
            f"{adding_bytes} more bytes would not fit; delete open uploads or ask an admin "
            "for a larger quota",
            where=where,
        )


def budget_of(session: Session, *, tablet: Tablet, limits: UploadLimits) -> Budget:
    """The quota budget of ``tablet``'s institution (records of no institution: no quota)."""
    if tablet.institution_id is None or limits.quota_bytes <= 0:
        return Budget(institution=None, used_bytes=0, quota_bytes=None)
    used = institution_usage_bytes(session, institution_id=tablet.institution_id)
    name = tablet.institution.name if tablet.institution is not None else None
    return Budget(
        institution=f"institution {name!r}" if name else f"institution {tablet.institution_id}",
        used_bytes=used,
        quota_bytes=limits.quota_bytes,
    )


def check_free_disk(directory: Path, adding_bytes: int, *, min_free_bytes: int) -> None:
    """507 when writing ``adding_bytes`` would leave less than ``min_free_bytes`` free."""
    try:
        free = shutil.disk_usage(directory).free
    except OSError as exc:
        raise storage_error_from_os(exc, None) from exc
    if free - adding_bytes < min_free_bytes:
        raise ApiError(
            507,
            f"the server's disk is nearly full ({free} bytes free, {adding_bytes} more asked, "
            f"{min_free_bytes} kept free): nothing more was written; try again later",
            where="storage",
        )


def create_upload(
    session: Session,
    *,
    tablet: Tablet,
    user: User,
    filename: str,
    size_bytes: int,
    uploads_dir: Path,
    limits: UploadLimits,
) -> Upload:
    """A new open upload with its (empty) part file; flushed, the caller commits.

    Refused up front (nothing created) when ``size_bytes`` is over the per-upload maximum
    (413), could not fit in the institution's quota (413) or on the disk (507); none of
    that reserves anything: the chunks are checked again as they arrive.
    """
    if size_bytes > limits.max_bytes:
        raise ApiError(
            413,
            f"size_bytes {size_bytes} exceeds the limit of {limits.max_bytes} bytes per upload",
            where="size_bytes",
        )
    refusal = budget_of(session, tablet=tablet, limits=limits).refusal(
        size_bytes, where="size_bytes"
    )
    if refusal is not None:
        raise refusal
    uploads_dir = Path(uploads_dir)
    try:
        uploads_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise storage_error_from_os(exc, None) from exc
    check_free_disk(uploads_dir, size_bytes, min_free_bytes=limits.min_free_bytes)
    upload_id = str(uuid.uuid4())
    path = part_path(uploads_dir, upload_id)
    create_part_file(path)
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
    api_prefix: str,
) -> Completion:
    """Check, validate and store the bundle; create scan + job. COMMITS (its own transaction).

    Raises ApiError: 409 (bytes missing, upload refused before, or a ``scan.id`` that is
    another scan: the upload stays open), 422 (checksum or bundle problems: nothing kept);
    StorageError (507/503) leaves the upload open to try again. ``api_prefix`` makes the
    URL named in a 409.
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
            api_prefix=api_prefix,
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
    api_prefix: str,
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
            return _same_scan(
                session, upload, path, existing, sha=actual, user=user, api_prefix=api_prefix
            )
    return _create_scan(
        session,
        upload,
        path,
        storage,
        user,
        sha=actual,
        scan_meta=scan_meta,
        api_prefix=api_prefix,
    )


def _existing(session: Session, upload: Upload) -> Completion:
    scan = session.scalar(select(Scan).where(Scan.bundle_key == upload.storage_key))
    job = latest_job(session, scan_id=scan.id) if scan is not None else None
    if scan is None or job is None:
        raise ApiError(409, f"upload {upload.id} is complete but its scan is gone")
    return Completion(scan=scan, job=job, created=False)


def _same_scan(
    session: Session,
    upload: Upload,
    path: Path,
    existing: Scan,
    *,
    sha: str,
    user: User,
    api_prefix: str,
) -> Completion:
    """The same bytes again: the existing scan (idempotent). Anything else: 409, bytes kept."""
    if existing.tablet_id != upload.tablet_id or existing.bundle_sha256 != sha:
        raise _scan_id_conflict(
            session, upload, existing, sha=sha, user=user, api_prefix=api_prefix
        )
    upload.state = UploadState.complete
    upload.sha256 = sha
    upload.storage_key = existing.bundle_key
    upload.ranges = []
    session.commit()
    path.unlink(missing_ok=True)
    return _existing(session, upload)


def _scan_id_conflict(
    session: Session, upload: Upload, existing: Scan, *, sha: str, user: User, api_prefix: str
) -> ApiError:
    """409 naming the scan that holds ``scan.id``, when the caller may see it.

    The upload stays open with its bytes (no silent loss): the client changes the bundle's
    ``scan.id`` and uploads again, or deletes this upload; an abandoned one expires.
    """
    session.rollback()  # nothing of this attempt is kept in the database
    tablet = session.get(Tablet, existing.tablet_id)
    keep = (
        f"this upload ({upload.id}) keeps its bytes: give the bundle a new scan.id and upload "
        f"it again, or DELETE {api_prefix}/uploads/{upload.id} to discard it"
    )
    if tablet is None or not crud.can_read_tablet(user, tablet):
        # The scan is on a record the caller may not see: say nothing about it.
        return ApiError(
            409, f"scan.id {existing.scan_uid!r} is already taken; {keep}", where="manifest.scan.id"
        )
    url = f"{api_prefix}/scans/{existing.id}"
    if existing.tablet_id != upload.tablet_id:
        why = f"is a scan of another tablet ({tablet.id})"
    else:
        why = f"was uploaded before with other content (sha256 {existing.bundle_sha256}, now {sha})"
    return ApiError(
        409,
        f"scan.id {existing.scan_uid!r} is already scan {existing.id} ({url}), which {why}; {keep}",
        where="manifest.scan.id",
    )


def _create_scan(
    session: Session,
    upload: Upload,
    path: Path,
    storage: Storage,
    user: User,
    *,
    sha: str,
    scan_meta,
    api_prefix: str,
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
        return _same_scan(
            session,
            session.get(Upload, upload_id),
            path,
            existing,
            sha=sha,
            user=user,
            api_prefix=api_prefix,
        )
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

    Deleting the row gives the upload's received bytes back to its institution's quota.
    Also removes part files that no upload row names and that are as old (a crash between
    creating the file and committing the row). Idempotent and safe beside chunks arriving
    and beside another sweep: each row is deleted by a conditional DELETE that re-checks
    state and age, and only the run that deleted it removes its file (on PostgreSQL a
    concurrent sweep waits for the row lock and then deletes nothing; SQLite serialises
    writers, so the later sweep fails with "database is locked"). Flushes; the caller
    commits. Returns how many uploads this call deleted.
    """
    if older_than.total_seconds() <= 0:
        raise ValueError(f"older_than must be positive, got {older_than}")
    cutoff = (now or datetime.now(UTC)) - older_than
    still_stale = (Upload.state != UploadState.complete, Upload.updated_at < cutoff)
    session.flush()
    candidates = session.scalars(select(Upload.id).where(*still_stale)).all()
    deleted = 0
    for upload_id in candidates:
        # A chunk recorded since the SELECT moved updated_at: the row is no longer stale.
        result = session.execute(
            delete(Upload)
            .where(Upload.id == upload_id, *still_stale)
            .execution_options(synchronize_session=False)
        )
        if result.rowcount == 1:
            deleted += 1
            part_path(uploads_dir, upload_id).unlink(missing_ok=True)
            loaded = session.identity_map.get(session.identity_key(Upload, upload_id))
            if loaded is not None:  # its row is gone: never flush it again
                session.expunge(loaded)
    uploads_dir = Path(uploads_dir)
    if uploads_dir.is_dir():
        known = set(session.scalars(select(Upload.id)))
        for part in uploads_dir.glob("*.part"):
            try:
                upload_id = str(uuid.UUID(part.stem))
                modified = datetime.fromtimestamp(part.stat().st_mtime, tz=UTC)
            except (ValueError, FileNotFoundError):
                continue  # not a part file of ours, or removed meanwhile
            if upload_id not in known and modified < cutoff:
                part.unlink(missing_ok=True)
    return deleted
