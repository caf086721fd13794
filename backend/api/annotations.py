"""Annotations of signs (W3C Web Annotations) and the parsed transliteration (issue 20).

- ``GET /tablets/{id}/transliteration``: the record's ATF, parsed (backend.atf).
- ``GET /tablets/{id}/annotations?q=``: every annotation of every model version of the
  tablet (each says its model id and version), ``GET /models/{id}/annotations?q=``: one
  version's; both an ``AnnotationPage``. ``q`` matches reference, reading and comment.
- ``POST /models/{id}/annotations``, ``GET/PATCH/DELETE /annotations/{id}``.

Who may: read, whoever may read the tablet; create, any signed-in user who may read it (staff
and registered scholars); change or delete, the author, staff of the institution that holds
the tablet, and admins. Answers are JSON-LD (``application/ld+json; profile=...anno.jsonld``).
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response
from fastapi.responses import JSONResponse
from sqlalchemy import and_, func, or_, select
from sqlalchemy.orm import Session

from backend import atf, crud
from backend.annotations import ANNO_CONTEXT, MEDIA_TYPE, polygon_px_from_mm, web_annotation
from backend.api.deps import OptionalUser, ReadableTablet, RowId, SessionDep, SettingsDep
from backend.api.models import check_tablet_access
from backend.errors import ApiError, forbidden, not_found, unauthorized
from backend.iiif import WHOLE
from backend.schemas import (
    AnnotationIn,
    AnnotationPageOut,
    AnnotationUpdate,
    LineOut,
    SignOut,
    SurfaceOut,
    TransliterationOut,
    WebAnnotationOut,
)
from backend.tables import Annotation, Model, Role, Scan, Tablet, User


class AnnotationJSON(JSONResponse):
    """JSON-LD of the Web Annotation Data Model (its media type names the context)."""

    media_type = MEDIA_TYPE


router = APIRouter(tags=["annotations"])
Search = Annotated[
    str | None, Query(max_length=200, description="words in the reference, reading or comment")
]


# --- transliteration ---------------------------------------------------------------------------


@router.get("/tablets/{tablet_id}/transliteration", response_model=TransliterationOut)
def read_transliteration(tablet: ReadableTablet) -> TransliterationOut:
    """The record's ATF parsed into surfaces, lines and signs (404 when it has none)."""
    if not tablet.atf:
        raise not_found(f"a transliteration of tablet {tablet.id}", where="tablet_id")
    parsed = atf.parse_atf(tablet.atf)
    return TransliterationOut(
        tablet_id=tablet.id,
        surfaces=[
            SurfaceOut(
                surface=s.abbrev,
                name=s.name,
                lines=[
                    LineOut(
                        number=line.number,
                        text=line.text,
                        signs=[
                            SignOut(
                                index=sign.index,
                                text=sign.text,
                                reference=f"{s.abbrev} {line.number} {sign.index}",
                            )
                            for sign in line.signs
                        ],
                    )
                    for line in s.lines
                ],
            )
            for s in parsed.surfaces
        ],
        problems=parsed.problems,
    )


# --- JSON-LD of one annotation -----------------------------------------------------------------


def _face_of(session: Session, model: Model) -> str:
    if model.scan_id is None:
        return WHOLE
    scan = session.get(Scan, model.scan_id)
    return scan.face if scan is not None else WHOLE


def _image_name(model: Model, face: str, image_face: str | None) -> str | None:
    """The image whose grid ``polygon_px`` is on: the face model's albedo (or normal map), or
    the face's normal map inside a whole-tablet model."""
    assets = model.assets or {}
    if face != WHOLE:
        return next((n for n in ("albedo.png", "normals.png") if n in assets), None)
    if image_face:
        name = f"faces/{image_face}/normals.png"
        return name if name in assets else None
    return None


def _creator(settings, user: User | None) -> dict | None:
    if user is None:
        return None
    # No e-mail address: annotations of public tablets are read by anyone.
    where = f" ({user.institution.name})" if user.institution is not None else ""
    return {
        "id": f"{settings.resolved_public_url}{settings.api_prefix}/users/{user.id}",
        "type": "Person",
        "name": f"user {user.id}{where}",
    }


