"""Catalogue records: search (JSON, CSV, JSON-lines) and create/read/update/delete.

Stable URL of a record: ``/api/v1/tablets/{id}``, or ``/api/v1/tablets/{P-number}``.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterator
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool

from backend import crud
from backend.api.deps import (
    EditableTablet,
    OptionalUser,
    ReadableTablet,
    SessionDep,
    SettingsDep,
    StaffUser,
    require_institution,
)
from backend.csv_cells import safe_row
from backend.errors import ApiError, conflict, forbidden
from backend.schemas import FacetValue, SearchPage, TabletCreate, TabletOut, TabletUpdate
from backend.search import SORT_CHOICES, SearchQuery, page_key, search_tablets
from backend.tables import Role

router = APIRouter(prefix="/tablets", tags=["tablets"])

# Exports are read outside the library (spreadsheets, other archives): every URL absolute,
# from the configured public URL, with the CDLI link and the licence that applies.
CSV_COLUMNS = [
    *(name for name in TabletOut.model_fields if name != "extra"),
    "iiif_manifest",
]
EXPORT_MAX_ROWS = 200_000
_ACCEPT_FORMATS = {
    "text/csv": "csv",
    "application/x-ndjson": "jsonl",
    "application/jsonl": "jsonl",
    "application/jsonlines": "jsonl",
    "application/json": "json",
}

Filter = Annotated[list[str] | None, Query(max_length=50)]


def _wanted_format(request: Request, fmt: str | None) -> str:
    if fmt:
        return fmt
    for part in request.headers.get("accept", "").split(","):
        media = part.split(";")[0].strip().lower()
        if media in _ACCEPT_FORMATS:
            return _ACCEPT_FORMATS[media]
    return "json"


def _csv_lines(rows: list[dict]) -> Iterator[str]:
    # Cells are made spreadsheet-safe here only: JSON lines are read by programs, not
    # spreadsheets, and keep the values exactly as stored.
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=CSV_COLUMNS, extrasaction="ignore")
    writer.writeheader()
    for i, row in enumerate(rows, 1):
        writer.writerow(safe_row(row))
        if i % 500 == 0:
            yield buffer.getvalue()
            buffer.seek(0)
            buffer.truncate()
    yield buffer.getvalue()


def _jsonl_lines(rows: list[dict]) -> Iterator[str]:
    for row in rows:
        yield json.dumps(row, ensure_ascii=False, default=str) + "\n"


@router.get(
    "",
    response_model=SearchPage,
    responses={200: {"content": {"text/csv": {}, "application/x-ndjson": {}}}},
)
async def search(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    user: OptionalUser,
    q: Annotated[str | None, Query(max_length=500, description="words; prefixes match")] = None,
    period: Filter = None,
    provenience: Filter = None,
    genre: Filter = None,
    collection: Filter = None,
    language: Filter = None,
    has_3d: bool | None = None,
    sort: Annotated[
        str | None,
        Query(
            description=f"one of {', '.join(SORT_CHOICES)}",
            json_schema_extra={"enum": list(SORT_CHOICES)},  # documented as checked below
        ),
    ] = None,
    page: Annotated[int, Query(ge=1, le=100_000)] = 1,
    page_size: Annotated[int, Query(ge=1)] = 25,
    format: Annotated[
        Literal["json", "csv", "jsonl"] | None,
        Query(description="json (paged), csv or jsonl (every match); default from Accept"),
    ] = None,
):
    """Search the catalogue; CSV and JSON-lines export every match (page is ignored)."""
    if page_size > settings.search_max_page_size:
        raise ApiError(
            422,
            f"page_size: at most {settings.search_max_page_size}",
            where="query.page_size",
        )
    if sort is not None and sort not in SORT_CHOICES:
        raise ApiError(422, f"sort: must be one of {', '.join(SORT_CHOICES)}", where="query.sort")
    filters = {
        name: tuple(values)
        for name, values in {
            "period": period,
            "provenience": provenience,
            "genre": genre,
            "collection": collection,
            "language": language,
        }.items()
        if values
    }
    query = SearchQuery(
        q=q, filters=filters, has_3d=has_3d, sort=sort, page=page, page_size=page_size
    )
    fmt = _wanted_format(request, format)
    prefix = settings.api_prefix
    if fmt == "json":
        snapshot = request.app.state.facet_snapshot

        def render() -> bytes:
            result = search_tablets(
                session,
                query,
                user=user,
                facet_limit=settings.search_facet_limit,
                snapshot=snapshot,
            )
            body = SearchPage(
                items=[TabletOut.of(t, api_prefix=prefix) for t in result.items],
                total=result.total,
                page=page,
                page_size=page_size,
                facets={
                    name: [FacetValue(value=v, count=n) for v, n in values]
                    for name, values in result.facets.items()
                },
            )
            # Already validated: serialise once instead of letting response_model re-validate.
            return body.model_dump_json().encode()

        # Pages are cached per viewer scope and dropped when the catalogue changes. The
        # route is async so that a hit is served without a hop to the thread pool.
        key = page_key(query, settings.search_facet_limit, prefix)
        body = snapshot.peek_page(user, key)
        if body is None:
            body = await run_in_threadpool(snapshot.cached_page, session, user, key, render)
        return Response(body, media_type="application/json")
    absolute = f"{settings.resolved_public_url}{prefix}"
    return await run_in_threadpool(_export, session, query, user, fmt, absolute)


def export_row(tablet, absolute_prefix: str) -> dict:
    """One exported record: its fields, absolute URLs, CDLI link and licence."""
    row = TabletOut.of(tablet, api_prefix=absolute_prefix).model_dump(mode="json")
    row["iiif_manifest"] = (
        f"{absolute_prefix}/tablets/{tablet.id}/iiif/manifest.json" if tablet.has_3d else None
    )
    return row


def _export(session, query: SearchQuery, user, fmt: str, absolute_prefix: str) -> StreamingResponse:
    result = search_tablets(session, query, user=user, with_facets=False, paged=False)
    if result.total > EXPORT_MAX_ROWS:
        raise ApiError(
            422, f"too many matches to export ({result.total} > {EXPORT_MAX_ROWS})", where="query"
        )
    rows = [export_row(t, absolute_prefix) for t in result.items]
    headers = {"X-Total-Count": str(result.total)}
    if fmt == "csv":
        headers["Content-Disposition"] = 'attachment; filename="tablets.csv"'
        return StreamingResponse(
            _csv_lines(rows), media_type="text/csv; charset=utf-8", headers=headers
        )
    return StreamingResponse(_jsonl_lines(rows), media_type="application/x-ndjson", headers=headers)


@router.post("", response_model=TabletOut, status_code=201)
def create(body: TabletCreate, session: SessionDep, settings: SettingsDep, user: StaffUser):
    """A new record; staff create records of their own institution.

    A P-number is unique per institution (docs/api.md "P-numbers"): 409 only when the same
    institution already has it; another institution's records, private or public, never
    block it and are never revealed.
    """
    if user.role == Role.staff:
        if body.institution_id not in (None, user.institution_id):
            raise forbidden("staff create records of their own institution only", "institution_id")
        institution_id = user.institution_id
    else:
        institution_id = body.institution_id
        require_institution(session, institution_id)
    fields = body.model_dump(exclude={"institution_id"}, exclude_none=True)
    try:
        tablet = crud.create_tablet(session, fields=fields, institution_id=institution_id)
    except ValueError as exc:
        raise conflict(str(exc), where="p_number") from exc
    return TabletOut.of(tablet, api_prefix=settings.api_prefix)


@router.get("/{tablet_id}", response_model=TabletOut)
def read(tablet: ReadableTablet, settings: SettingsDep):
    return TabletOut.of(tablet, api_prefix=settings.api_prefix)


@router.patch("/{tablet_id}", response_model=TabletOut)
def update(
    body: TabletUpdate,
    tablet: EditableTablet,
    session: SessionDep,
    settings: SettingsDep,
    user: OptionalUser,
):
    """Change fields; fields left out stay as they are, ``null`` clears them."""
    changes = body.model_dump(exclude_unset=True)
    moves = "institution_id" in changes and changes["institution_id"] != tablet.institution_id
    if moves and (user is None or user.role != Role.admin):
        raise forbidden("only admins move a record to another institution", "institution_id")
    if moves:
        require_institution(session, changes["institution_id"])
    for required in ("designation", "is_public", "extra"):
        if required in changes and changes[required] is None:
            raise ApiError(422, f"{required}: must not be null", where=f"body.{required}")
    try:
        tablet = crud.update_tablet(session, tablet=tablet, changes=changes)
    except ValueError as exc:
        raise conflict(str(exc), where="p_number") from exc
    return TabletOut.of(tablet, api_prefix=settings.api_prefix)


@router.delete("/{tablet_id}", status_code=204)
def delete(tablet: EditableTablet, session: SessionDep) -> Response:
    crud.delete_tablet(session, tablet=tablet)
    return Response(status_code=204)
