"""Model versions and their files: ``GET /models/{id}`` and ``GET /models/{id}/assets/{name}``.

Asset URLs are stable per model version (a model id is one version, never overwritten), so
responses carry a strong ETag (the file's SHA-256) and ``Cache-Control: immutable``; they
answer ``If-None-Match`` with 304 and a single HTTP ``Range`` with 206 (unsatisfiable: 416).
Private tablets' models are served only to those who may read the tablet (else 404).

Also home of what the other routers of this family share: the storage dependency, the route
class that turns :class:`StorageError` into ``{detail, where}`` JSON (507/503), and the
access check for records reached through a tablet.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections import OrderedDict
from datetime import UTC, datetime
from email.utils import format_datetime, parsedate_to_datetime
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request, Response
from fastapi.responses import JSONResponse, RedirectResponse, StreamingResponse
from fastapi.routing import APIRoute
from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy.orm import Session

from backend import crud, jobs, licences
from backend.api.deps import OptionalUser, RowId, SessionDep, SettingsDep
from backend.errors import error_body, forbidden, not_found, unauthorized
from backend.schemas import LicenceFields
from backend.storage import Storage, StorageError, storage_from_settings
from backend.tables import Model, Scan, Tablet, User

CONTENT_TYPES = {
    ".glb": "model/gltf-binary",
    ".gltf": "model/gltf+json",
    ".ply": "application/ply",
    ".png": "image/png",
    ".pdf": "application/pdf",
    ".jpg": "image/jpeg",
    ".json": "application/json",
    ".npy": "application/octet-stream",
}
ONE_YEAR_S = 365 * 24 * 3600


class StorageErrorRoute(APIRoute):
    """Answers a :class:`StorageError` as JSON with its status (507 full, 503 unavailable)."""

    def get_route_handler(self):
        handler = super().get_route_handler()

        async def handle(request: Request) -> Response:
            try:
                return await handler(request)
            except StorageError as exc:
                headers = {"Retry-After": "30"} if exc.status_code == 503 else None
                return JSONResponse(
                    error_body(exc.message, "storage"), status_code=exc.status_code, headers=headers
                )

        return handle


def get_storage(request: Request) -> Storage:
    """The app's storage (``app.state.storage``; made from settings on first use)."""
    store = getattr(request.app.state, "storage", None)
    if store is None:
        store = storage_from_settings(request.app.state.settings)
        request.app.state.storage = store
    return store


StorageDep = Annotated[Storage, Depends(get_storage)]


def check_tablet_access(
    session: Session, user: User | None, tablet_id: int, *, what: str, where: str, edit: bool
) -> Tablet:
    """The tablet of a scan/job/model/upload, or 404 (not visible) / 401 / 403 (not editable)."""
    tablet = session.get(Tablet, tablet_id)
    if tablet is None or not crud.can_read_tablet(user, tablet):
        raise not_found(what, where=where)
    if edit:
        if user is None:
            raise unauthorized()
        if not crud.can_edit_tablet(user, tablet):
            raise forbidden(f"{what} belongs to another institution's tablet", where=where)
    return tablet


class ModelOut(BaseModel):
    id: int
    scan_id: int | None
    tablet_id: int
    job_id: int
    version: int
    created_at: datetime
    report: dict[str, Any]
    assets: dict[str, str]
    simulated: bool  # made from simulated scans (its report says so)
    licence: str | None = Field(
        default=None, description="the model's own licence (null: the tablet's)"
    )
    attribution: str | None = None
    effective_licence: str | None = Field(
        default=None,
        description="the licence that applies: the model's, else the tablet's or institution's",
    )
    effective_attribution: str | None = None

    @classmethod
    def of(cls, model: Model, *, api_prefix: str) -> ModelOut:
        base = f"{api_prefix}/models/{model.id}/assets"
        applies = licences.effective(model.tablet, model)
        return cls(
            id=model.id,
            scan_id=model.scan_id,
            tablet_id=model.tablet_id,
            job_id=model.job_id,
            version=model.version,
            created_at=model.created_at,
            report=model.report or {},
            assets={name: f"{base}/{name}" for name in sorted(model.assets or {})},
            simulated=model_is_simulated(model),
            licence=model.licence,
            attribution=model.attribution,
            effective_licence=applies.licence,
            effective_attribution=applies.attribution,
        )


