"""Resumable bundle uploads (protocol: docs/uploads.md).

``POST /uploads`` → ``PUT /uploads/{id}/chunks?offset=N`` (raw body, any order, repeatable)
→ ``POST /uploads/{id}/complete {sha256}`` → 201 ``{scan, job}`` (200 when the manifest's
``scan.id`` was uploaded before). ``GET /uploads/{id}`` says what is still missing;
``DELETE /uploads/{id}`` abandons an open upload. Staff of the tablet's institution and
admins only.
"""

from __future__ import annotations

import os
from pathlib import Path as FsPath
from typing import Annotated

from fastapi import APIRouter, Depends, Path, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, Field
from starlette.requests import ClientDisconnect

from backend import uploads
from backend.api.deps import CurrentUser, SessionDep, SettingsDep
from backend.api.jobs import DispatcherDep, JobOut, send
from backend.api.models import StorageDep, StorageErrorRoute, check_tablet_access
from backend.api.scans import ScanOut
from backend.errors import ApiError, not_found
from backend.storage import storage_error_from_os
from backend.tables import Tablet, Upload, UploadState

WRITE_BUFFER_BYTES = 4 << 20
UUID_PATTERN = r"^[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}$"
SHA256_PATTERN = r"^[0-9a-fA-F]{64}$"


class UploadCreate(BaseModel):
    tablet_id: int = Field(ge=1)
    filename: str = Field(min_length=1, max_length=255, pattern=r"^[^/\\\x00]+\.[zZ][iI][pP]$")
    size_bytes: int = Field(gt=0)


class UploadComplete(BaseModel):
    sha256: str = Field(pattern=SHA256_PATTERN, description="SHA-256 (hex) of the whole file")


class UploadOut(BaseModel):
    id: str
    tablet_id: int
    filename: str
    size_bytes: int
    received_bytes: int
    ranges: list[list[int]]
    missing: list[list[int]]
    chunk_size: int
    state: str

    @classmethod
    def of(cls, upload: Upload, *, chunk_size: int) -> UploadOut:
        ranges = upload.ranges or []
        done = upload.state != UploadState.open
        return cls(
            id=upload.id,
            tablet_id=upload.tablet_id,
            filename=upload.filename,
            size_bytes=upload.size_bytes,
            received_bytes=upload.size_bytes
            if upload.state == UploadState.complete
            else uploads.received_bytes(ranges),
            ranges=[[0, upload.size_bytes]] if upload.state == UploadState.complete else ranges,
            missing=[] if done else uploads.missing_ranges(ranges, upload.size_bytes),
            chunk_size=chunk_size,
            state=upload.state.value,
        )


class CompletionOut(BaseModel):
    scan: ScanOut
    job: JobOut


def uploads_dir(settings) -> FsPath:
    return FsPath(settings.data_dir) / "uploads"


router = APIRouter(prefix="/uploads", tags=["uploads"], route_class=StorageErrorRoute)

UploadId = Annotated[str, Path(pattern=UUID_PATTERN, description="the id POST /uploads gave")]


def get_own_upload(upload_id: UploadId, session: SessionDep, user: CurrentUser) -> Upload:
    upload = session.get(Upload, upload_id)
    if upload is None:
        raise not_found(f"upload {upload_id}", where="upload_id")
    check_tablet_access(
        session, user, upload.tablet_id, what=f"upload {upload_id}", where="upload_id", edit=True
    )
    return upload


OwnUpload = Annotated[Upload, Depends(get_own_upload)]


@router.post("", response_model=UploadOut, status_code=201)
def create_upload(
    body: UploadCreate, session: SessionDep, user: CurrentUser, settings: SettingsDep
):
    """Start an upload. Nothing is reserved: 413 over the per-upload maximum or the
    institution's quota, 507 when the disk could not hold it; chunks are checked again."""
    tablet = check_tablet_access(
        session,
        user,
        body.tablet_id,
        what=f"tablet {body.tablet_id}",
        where="tablet_id",
        edit=True,
    )
    upload = uploads.create_upload(
        session,
        tablet=tablet,
        user=user,
        filename=body.filename,
        size_bytes=body.size_bytes,
        uploads_dir=uploads_dir(settings),
        limits=uploads.UploadLimits.of(settings),
    )
    return UploadOut.of(upload, chunk_size=settings.upload_chunk_size_bytes)


@router.get("/{upload_id}", response_model=UploadOut)
def read_upload(upload: OwnUpload, settings: SettingsDep):
    return UploadOut.of(upload, chunk_size=settings.upload_chunk_size_bytes)


@router.delete("/{upload_id}", status_code=204)
def abandon_upload(upload: OwnUpload, session: SessionDep, settings: SettingsDep) -> Response:
    """Drop an open (or refused) upload and its bytes; a complete one is its scan's now."""
    if upload.state == UploadState.complete:
        raise ApiError(409, f"upload {upload.id} is complete", where="upload_id")
    uploads.part_path(uploads_dir(settings), upload.id).unlink(missing_ok=True)
    session.delete(upload)
    return Response(status_code=204)


def _open_part(path: FsPath) -> int:
    try:
        return os.open(path, os.O_WRONLY)
    except FileNotFoundError:
        raise ApiError(409, "the upload's bytes are gone; create a new upload") from None
    except OSError as exc:
        raise storage_error_from_os(exc, None) from exc


