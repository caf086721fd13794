"""IIIF Presentation 3.0: ``GET /tablets/{id}/iiif/manifest.json`` (and its Scenes by id).

Every ``id`` in the manifest dereferences: the manifest itself, the asset URLs of the model
versions, and the Scenes / AnnotationPages / Annotations, served by the second route from
the same document. The newest model version of each face is shown.
"""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse
from sqlalchemy import select
from sqlalchemy.orm import Session

from backend.api.deps import ReadableTablet, SessionDep, SettingsDep
from backend.api.models import StorageErrorRoute
from backend.errors import not_found
from backend.iiif import CONTEXT, MEDIA_TYPE, WHOLE, FaceModel, build_manifest, find_by_id
from backend.tables import Model, Scan, Tablet

router = APIRouter(tags=["iiif"], route_class=StorageErrorRoute)

FIELDS = [
    "designation",
    "p_number",
    "museum_no",
    "excavation_no",
    "collection",
    "owner",
    "period",
    "provenience",
    "genre",
    "subgenre",
    "language",
    "material",
    "object_type",
    "primary_publication",
    "height_mm",
    "width_mm",
    "thickness_mm",
    "extra",
]


def newest_models(session: Session, tablet_id: int) -> dict[str, Model]:
    """The newest model version per face (``WHOLE`` for models not made from one scan)."""
    rows = session.execute(
        select(Model, Scan.face)
        .outerjoin(Scan, Model.scan_id == Scan.id)
        .where(Model.tablet_id == tablet_id)
        .order_by(Model.version, Model.id)
    ).all()
    newest: dict[str, Model] = {}
    for model, face in rows:
        newest[face or WHOLE] = model  # ordered by version: the last one wins
    return newest


def _manifest(session: Session, settings, tablet: Tablet) -> dict:
    # The configured public URL, never the request's Host header: a forged Host must not
    # put another site's address into ids that harvesters store and follow.
    base = settings.resolved_public_url
    api = f"{base}{settings.api_prefix}"
    models = newest_models(session, tablet.id)
    if not models:
        raise not_found(f"a 3-D model of tablet {tablet.id}", where="tablet_id")
    face_models = [
        FaceModel(
            face=face,
            model_id=model.id,
            version=model.version,
            asset_urls={
                name: f"{api}/models/{model.id}/assets/{name}" for name in (model.assets or {})
            },
        )
        for face, model in models.items()
        if "model.glb" in (model.assets or {})
    ]
    if not face_models:
        raise not_found(f"a 3-D model of tablet {tablet.id}", where="tablet_id")
    dist = settings.resolved_frontend_dist
    homepage = f"{base}/tablet.html?id={tablet.id}" if dist is not None and dist.is_dir() else None
    return build_manifest(
        manifest_id=f"{api}/tablets/{tablet.id}/iiif/manifest.json",
        fields={name: getattr(tablet, name) for name in FIELDS},
        face_models=face_models,
        homepage=homepage,
        institution=tablet.institution.name if tablet.institution else None,
    )


@router.get("/tablets/{tablet_id}/iiif/manifest.json", response_class=JSONResponse)
def read_manifest(tablet: ReadableTablet, session: SessionDep, settings: SettingsDep):
    """The IIIF Presentation 3.0 Manifest of the tablet (404 until a model exists)."""
    return JSONResponse(_manifest(session, settings, tablet), media_type=MEDIA_TYPE)


@router.get("/tablets/{tablet_id}/iiif/scene/{part:path}", response_class=JSONResponse)
def read_manifest_part(
    part: str, tablet: ReadableTablet, session: SessionDep, settings: SettingsDep
):
    """A Scene, AnnotationPage or Annotation of the manifest, by its id."""
    manifest = _manifest(session, settings, tablet)
    wanted = manifest["id"].rsplit("/", 1)[0] + f"/scene/{part}"
    found = find_by_id(manifest, wanted)
    if found is None:
        raise not_found(f"IIIF resource scene/{part}", where="part")
    return JSONResponse({"@context": CONTEXT, **found}, media_type=MEDIA_TYPE)
