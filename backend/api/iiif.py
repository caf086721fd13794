"""IIIF: ``GET /tablets/{id}/iiif/manifest.json`` (Presentation 3, relightable 2.5-D faces)
and ``GET /tablets/{id}/iiif/3d/manifest.json`` (the 3-D models, Presentation 4 draft).

Every ``id`` in both manifests dereferences: the manifests, the asset URLs of the model
versions, and the Canvases / Scenes / AnnotationPages / Annotations / services, served by
the ``canvas`` and ``3d/scene`` routes from the same documents. The newest model version of
each face is shown.
"""

from __future__ import annotations

from dataclasses import replace

from fastapi import APIRouter
from fastapi.responses import JSONResponse
from sqlalchemy import select
from sqlalchemy.orm import Session

from backend import licences
from backend.annotations import (
    GLB_HEADER_BYTES,
    glb_json_length,
    scan_to_scene_matrix,
    transform_points,
)
from backend.api.deps import ReadableTablet, SessionDep, SettingsDep
from backend.api.models import StorageDep, StorageErrorRoute, model_is_simulated
from backend.errors import not_found
from backend.iiif import (
    CONTEXT,
    CONTEXT_3D,
    MEDIA_TYPE,
    MEDIA_TYPE_3D,
    WHOLE,
    FaceModel,
    Provenance,
    SignAnnotation,
    build_3d_manifest,
    build_manifest,
    find_by_id,
    has_canvas,
)
from backend.storage import ObjectNotFound, Storage
from backend.tables import Annotation, Model, Scan, Tablet

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


def _grid(report: dict) -> tuple[int | None, int | None, float | None]:
    size = report.get("image_size") if isinstance(report, dict) else None
    width = size.get("width") if isinstance(size, dict) else None
    height = size.get("height") if isinstance(size, dict) else None
    pixel = report.get("pixel_size_um") if isinstance(report, dict) else None
    ok = all(isinstance(v, int) and v > 0 for v in (width, height))
    return (
        (width, height, float(pixel) if isinstance(pixel, int | float) and pixel > 0 else None)
        if ok
        else (None, None, None)
    )


def tablet_urls(settings, tablet: Tablet) -> dict[str, str | None]:
    """Absolute URLs of a tablet: its record, its manifests and its page (if served)."""
    # The configured public URL, never the request's Host header: a forged Host must not
    # put another site's address into ids that harvesters store and follow.
    base = settings.resolved_public_url
    api = f"{base}{settings.api_prefix}"
    dist = settings.resolved_frontend_dist
    return {
        "api": api,
        "record": f"{api}/tablets/{tablet.id}",
        "manifest": f"{api}/tablets/{tablet.id}/iiif/manifest.json",
        "manifest_3d": f"{api}/tablets/{tablet.id}/iiif/3d/manifest.json",
        "page": f"{base}/tablet.html?id={tablet.id}"
        if dist is not None and dist.is_dir()
        else None,
    }


def _inputs(session: Session, settings, tablet: Tablet):
    urls = tablet_urls(settings, tablet)
    models = newest_models(session, tablet.id)
    face_models = []
    signs = _sign_annotations(session, [m.id for f, m in models.items() if f != WHOLE])
    for face, model in models.items():
        width, height, pixel = _grid(model.report or {})
        face_models.append(
            FaceModel(
                face=face,
                model_id=model.id,
                version=model.version,
                asset_urls={
                    name: f"{urls['api']}/models/{model.id}/assets/{name}"
                    for name in (model.assets or {})
                },
                width_px=width,
                height_px=height,
                pixel_size_um=pixel,
                tile_services=(
                    {
                        layer: f"{urls['api']}/models/{model.id}/assets/tiles/iiif/{layer}"
                        for layer in ("albedo", "normals", "height")
                    }
                    if "tiles/index.json" in (model.assets or {})
                    else {}
                ),
                rights=model.licence,
                attribution=model.attribution,
                annotations=tuple(signs.get((model.id, face), ())),
                simulated=model_is_simulated(model),
            )
        )
    licence = licences.effective(tablet)
    fields = {name: getattr(tablet, name) for name in FIELDS}
    return urls, face_models, fields, licence


def _sign_annotations(
    session: Session, model_ids: list[int]
) -> dict[tuple[int, str], list[SignAnnotation]]:
    """(model id, face) → the annotations on that face's image grid, oldest first."""
    found: dict[tuple[int, str], list[SignAnnotation]] = {}
    if not model_ids:
        return found
    rows = session.scalars(
        select(Annotation)
        .where(Annotation.model_id.in_(model_ids), Annotation.polygon_px.is_not(None))
        .order_by(Annotation.id)
    )
    for a in rows:
        if not a.image_face or not a.polygon_px:
            continue
        found.setdefault((a.model_id, a.image_face), []).append(
            SignAnnotation(a.id, a.reference, a.reading, a.comment, a.polygon_px)
        )
    return found