def model_is_simulated(model: Model) -> bool:
    """Made from simulated scans: its report says so (a whole tablet) or its scan's free
    metadata does (``scan.tablet.simulated``, SCAN_BUNDLE.md)."""
    from worker.bundle import is_simulated  # as backend.uploads: loaded on first use

    report = model.report or {}
    scan = report.get("scan") if isinstance(report.get("scan"), dict) else {}
    return report.get("simulated") is True or is_simulated(scan.get("tablet"))


class ModelUpdate(LicenceFields):
    """The model's own licence and credit line (``null``: the tablet's apply)."""

    model_config = ConfigDict(extra="forbid")


router = APIRouter(prefix="/models", tags=["models"], route_class=StorageErrorRoute)


def get_readable_model(model_id: RowId, session: SessionDep, user: OptionalUser) -> Model:
    model = session.get(Model, model_id)
    if model is None:
        raise not_found(f"model {model_id}", where="model_id")
    tablet = check_tablet_access(
        session, user, model.tablet_id, what=f"model {model_id}", where="model_id", edit=False
    )
    model.is_public = tablet.is_public  # type: ignore[attr-defined]  # for Cache-Control
    return model


ReadableModel = Annotated[Model, Depends(get_readable_model)]


@router.get("", response_model=list[ModelOut])
def list_tablet_models(
    tablet_id: RowId,
    session: SessionDep,
    user: OptionalUser,
    settings: SettingsDep,
) -> list[ModelOut]:
    """The tablet-level models of a tablet (registration of all its scans: whole-tablet GLB,
    merged surface, fatcross plates), oldest version first; 404 if the tablet is not visible."""
    check_tablet_access(
        session, user, tablet_id, what=f"tablet {tablet_id}", where="tablet_id", edit=False
    )
    from sqlalchemy import select

    rows = session.scalars(
        select(Model)
        .where(Model.tablet_id == tablet_id, Model.scan_id.is_(None))
        .order_by(Model.version)
    )
    return [ModelOut.of(m, api_prefix=settings.api_prefix) for m in rows]


@router.get("/{model_id}", response_model=ModelOut)
def read_model(model: ReadableModel, settings: SettingsDep) -> ModelOut:
    return ModelOut.of(model, api_prefix=settings.api_prefix)


@router.patch("/{model_id}", response_model=ModelOut)
def update_model(
    model_id: RowId,
    body: ModelUpdate,
    session: SessionDep,
    settings: SettingsDep,
    user: OptionalUser,
) -> ModelOut:
    """Set the model's licence URI and attribution: staff of the holding institution, admins.

    A model made elsewhere may carry its maker's licence and credit; manifests, exports and
    citations then show them for this model (backend.licences.effective)."""
    model = session.get(Model, model_id)
    if model is None:
        raise not_found(f"model {model_id}", where="model_id")
    check_tablet_access(
        session, user, model.tablet_id, what=f"model {model_id}", where="model_id", edit=True
    )
    for name, value in body.model_dump(exclude_unset=True).items():
        setattr(model, name, value)
    session.flush()
    return ModelOut.of(model, api_prefix=settings.api_prefix)


# RFC 9110 14.1: the range unit is compared case-insensitively ("Bytes=0-9" is a range).
_RANGE = re.compile(r"^bytes=([0-9]*)-([0-9]*)$", re.IGNORECASE)