def to_json_ld(session: Session, settings, annotation: Annotation) -> dict:
    api = f"{settings.resolved_public_url}{settings.api_prefix}"
    model = annotation.model
    face = _face_of(session, model)
    ref = atf.parse_reference(annotation.reference)
    glb = "model.glb" if "model.glb" in (model.assets or {}) else None
    model_source = {
        "id": f"{api}/models/{model.id}/assets/{glb}" if glb else f"{api}/models/{model.id}",
        "type": "Model" if glb else "Dataset",
        "format": "model/gltf-binary" if glb else "application/json",
    }
    image = _image_name(model, face, annotation.image_face)
    image_source = (
        {"id": f"{api}/models/{model.id}/assets/{image}", "type": "Image", "format": "image/png"}
        if image
        else None
    )
    return web_annotation(
        annotation_id=f"{api}/annotations/{annotation.id}",
        reference=annotation.reference,
        reading=annotation.reading,
        comment=annotation.comment,
        polygon_mm=annotation.polygon_mm,
        polygon_px=annotation.polygon_px,
        model_source=model_source,
        image_source=image_source,
        creator=_creator(settings, annotation.creator),
        created=annotation.created_at,
        modified=annotation.updated_at,
        extra={
            "annotationId": annotation.id,
            "tabletId": annotation.tablet_id,
            "modelId": model.id,
            "modelVersion": model.version,
            "face": face,
            "reference": {
                "text": ref.text,
                "surface": ref.surface,
                "line": ref.line,
                "sign": ref.sign,
            },
            "reading": annotation.reading,
            "comment": annotation.comment,
            "polygonMm": annotation.polygon_mm,
            "polygonPx": annotation.polygon_px,
            "imageFace": annotation.image_face,
            "creatorId": annotation.creator_id,
        },
    )


def _page(session: Session, settings, page_id: str, rows: list[Annotation]) -> AnnotationJSON:
    items = [to_json_ld(session, settings, a) for a in rows]
    body = {
        "@context": ANNO_CONTEXT,
        "id": page_id,
        "type": "AnnotationPage",
        "startIndex": 0,
        "total": len(items),
        "items": items,
    }
    return AnnotationJSON(body)


def _escape(text: str) -> str:
    return text.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")


def _search(statement, q: str | None):
    """Every word of ``q`` in the reference, reading or comment (any case); a query shaped
    like the start of a reference ("r 1") matches references from their start instead."""
    words = (q or "").lower().split()
    if not words:
        return statement
    prefix = atf.reference_prefix(q or "")
    by_reference = None
    if prefix is not None:
        by_reference = or_(
            Annotation.reference == prefix,
            Annotation.reference.like(_escape(prefix) + " %", escape="\\"),
        )
        if len(words) > 1:  # "r 1": line 1 of the reverse, not any "r" and any "1"
            return statement.where(by_reference)
    by_words = and_(
        *(
            or_(
                func.lower(Annotation.reference).like(f"%{_escape(w)}%", escape="\\"),
                func.lower(func.coalesce(Annotation.reading, "")).like(
                    f"%{_escape(w)}%", escape="\\"
                ),
                func.lower(func.coalesce(Annotation.comment, "")).like(
                    f"%{_escape(w)}%", escape="\\"
                ),
            )
            for w in words
        )
    )
    # One word that is also a surface ("be" is a reading too): either.
    return statement.where(by_words if by_reference is None else or_(by_reference, by_words))


def _query_suffix(q: str | None) -> str:
    from urllib.parse import urlencode

    return f"?{urlencode({'q': q})}" if q else ""


# --- listing -------------------------------------------------------------------------------------


@router.get(
    "/tablets/{tablet_id}/annotations",
    response_model=AnnotationPageOut,
    response_class=AnnotationJSON,
)
def list_tablet_annotations(
    tablet: ReadableTablet, session: SessionDep, settings: SettingsDep, q: Search = None
):
    """Every annotation of the tablet's model versions, oldest first; each names its version."""
    rows = session.scalars(
        _search(select(Annotation).where(Annotation.tablet_id == tablet.id), q).order_by(
            Annotation.id
        )
    ).all()
    api = f"{settings.resolved_public_url}{settings.api_prefix}"
    return _page(
        session, settings, f"{api}/tablets/{tablet.id}/annotations{_query_suffix(q)}", list(rows)
    )