def _pwrite_all(fd: int, data: bytes, offset: int) -> None:
    try:
        view = memoryview(data)
        while view:
            n = os.pwrite(fd, view, offset)
            view, offset = view[n:], offset + n
    except OSError as exc:
        raise storage_error_from_os(exc, None) from exc


def _fsync(fd: int) -> None:
    try:
        os.fsync(fd)
    except OSError as exc:
        raise storage_error_from_os(exc, None) from exc


@router.put(
    "/{upload_id}/chunks",
    response_model=UploadOut,
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {"application/octet-stream": {"schema": {"type": "string"}}},
        }
    },
)
async def put_chunk(
    request: Request,
    upload: OwnUpload,
    session: SessionDep,
    settings: SettingsDep,
    offset: Annotated[int, Query(ge=0, description="byte offset of the body in the file")],
):
    """Write the raw body at ``offset``; idempotent, any order. Returns the upload's state.

    Bytes are written as they arrive; the institution's quota (413) and the free-disk
    margin (507) are checked before each write, counting only bytes not received before.
    What was written before a refusal or a disconnect is kept and recorded.
    """
    if upload.state != UploadState.open:
        raise ApiError(409, f"upload {upload.id} is {upload.state.value}", where="upload_id")
    size = upload.size_bytes
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and offset + int(declared) > size:
        raise _past_end(offset, int(declared), size)
    limits = uploads.UploadLimits.of(settings)
    budget = await run_in_threadpool(_budget_of_upload, session, upload, limits)
    known = [list(r) for r in upload.ranges or []]
    if declared is not None and declared.isdigit():
        refusal = budget.refusal(
            uploads.new_bytes(known, offset, offset + int(declared)), where="offset"
        )
        if refusal is not None:
            raise refusal
    # The checks are done: end the read transaction before a long body transfer.
    await run_in_threadpool(session.commit)
    directory = uploads_dir(settings)
    path = uploads.part_path(directory, upload.id)
    fd = await run_in_threadpool(_open_part, path)
    pos, buffer, disconnected, refusal = offset, bytearray(), False, None

    async def flush() -> None:
        nonlocal pos, refusal
        refusal = budget.refusal(
            uploads.new_bytes(known, offset, pos + len(buffer)), where="offset"
        )
        if refusal is not None:  # write what still fits, then stop
            del buffer[budget.fitting_prefix(known, offset, pos, len(buffer)) :]
        if buffer:
            try:
                await run_in_threadpool(
                    uploads.check_free_disk,
                    directory,
                    len(buffer),
                    min_free_bytes=limits.min_free_bytes,
                )
            except ApiError as exc:
                refusal = exc
                buffer.clear()
        if buffer:
            await run_in_threadpool(_pwrite_all, fd, bytes(buffer), pos)
            pos += len(buffer)
        buffer.clear()

    try:
        try:
            async for piece in request.stream():
                if pos + len(buffer) + len(piece) > size:
                    raise _past_end(offset, pos + len(buffer) + len(piece) - offset, size)
                buffer += piece
                if len(buffer) >= WRITE_BUFFER_BYTES:
                    await flush()
                    if refusal is not None:
                        break  # a client lying about its size is cut off here
        except ClientDisconnect:
            disconnected = True  # keep what arrived: the client resends only the rest
        if buffer and refusal is None:
            await flush()
        await run_in_threadpool(_fsync, fd)
    finally:
        os.close(fd)
    if pos > offset:
        upload = await run_in_threadpool(
            uploads.record_range,
            request.app.state.sessionmaker,
            upload_id=upload.id,
            start=offset,
            end=pos,
        )
    if refusal is not None:
        raise refusal
    if disconnected:
        return Response(status_code=400)
    return UploadOut.of(upload, chunk_size=settings.upload_chunk_size_bytes)


def _budget_of_upload(session, upload: Upload, limits: uploads.UploadLimits) -> uploads.Budget:
    tablet = session.get(Tablet, upload.tablet_id)
    if tablet is None:  # deleted with its uploads (ON DELETE CASCADE) meanwhile
        raise not_found(f"upload {upload.id}", where="upload_id")
    return uploads.budget_of(session, tablet=tablet, limits=limits)


def _past_end(offset: int, length: int, size: int) -> ApiError:
    return ApiError(
        422,
        f"a chunk of {length} bytes at offset {offset} runs past the upload's {size} bytes",
        where="offset",
    )


@router.post(
    "/{upload_id}/complete",
    response_model=CompletionOut,
    status_code=201,
    responses={200: {"description": "the same scan (scan.id) was uploaded before"}},
)
def complete(
    body: UploadComplete,
    upload: OwnUpload,
    session: SessionDep,
    user: CurrentUser,
    settings: SettingsDep,
    storage: StorageDep,
    dispatcher: DispatcherDep,
    response: Response,
):
    """Check the SHA-256, validate the bundle (422 lists every problem), make scan + job."""
    done = uploads.complete_upload(
        session,
        upload=upload,
        sha256=body.sha256,
        uploads_dir=uploads_dir(settings),
        storage=storage,
        user=user,
        api_prefix=settings.api_prefix,
    )
    job = done.job
    if done.created:
        job = send(session, job, dispatcher)
    else:
        response.status_code = 200
    return CompletionOut(
        scan=ScanOut.of(session, done.scan, api_prefix=settings.api_prefix), job=JobOut.of(job)
    )