def parse_range(header: str, size_bytes: int) -> tuple[int, int] | None:
    """One ``bytes=`` range → half-open ``(start, end)``; None: ignore the header (serve all).

    Raises ValueError when the range cannot be satisfied (416).
    """
    match = _RANGE.match(header.strip().replace(" ", ""))
    if match is None:
        return None  # several ranges or another unit: RFC 9110 lets us send the whole file
    first, last = match.groups()
    if not first and not last:
        return None
    if not first:  # suffix: the last N bytes
        n = int(last)
        if n == 0 or size_bytes == 0:
            raise ValueError("empty suffix range")
        return max(0, size_bytes - n), size_bytes
    start = int(first)
    end = size_bytes if not last else min(int(last) + 1, size_bytes)
    if last and int(last) < start:
        return None  # syntactically invalid: ignored
    if start >= size_bytes:
        raise ValueError("range starts past the end")
    return start, end


def _etag_matches(header: str, etag: str) -> bool:
    if header.strip() == "*":
        return True
    # Weak comparison (RFC 9110 13.1.2): W/"x" matches "x".
    tags = [t.strip().removeprefix("W/") for t in header.split(",")]
    return etag in tags


@router.get("/{model_id}/assets/{name:path}")
def read_asset(
    name: str, model: ReadableModel, request: Request, storage: StorageDep, settings: SettingsDep
) -> Response:
    """A file of the model version, with caching and Range support."""
    return _serve_asset(name, model, request, storage, settings)


@router.head("/{model_id}/assets/{name:path}")
def head_asset(
    name: str, model: ReadableModel, request: Request, storage: StorageDep, settings: SettingsDep
) -> Response:
    """The headers of ``GET`` without the body."""
    return _serve_asset(name, model, request, storage, settings)


def _files_index(storage: Storage, key: str, sha256: str) -> dict[str, Any]:
    """The parsed tiles/files.json at ``key`` (content ``sha256``), cached per process:
    a model version's files never change, so (key, sha256) names one content forever."""
    cached = _FILES_CACHE.get((key, sha256))
    if cached is not None:
        _FILES_CACHE.move_to_end((key, sha256))
        return cached
    try:
        files = json.loads(b"".join(storage.open_range(key, 0, None)))
    except ValueError:
        files = {}
    if not isinstance(files, dict):
        files = {}
    _FILES_CACHE[(key, sha256)] = files
    while len(_FILES_CACHE) > FILES_CACHE_SIZE:
        _FILES_CACHE.popitem(last=False)
    return files


FILES_CACHE_SIZE = 64
_FILES_CACHE: OrderedDict[tuple[str, str], dict[str, Any]] = OrderedDict()


def asset_info(model: Model, name: str, storage: Storage) -> dict[str, Any] | None:
    """{size_bytes, sha256} of the model's file ``name``, or None. Files inside a tiles/
    folder are looked up in that folder's files.json (``backend.jobs.recorded_assets``):
    only names listed there (written by the worker) can be served, so no name reaches
    outside the model's own files."""
    assets = model.assets or {}
    info = assets.get(name)
    if info is not None:
        return info
    part = jobs.tiles_part(name)
    if not part:
        return None
    files_name = name[: len(name) - len(part)] + "files.json"
    files_info = assets.get(files_name)
    if files_info is None:
        return None
    files = _files_index(storage, f"{model.storage_prefix}/{files_name}", str(files_info["sha256"]))
    entry = files.get(part)
    if not isinstance(entry, dict) or "size_bytes" not in entry or "sha256" not in entry:
        return None
    return entry


_IIIF_LAYER = re.compile(r"^(?:.+/)?tiles/(?:.+/)?iiif/[^/]+$")
_IIIF_INFO = re.compile(r"^(?:.+/)?tiles/(?:.+/)?iiif/[^/]+/info\.json$")


def _iiif_info_body(
    name: str, model: Model, storage: Storage, settings: Any, info: dict
) -> bytes | None:
    """An IIIF info.json with its ``id`` set to the layer's public URL (from
    HAMMURABI_PUBLIC_URL, never the Host header: the worker writes a placeholder)."""
    if not _IIIF_INFO.match(name):
        return None
    raw = b"".join(storage.open_range(f"{model.storage_prefix}/{name}", 0, None))
    try:
        doc = json.loads(raw)
    except ValueError:
        return None
    if not isinstance(doc, dict):
        return None
    base = f"{settings.resolved_public_url}{settings.api_prefix}/models/{model.id}/assets"
    doc["id"] = f"{base}/{name.rsplit('/', 1)[0]}"
    return json.dumps(doc, indent=1).encode()


