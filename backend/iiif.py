"""IIIF manifests of tablets: pure functions from records to JSON.

Two documents per tablet:

- ``build_manifest``: a IIIF Presentation 3.0 Manifest (https://iiif.io/api/presentation/3.0/)
  that validates with ``iiif-prezi3``. One ``Canvas`` per scanned face, sized in pixels of
  the face's image grid, painted by two image layers: the albedo (shown first) and the
  normal map. Each layer carries the *lighting map* service descriptor
  (``profile`` http://iiif.io/api/annex/services/lightingmap, ``mapType`` albedo / normal)
  that the Bodleian's ARCHiOx relighting plugin for Mirador reads to pair the two maps; the
  height map (µm) and the mesh are ``rendering`` downloads of the canvas, and the canvas's
  physical scale is the Physical Dimensions service (mm per pixel). Catalogue fields are
  ``metadata``, the licence is ``rights``, the attribution ``requiredStatement``, our JSON
  record and the CDLI record are ``seeAlso``, the tablet page ``homepage``.
- ``build_3d_manifest``: the 3-D models as ``Scene`` s painted by ``Model`` bodies
  (glTF binary), the shape of the IIIF 3D community group's Presentation 4 draft. It is a
  separate document because ``Scene`` / ``Model`` are not Presentation 3 types.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from backend.annotations import iiif_annotation, scene_annotation

CONTEXT = "http://iiif.io/api/presentation/3/context.json"
CONTEXT_3D = "http://iiif.io/api/presentation/4/context.json"
MEDIA_TYPE = f'application/ld+json;profile="{CONTEXT}"'
MEDIA_TYPE_3D = f'application/ld+json;profile="{CONTEXT_3D}"'
WHOLE = "tablet"  # the face name used for the registered model of the whole tablet
LIGHTING_MAP = "http://iiif.io/api/annex/services/lightingmap"
PHYSICAL_DIMENSIONS = "http://iiif.io/api/annex/services/physdim"
# CDLI's artifact pages are addressed by the P-number's digits (P254191 -> /artifacts/254191).
CDLI_ARTIFACT_URL = "https://cdli.mpiwg-berlin.mpg.de/artifacts/{}"
FACE_ORDER = ("obverse", "reverse", "top", "bottom", "left", "right", "other")

# Catalogue field → English label, in display order.
METADATA_FIELDS = (
    ("designation", "Designation"),
    ("p_number", "CDLI number"),
    ("museum_no", "Museum number"),
    ("excavation_no", "Excavation number"),
    ("collection", "Collection"),
    ("owner", "Owner"),
    ("period", "Period"),
    ("provenience", "Provenience"),
    ("genre", "Genre"),
    ("subgenre", "Subgenre"),
    ("language", "Language"),
    ("material", "Material"),
    ("object_type", "Object type"),
    ("primary_publication", "Primary publication"),
)
# Presentation 3 §3.3.1 "rights": a Creative Commons licence or a RightsStatements.org
# statement (either scheme, http or https as both organisations publish them).
RIGHTS_PATTERN = re.compile(
    r"^https?://(creativecommons\.org/(licenses|publicdomain)/[a-z0-9.+-]+(/[0-9.]+)?"
    r"(/[a-z-]+)?/?|rightsstatements\.org/vocab/[A-Za-z-]+/[0-9.]+/?)$"
)

# Downloads of a face: name → (IIIF type, format, label).
RENDERINGS = (
    ("mesh.ply", "Model", "application/ply", "Mesh (PLY, millimetres)"),
    ("model.glb", "Model", "model/gltf-binary", "Model (glTF binary, metres)"),
    ("height.npy", "Dataset", "application/octet-stream", "Height map (NumPy float32, µm)"),
    ("normals.npy", "Dataset", "application/octet-stream", "Normal map (NumPy float32)"),
)
# Image layers of a face's canvas, bottom first: name → (lighting map type, label).
LAYERS = (
    ("albedo.png", "albedo", "Albedo (reflectance, sRGB)"),
    ("normals.png", "normal", "Normal map (RGB = (n + 1) / 2)"),
)
# The tiles' layer of each image layer above (FaceModel.tile_services).
TILE_LAYER = {"albedo.png": "albedo", "normals.png": "normals"}
# Tile side of the workers' IIIF pyramids (worker/tiles/iiif.py TILE_PX): level-0 services
# have whole-image renditions only at the sizes libvips' dzsave wrote.
IIIF_TILE_PX = 512


@dataclass(frozen=True)
class FaceModel:
    """The model version shown for one face: id, version, asset URLs and image grid."""

    face: str
    model_id: int
    version: int
    asset_urls: Mapping[str, str]
    width_px: int | None = None
    height_px: int | None = None
    pixel_size_um: float | None = None
    # IIIF Image API 3.0 level-0 services of the face's tiles (worker/tiles, docs/tiles.md):
    # layer ("albedo", "normals", "height") → the service id (its info.json is id/info.json).
    tile_services: Mapping[str, str] = field(default_factory=dict)
    # The model's own licence and credit, when it sets them (else the manifest's apply).
    rights: str | None = None
    attribution: str | None = None
    annotations: Sequence[SignAnnotation] = ()
    # The annotations of the model with their regions in its scene (metres), 3-D manifest.
    scene_annotations: Sequence[SignAnnotation] = ()
    # Made from simulated scans: labels and the summary say so, as the pages and plates do.
    simulated: bool = False


@dataclass(frozen=True)
class SignAnnotation:
    """An annotation of a sign with its region in the face's image grid (canvas pixels)."""

    number: int  # our annotation id
    reference: str
    reading: str | None
    comment: str | None
    polygon: Sequence[Sequence[float]]  # image-grid pixels (canvas) or scene metres (scene)