def _readable_model(session: Session, user: User | None, model_id: int) -> tuple[Model, Tablet]:
    model = session.get(Model, model_id)
    if model is None:
        raise not_found(f"model {model_id}", where="model_id")
    tablet = check_tablet_access(
        session, user, model.tablet_id, what=f"model {model_id}", where="model_id", edit=False
    )
    return model, tablet


@router.get(
    "/models/{model_id}/annotations",
    response_model=AnnotationPageOut,
    response_class=AnnotationJSON,
)
def list_model_annotations(
    model_id: RowId,
    session: SessionDep,
    settings: SettingsDep,
    user: OptionalUser,
    q: Search = None,
):
    """The annotations of one model version, oldest first."""
    model, _tablet = _readable_model(session, user, model_id)
    rows = session.scalars(
        _search(select(Annotation).where(Annotation.model_id == model.id), q).order_by(
            Annotation.id
        )
    ).all()
    api = f"{settings.resolved_public_url}{settings.api_prefix}"
    return _page(
        session, settings, f"{api}/models/{model.id}/annotations{_query_suffix(q)}", list(rows)
    )


# --- create, read, change, delete ----------------------------------------------------------------


def _grid(model: Model) -> tuple[int | None, int | None, float | None]:
    report = model.report if isinstance(model.report, dict) else {}
    size = report.get("image_size") if isinstance(report.get("image_size"), dict) else {}
    width, height = size.get("width"), size.get("height")
    pixel = report.get("pixel_size_um")
    ok = isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0
    pixel_ok = isinstance(pixel, int | float) and not isinstance(pixel, bool) and pixel > 0
    return (width if ok else None, height if ok else None, float(pixel) if pixel_ok else None)


def _check_reference(tablet: Tablet, reference: str) -> None:
    """A reference must name a sign of the transliteration, when the record has one."""
    if not tablet.atf:
        return
    try:
        atf.check_against(atf.parse_reference(reference), atf.parse_atf(tablet.atf))
    except atf.ReferenceError_ as exc:
        raise ApiError(422, f"reference {reference!r}: {exc}", where="body.reference") from exc


def _region(
    session: Session,
    model: Model,
    polygon_mm: list,
    polygon_px: list | None,
    image_face: str | None,
    *,
    px_given: bool,
) -> tuple[list | None, str | None]:
    """The image-grid polygon and its face, checked against the model (422 naming the field)."""
    face = _face_of(session, model)
    if face != WHOLE:
        if image_face not in (None, face):
            raise ApiError(
                422,
                f"image_face: this model is of the {face}; its image grid is the {face}'s",
                where="body.image_face",
            )
        image_face = face
        width, height, pixel_um = _grid(model)
        where = "body.polygon_px"
        if polygon_px is None and not px_given and pixel_um is not None:
            polygon_px, where = polygon_px_from_mm(polygon_mm, pixel_um), "body.polygon_mm"
        if polygon_px is not None and width is not None and height is not None:
            for i, (col, row) in enumerate(polygon_px):
                if not (-0.5 <= col <= width + 0.5 and -0.5 <= row <= height + 0.5):
                    raise ApiError(
                        422,
                        f"{where.split('.')[1]}: point {i} lies at column {col:g}, row {row:g}, "
                        f"outside the model's image grid ({width} × {height} px)",
                        where=where,
                    )
    elif polygon_px is not None and image_face is None:
        raise ApiError(
            422,
            "image_face: a whole-tablet model has one image grid per face; name the face "
            "polygon_px is on",
            where="body.image_face",
        )
    if polygon_px is not None and len(polygon_px) != len(polygon_mm):
        raise ApiError(
            422,
            f"polygon_px: {len(polygon_px)} points, but polygon_mm has {len(polygon_mm)}; "
            "they are the same points",
            where="body.polygon_px",
        )
    return polygon_px, image_face if polygon_px is not None else None