def _manifest(session: Session, settings, tablet: Tablet) -> dict:
    urls, face_models, fields, licence = _inputs(session, settings, tablet)
    if not any(has_canvas(f) for f in face_models):
        raise not_found(f"a relightable scan of tablet {tablet.id}", where="tablet_id")
    links = {}
    if any("model.glb" in f.asset_urls for f in face_models):
        links["3-D models (IIIF Presentation 4 draft)"] = urls["manifest_3d"]
    return build_manifest(
        manifest_id=urls["manifest"],
        fields=fields,
        face_models=face_models,
        provenance=Provenance(licence.licence, licence.attribution, links),
        record_url=urls["record"],
        homepage=urls["page"],
    )


def scene_matrix(storage: Storage, model: Model) -> list[list[float]] | None:
    """The scan frame → scene matrix of the model's model.glb (its root node), or None when
    the file is absent or written without one (older GLBs)."""
    info = (model.assets or {}).get("model.glb")
    size = int(info.get("size_bytes", 0)) if isinstance(info, dict) else 0
    key = f"{model.storage_prefix}/model.glb"
    try:
        header = b"".join(storage.open_range(key, 0, min(GLB_HEADER_BYTES, size)))
        length = glb_json_length(header)
        if length is None or GLB_HEADER_BYTES + length > size:
            return None
        document = b"".join(storage.open_range(key, GLB_HEADER_BYTES, GLB_HEADER_BYTES + length))
    except (ObjectNotFound, ValueError):
        return None
    return scan_to_scene_matrix(document)


def _scene_annotations(
    session: Session, storage: Storage, models: dict[str, Model]
) -> dict[int, list[SignAnnotation]]:
    """Model id → its annotations with their regions in its scene (metres), oldest first."""
    by_model: dict[int, list[Annotation]] = {}
    ids = [m.id for m in models.values()]
    if ids:
        rows = session.scalars(
            select(Annotation).where(Annotation.model_id.in_(ids)).order_by(Annotation.id)
        )
        for a in rows:
            by_model.setdefault(a.model_id, []).append(a)
    found: dict[int, list[SignAnnotation]] = {}
    for model in models.values():
        if model.id not in by_model:
            continue
        matrix = scene_matrix(storage, model)
        if matrix is None:
            continue
        found[model.id] = [
            SignAnnotation(
                a.id, a.reference, a.reading, a.comment, transform_points(matrix, a.polygon_mm)
            )
            for a in by_model[model.id]
        ]
    return found


def _manifest_3d(session: Session, settings, tablet: Tablet, storage: Storage) -> dict:
    urls, face_models, fields, licence = _inputs(session, settings, tablet)
    signs = _scene_annotations(session, storage, newest_models(session, tablet.id))
    face_models = [
        replace(f, scene_annotations=tuple(signs.get(f.model_id, ()))) for f in face_models
    ]
    if not any("model.glb" in f.asset_urls for f in face_models):
        raise not_found(f"a 3-D model of tablet {tablet.id}", where="tablet_id")
    return build_3d_manifest(
        manifest_id=urls["manifest_3d"],
        fields=fields,
        face_models=face_models,
        provenance=Provenance(licence.licence, licence.attribution),
        record_url=urls["record"],
        homepage=urls["page"],
    )


def _part(manifest: dict, prefix: str, part: str, context: str, media_type: str):
    wanted = manifest["id"].rsplit("/", 1)[0] + f"/{prefix}/{part}"
    found = find_by_id(manifest, wanted)
    if found is None:
        raise not_found(f"IIIF resource {prefix}/{part}", where="part")
    return JSONResponse({"@context": context, **found}, media_type=media_type)


@router.get("/tablets/{tablet_id}/iiif/manifest.json", response_class=JSONResponse)
def read_manifest(tablet: ReadableTablet, session: SessionDep, settings: SettingsDep):
    """The IIIF Presentation 3.0 Manifest: one canvas per scanned face (404 until one exists)."""
    return JSONResponse(_manifest(session, settings, tablet), media_type=MEDIA_TYPE)


@router.get("/tablets/{tablet_id}/iiif/canvas/{part:path}", response_class=JSONResponse)
def read_manifest_part(
    part: str, tablet: ReadableTablet, session: SessionDep, settings: SettingsDep
):
    """A Canvas, AnnotationPage, Annotation or service of the manifest, by its id."""
    manifest = _manifest(session, settings, tablet)
    return _part(manifest, "canvas", part, CONTEXT, MEDIA_TYPE)


@router.get("/tablets/{tablet_id}/iiif/3d/manifest.json", response_class=JSONResponse)
def read_manifest_3d(
    tablet: ReadableTablet, session: SessionDep, settings: SettingsDep, storage: StorageDep
):
    """The 3-D models as a IIIF Presentation 4 draft Manifest of Scenes (404 until one)."""
    return JSONResponse(_manifest_3d(session, settings, tablet, storage), media_type=MEDIA_TYPE_3D)


@router.get("/tablets/{tablet_id}/iiif/3d/scene/{part:path}", response_class=JSONResponse)
def read_manifest_3d_part(
    part: str,
    tablet: ReadableTablet,
    session: SessionDep,
    settings: SettingsDep,
    storage: StorageDep,
):
    """A Scene, AnnotationPage or Annotation of the 3-D manifest, by its id."""
    manifest = _manifest_3d(session, settings, tablet, storage)
    return _part(manifest, "scene", part, CONTEXT_3D, MEDIA_TYPE_3D)