@dataclass(frozen=True)
class Provenance:
    """Who holds the rights and under which licence: ``rights`` is a licence URI."""

    rights: str | None = None
    attribution: str | None = None
    links: Mapping[str, str] = field(default_factory=dict)


def lang(value: str, language: str = "none") -> dict[str, list[str]]:
    return {language: [value]}


def is_rights_uri(value: object) -> bool:
    """True for a Creative Commons or RightsStatements.org URI (Presentation 3 ``rights``)."""
    return isinstance(value, str) and RIGHTS_PATTERN.match(value) is not None


def cdli_url(p_number: str | None) -> str | None:
    """The CDLI artifact page of a P-number (``P254191`` → …/artifacts/254191), else None."""
    if not p_number or not re.fullmatch(r"P[0-9]{6}", p_number) or int(p_number[1:]) == 0:
        return None
    return CDLI_ARTIFACT_URL.format(int(p_number[1:]))


def metadata_entries(fields: Mapping[str, Any]) -> list[dict[str, Any]]:
    """``metadata`` pairs of the catalogue fields that have a value (plus dimensions)."""
    entries = [
        {"label": lang(label, "en"), "value": lang(str(fields[name]))}
        for name, label in METADATA_FIELDS
        if fields.get(name) not in (None, "")
    ]
    dims = [(fields.get(k), k.split("_")[0]) for k in ("height_mm", "width_mm", "thickness_mm")]
    if any(v is not None for v, _ in dims):
        text = ", ".join(f"{what} {value:g} mm" for value, what in dims if value is not None)
        entries.append({"label": lang("Dimensions", "en"), "value": lang(text)})
    return entries


SIMULATED_NOTE = "SIMULATED scans, not measurements of this tablet"


def summary_text(fields: Mapping[str, Any], faces: Sequence[str], simulated: bool = False) -> str:
    """One sentence a harvester can show under the label (saying so when any scan shown is
    simulated: a demo attaches simulated scans to a real catalogue record)."""
    what = str(fields.get("object_type") or "Cuneiform tablet")
    where = ", ".join(str(fields[k]) for k in ("period", "provenience") if fields.get(k))
    text = f"{what}{f' ({where})' if where else ''}"
    if faces:
        text += f": relightable 2.5-D scans of {', '.join(faces)}"
    return text + (f" ({SIMULATED_NOTE})." if simulated else ".")


def _version_label(what: str, face_model: FaceModel) -> str:
    simulated = ", simulated scan" if face_model.simulated else ""
    return f"{what}, model version {face_model.version}{simulated}"


def _face_key(face: str) -> tuple[int, str]:
    return (FACE_ORDER.index(face) if face in FACE_ORDER else len(FACE_ORDER), face)