def _serve_asset(
    name: str, model: Model, request: Request, storage: Storage, settings: Any
) -> Response:
    info = asset_info(model, name, storage)
    if info is None:
        if _IIIF_LAYER.match(name) and asset_info(model, f"{name}/info.json", storage):
            # IIIF Image API 3.0 §2.2: the service's base URI redirects to its info.json.
            base = f"{settings.resolved_public_url}{settings.api_prefix}"
            return RedirectResponse(
                f"{base}/models/{model.id}/assets/{name}/info.json", status_code=303
            )
        raise not_found(f"asset {name!r} of model {model.id}", where="name")
    size = int(info["size_bytes"])
    etag = f'"{info["sha256"]}"'
    body_bytes = _iiif_info_body(name, model, storage, settings, info)
    if body_bytes is not None:
        size = len(body_bytes)
        etag = f'"{hashlib.sha256(body_bytes).hexdigest()}"'
    last_modified = model.created_at
    if last_modified.tzinfo is None:
        last_modified = last_modified.replace(tzinfo=UTC)
    visibility = "public" if getattr(model, "is_public", False) else "private"
    headers = {
        "ETag": etag,
        "Last-Modified": format_datetime(last_modified.astimezone(UTC), usegmt=True),
        "Cache-Control": f"{visibility}, max-age={ONE_YEAR_S}, immutable",
        "Accept-Ranges": "bytes",
    }
    if body_bytes is not None:
        # The id follows the configured public URL, which may change: revalidate.
        headers["Cache-Control"] = f"{visibility}, no-cache"
        headers["Access-Control-Allow-Origin"] = "*"  # IIIF viewers on other origins
    if _not_modified(request, etag, last_modified):
        return Response(status_code=304, headers=headers)
    media_type = CONTENT_TYPES.get(
        "." + name.rsplit(".", 1)[-1].lower(), "application/octet-stream"
    )
    headers["Content-Disposition"] = f'inline; filename="{name.rsplit("/", 1)[-1]}"'
    start, end, status = 0, size, 200
    range_header = request.headers.get("range")
    if_range = request.headers.get("if-range")
    if range_header and (if_range is None or if_range.strip() == etag):
        try:
            parsed = parse_range(range_header, size)
        except ValueError:
            return JSONResponse(
                error_body(
                    f"range {range_header!r} is outside the {size} bytes of {name}", "range"
                ),
                status_code=416,
                headers={**headers, "Content-Range": f"bytes */{size}"},
            )
        if parsed is not None:
            start, end = parsed
            status = 206
            headers["Content-Range"] = f"bytes {start}-{end - 1}/{size}"
    headers["Content-Length"] = str(end - start)
    if request.method == "HEAD":
        return Response(status_code=status, headers=headers, media_type=media_type)
    if body_bytes is not None:
        return Response(
            body_bytes[start:end], status_code=status, headers=headers, media_type=media_type
        )
    body = storage.open_range(f"{model.storage_prefix}/{name}", start, end)
    return StreamingResponse(body, status_code=status, headers=headers, media_type=media_type)


def _not_modified(request: Request, etag: str, last_modified: datetime) -> bool:
    if_none_match = request.headers.get("if-none-match")
    if if_none_match is not None:
        return _etag_matches(if_none_match, etag)
    since = request.headers.get("if-modified-since")
    if since:
        try:
            when = parsedate_to_datetime(since)
        except (TypeError, ValueError):
            return False
        if when.tzinfo is None:
            when = when.replace(tzinfo=UTC)
        return last_modified.replace(microsecond=0) <= when
    return False


def models_of_scan(session: Session, scan: Scan) -> list[Model]:
    from sqlalchemy import select

    return list(
        session.scalars(select(Model).where(Model.scan_id == scan.id).order_by(Model.version))
    )