@router.post(
    "/models/{model_id}/annotations",
    response_model=WebAnnotationOut,
    response_class=AnnotationJSON,
    status_code=201,
)
def create_annotation(
    model_id: RowId,
    body: AnnotationIn,
    session: SessionDep,
    settings: SettingsDep,
    user: OptionalUser,
):
    """Tie a region of this model version to a sign; staff and registered users."""
    model, tablet = _readable_model(session, user, model_id)
    if user is None:
        raise unauthorized()
    _check_reference(tablet, body.reference)
    polygon_px, image_face = _region(
        session,
        model,
        body.polygon_mm,
        body.polygon_px,
        body.image_face,
        px_given="polygon_px" in body.model_fields_set,
    )
    annotation = Annotation(
        model_id=model.id,
        tablet_id=model.tablet_id,
        creator_id=user.id,
        reference=body.reference,
        reading=body.reading,
        comment=body.comment,
        polygon_mm=body.polygon_mm,
        polygon_px=polygon_px,
        image_face=image_face,
    )
    session.add(annotation)
    session.flush()
    session.refresh(annotation)
    return AnnotationJSON(to_json_ld(session, settings, annotation), status_code=201)


def _annotation(session: Session, user: User | None, annotation_id: int, *, edit: bool):
    annotation = session.get(Annotation, annotation_id)
    if annotation is None:
        raise not_found(f"annotation {annotation_id}", where="annotation_id")
    tablet = check_tablet_access(
        session,
        user,
        annotation.tablet_id,
        what=f"annotation {annotation_id}",
        where="annotation_id",
        edit=False,
    )
    if edit:
        if user is None:
            raise unauthorized()
        own = annotation.creator_id is not None and annotation.creator_id == user.id
        holder = user.role in (Role.admin, Role.staff) and crud.can_edit_tablet(user, tablet)
        if not (own or holder):
            raise forbidden(
                f"annotation {annotation_id} is another user's; its author and the "
                "holding institution's staff may change it",
                where="annotation_id",
            )
    return annotation, tablet


@router.get(
    "/annotations/{annotation_id}",
    response_model=WebAnnotationOut,
    response_class=AnnotationJSON,
)
def read_annotation(
    annotation_id: RowId, session: SessionDep, settings: SettingsDep, user: OptionalUser
):
    annotation, _tablet = _annotation(session, user, annotation_id, edit=False)
    return AnnotationJSON(to_json_ld(session, settings, annotation))


@router.patch(
    "/annotations/{annotation_id}",
    response_model=WebAnnotationOut,
    response_class=AnnotationJSON,
)
def update_annotation(
    annotation_id: RowId,
    body: AnnotationUpdate,
    session: SessionDep,
    settings: SettingsDep,
    user: OptionalUser,
):
    """Change fields (left out: kept; ``null`` clears reading, comment, the image polygon)."""
    annotation, tablet = _annotation(session, user, annotation_id, edit=True)
    changes = body.model_dump(exclude_unset=True)
    for required in ("reference", "polygon_mm"):
        if required in changes and changes[required] is None:
            raise ApiError(422, f"{required}: must not be null", where=f"body.{required}")
    if "reference" in changes:
        _check_reference(tablet, changes["reference"])
    if {"polygon_mm", "polygon_px", "image_face"} & changes.keys():
        polygon_mm = changes.get("polygon_mm", annotation.polygon_mm)
        # New outline without new pixels: derived again (the old ones are of the old outline).
        polygon_px = changes.get("polygon_px")
        polygon_px, image_face = _region(
            session,
            annotation.model,
            polygon_mm,
            polygon_px,
            changes.get("image_face", annotation.image_face),
            px_given="polygon_px" in changes,
        )
        annotation.polygon_mm, annotation.polygon_px = polygon_mm, polygon_px
        annotation.image_face = image_face
    for name in ("reference", "reading", "comment"):
        if name in changes:
            setattr(annotation, name, changes[name])
    session.flush()
    session.refresh(annotation)
    return AnnotationJSON(to_json_ld(session, settings, annotation))


@router.delete("/annotations/{annotation_id}", status_code=204)
def delete_annotation(annotation_id: RowId, session: SessionDep, user: OptionalUser) -> Response:
    annotation, _tablet = _annotation(session, user, annotation_id, edit=True)
    session.delete(annotation)
    return Response(status_code=204)