def _image(url: str, width: int | None = None, height: int | None = None) -> dict[str, Any]:
    image: dict[str, Any] = {"id": url, "type": "Image", "format": "image/png"}
    if width and height:
        image["width"], image["height"] = width, height
    return image


def image_service(service_id: str) -> dict[str, Any]:
    """A IIIF Image API 3.0 level-0 service reference (Presentation 3 §3.4.1 `service`)."""
    return {"id": service_id, "type": "ImageService3", "profile": "level0"}


def level0_full_size(width_px: int, height_px: int, tile_px: int = IIIF_TILE_PX) -> tuple[int, int]:
    """The largest whole-image rendition of a static (dzsave iiif3) pyramid: the image
    scaled by the smallest power of two that fits it in one tile, sides rounded up."""
    factor = 1
    while -(-width_px // factor) > tile_px or -(-height_px // factor) > tile_px:
        factor *= 2
    return -(-width_px // factor), -(-height_px // factor)


def _height_annotations(canvas_id: str, service_id: str, w: int, h: int) -> list[dict[str, Any]]:
    """The height map as a supplementing image (not painted: it is data, 16-bit grey,
    height_um = offset + scale·v as the tiles' index.json says), with its image service."""
    fw, fh = level0_full_size(w, h)
    body = _image(f"{service_id}/full/{fw},{fh}/0/default.png", fw, fh)
    body["label"] = lang("Height map (16-bit grey PNG; µm = offset + scale · value)", "en")
    body["service"] = [image_service(service_id)]
    page_id = f"{canvas_id}/supplementing/1"
    return [
        {
            "id": page_id,
            "type": "AnnotationPage",
            "items": [
                {
                    "id": f"{page_id}/height",
                    "type": "Annotation",
                    "motivation": "supplementing",
                    "body": body,
                    "target": canvas_id,
                }
            ],
        }
    ]


def _renderings(urls: Mapping[str, str]) -> list[dict[str, Any]]:
    return [
        {"id": urls[name], "type": kind, "label": lang(text, "en"), "format": fmt}
        for name, kind, fmt, text in RENDERINGS
        if name in urls
    ]


def has_canvas(face_model: FaceModel) -> bool:
    """A face gets a canvas when it has an albedo image and a known image grid."""
    return (
        face_model.face != WHOLE
        and "albedo.png" in face_model.asset_urls
        and bool(face_model.width_px)
        and bool(face_model.height_px)
    )


def _canvas(base: str, face_model: FaceModel) -> dict[str, Any]:
    canvas_id = f"{base}/canvas/{face_model.face}"
    urls = face_model.asset_urls
    w, h = int(face_model.width_px or 0), int(face_model.height_px or 0)
    annotations = []
    for index, (name, map_type, text) in enumerate(LAYERS, 1):
        if name not in urls:
            continue
        body = _image(urls[name], w, h)
        body["label"] = lang(text, "en")
        body["service"] = [
            {
                "id": f"{canvas_id}/lightingmap/{map_type}",
                "type": "Service",
                "profile": LIGHTING_MAP,
                "mapType": map_type,
            }
        ]
        tiles = face_model.tile_services.get(TILE_LAYER[name])
        if tiles:
            body["service"].append(image_service(tiles))
        annotations.append(
            {
                "id": f"{canvas_id}/annotation/{index}",
                "type": "Annotation",
                "motivation": "painting",
                "body": body,
                "target": canvas_id,
            }
        )
    canvas: dict[str, Any] = {
        "id": canvas_id,
        "type": "Canvas",
        "label": lang(_version_label(face_model.face, face_model), "en"),
        "width": w,
        "height": h,
        "items": [{"id": f"{canvas_id}/page/1", "type": "AnnotationPage", "items": annotations}],
    }
    if face_model.pixel_size_um:
        canvas["service"] = [
            {
                "id": f"{canvas_id}/physdim",
                "type": "Service",
                "profile": PHYSICAL_DIMENSIONS,
                "physicalScale": face_model.pixel_size_um / 1000.0,
                "physicalUnits": "mm",
            }
        ]
    if face_model.tile_services.get("height"):
        canvas["annotations"] = _height_annotations(
            canvas_id, face_model.tile_services["height"], w, h
        )
    renderings = _renderings(urls)
    if renderings:
        canvas["rendering"] = renderings
    if "thumbnail.png" in urls:
        canvas["thumbnail"] = [_image(urls["thumbnail.png"])]
    _own_rights(canvas, face_model)
    if face_model.annotations:
        # Non-painting annotations (Presentation 3 §3.4 "annotations"): the signs scholars
        # tied to regions of this face, as tagging / commenting annotations on the canvas.
        canvas["annotations"] = _sign_page(
            canvas_id,
            [
                iiif_annotation(
                    annotation_id=f"{canvas_id}/annotations/{a.number}",
                    canvas_id=canvas_id,
                    reference=a.reference,
                    reading=a.reading,
                    comment=a.comment,
                    polygon_px=a.polygon,
                )
                for a in face_model.annotations
            ],
        )
    return canvas


def _sign_page(owner_id: str, items: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The `annotations` of a canvas or scene: one page of its signs' annotations."""
    return [
        {
            "id": f"{owner_id}/annotations",
            "type": "AnnotationPage",
            "label": lang("Signs linked to the transliteration", "en"),
            "items": items,
        }
    ]


def _own_rights(resource: dict[str, Any], face_model: FaceModel) -> None:
    """A model with its own licence or credit says so on its canvas or scene (Presentation 3
    allows ``rights`` and ``requiredStatement`` on any resource)."""
    if is_rights_uri(face_model.rights):
        resource["rights"] = face_model.rights
    if face_model.attribution:
        resource["requiredStatement"] = {
            "label": lang("Attribution", "en"),
            "value": lang(face_model.attribution, "en"),
        }


def _thumbnail(face_models: Sequence[FaceModel]) -> dict[str, Any] | None:
    # The obverse is what a catalogue shows first; a bottom edge says nothing.
    for face_model in sorted(face_models, key=lambda f: _face_key(f.face)):
        for name in ("thumbnail.png", "albedo.png"):
            if name in face_model.asset_urls:
                return _image(face_model.asset_urls[name])
    return None


def _descriptive(
    manifest: dict[str, Any],
    *,
    fields: Mapping[str, Any],
    provenance: Provenance,
    record_url: str | None,
    homepage: str | None,
) -> None:
    """The properties shared by both manifests: rights, attribution, links, homepage."""
    if is_rights_uri(provenance.rights):
        manifest["rights"] = provenance.rights
    if provenance.attribution:
        manifest["requiredStatement"] = {
            "label": lang("Attribution", "en"),
            "value": lang(provenance.attribution, "en"),
        }
    see_also = []
    if record_url:
        see_also.append(
            {
                "id": record_url,
                "type": "Dataset",
                "format": "application/json",
                "label": lang("Catalogue record (JSON)", "en"),
            }
        )
    cdli = cdli_url(fields.get("p_number"))
    if cdli:
        see_also.append(
            {
                "id": cdli,
                "type": "Text",
                "format": "text/html",
                "label": lang(f"CDLI record {fields['p_number']}", "en"),
            }
        )
    for label, url in provenance.links.items():
        see_also.append(
            {"id": url, "type": "Dataset", "format": "application/ld+json", "label": lang(label)}
        )
    if see_also:
        manifest["seeAlso"] = see_also
    if homepage:
        manifest["homepage"] = [
            {
                "id": homepage,
                "type": "Text",
                "label": lang(str(fields.get("designation") or "tablet")),
                "format": "text/html",
            }
        ]


def build_manifest(
    *,
    manifest_id: str,
    fields: Mapping[str, Any],
    face_models: Sequence[FaceModel],
    provenance: Provenance = Provenance(),
    record_url: str | None = None,
    homepage: str | None = None,
) -> dict[str, Any]:
    """The Presentation 3 Manifest of a tablet whose shown ``face_models`` are given.

    Only faces for which :func:`has_canvas` holds become canvases; at least one must.
    """
    shown = sorted((f for f in face_models if has_canvas(f)), key=lambda f: _face_key(f.face))
    if not shown:
        raise ValueError("face_models must hold at least one face with an albedo image")
    base = manifest_id.rsplit("/", 1)[0]
    return _manifest_of(
        CONTEXT,
        manifest_id,
        fields,
        summary=summary_text(fields, [f.face for f in shown], any(f.simulated for f in shown)),
        items=[_canvas(base, f) for f in shown],
        shown=shown,
        provenance=provenance,
        record_url=record_url,
        homepage=homepage,
    )


def _manifest_of(
    context, manifest_id, fields, *, summary, items, shown, provenance, record_url, homepage
) -> dict[str, Any]:
    """What both manifests share around their items: label, summary, metadata, thumbnail
    (the obverse) and the descriptive properties (rights, attribution, links)."""
    manifest: dict[str, Any] = {
        "@context": context,
        "id": manifest_id,
        "type": "Manifest",
        "label": lang(str(fields.get("designation") or "tablet")),
        "summary": lang(summary, "en"),
        "metadata": metadata_entries(fields),
        "items": items,
    }
    thumbnail = _thumbnail(shown)
    if thumbnail:
        manifest["thumbnail"] = [thumbnail]
    _descriptive(
        manifest, fields=fields, provenance=provenance, record_url=record_url, homepage=homepage
    )
    return manifest


def _scene(base: str, face_model: FaceModel) -> dict[str, Any]:
    scene_id = f"{base}/scene/{face_model.face}"
    urls = face_model.asset_urls
    label = "whole tablet" if face_model.face == WHOLE else face_model.face
    annotation = {
        "id": f"{scene_id}/annotation/1",
        "type": "Annotation",
        "motivation": ["painting"],
        "body": {
            "id": urls["model.glb"],
            "type": "Model",
            "format": "model/gltf-binary",
            "label": lang(_version_label(label, face_model), "en"),
        },
        "target": {"id": scene_id, "type": "Scene"},
    }
    scene: dict[str, Any] = {
        "id": scene_id,
        "type": "Scene",
        "label": lang(f"{label} (simulated scan)" if face_model.simulated else label, "en"),
        "items": [{"id": f"{scene_id}/page/1", "type": "AnnotationPage", "items": [annotation]}],
    }
    renderings = _renderings({k: v for k, v in urls.items() if k != "model.glb"})
    if renderings:
        scene["rendering"] = renderings
    if "thumbnail.png" in urls:
        scene["thumbnail"] = [_image(urls["thumbnail.png"])]
    _own_rights(scene, face_model)
    if face_model.scene_annotations:
        scene["annotations"] = _sign_page(
            scene_id,
            [
                scene_annotation(
                    annotation_id=f"{scene_id}/annotations/{a.number}",
                    scene_id=scene_id,
                    reference=a.reference,
                    reading=a.reading,
                    comment=a.comment,
                    polygon_scene_m=a.polygon,
                )
                for a in face_model.scene_annotations
            ],
        )
    return scene


def build_3d_manifest(
    *,
    manifest_id: str,
    fields: Mapping[str, Any],
    face_models: Sequence[FaceModel],
    provenance: Provenance = Provenance(),
    record_url: str | None = None,
    homepage: str | None = None,
) -> dict[str, Any]:
    """The 3-D models as a Presentation 4 draft Manifest: one ``Scene`` per ``model.glb``.

    The whole-tablet model, if any, comes first.
    """
    shown = [f for f in face_models if "model.glb" in f.asset_urls]
    if not shown:
        raise ValueError("face_models must hold at least one model with a model.glb")
    ordered = sorted(shown, key=lambda f: (f.face != WHOLE, _face_key(f.face)))
    base = manifest_id.rsplit("/", 1)[0]
    return _manifest_of(
        CONTEXT_3D,
        manifest_id,
        fields,
        summary=summary_text(fields, []).rstrip(".")
        + (
            f": 3-D models ({SIMULATED_NOTE})."
            if any(f.simulated for f in shown)
            else ": 3-D models."
        ),
        items=[_scene(base, f) for f in ordered],
        shown=shown,
        provenance=provenance,
        record_url=record_url,
        homepage=homepage,
    )


def find_by_id(document: Any, wanted: str) -> dict[str, Any] | None:
    """The object inside ``document`` whose ``id`` is ``wanted`` (depth first), or None."""
    if isinstance(document, dict):
        if document.get("id") == wanted and "type" in document:
            return document
        children = document.values()
    elif isinstance(document, list):
        children = document
    else:
        return None
    for child in children:
        found = find_by_id(child, wanted)
        if found is not None:
            return found
    return None
