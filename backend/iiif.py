"""IIIF Presentation 3.0 manifests of tablets: pure functions from records to JSON.

One ``Scene`` per face (and one for the whole tablet when a registered model exists), each
painted by its ``model.glb`` as an Annotation whose body has ``type: "Model"`` and
``format: "model/gltf-binary"``. Downloads (PLY mesh, height map) are ``rendering``
entries, the thumbnail is ``thumbnail``, catalogue fields are ``metadata`` (language maps),
and ``rights`` / ``requiredStatement`` appear when the record says who holds the rights.
Spec: https://iiif.io/api/presentation/3.0/ ; the ``Scene`` container and ``Model`` body
follow the IIIF 3D community group's extension of it (a Scene is a 3-D Canvas).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

CONTEXT = "http://iiif.io/api/presentation/3/context.json"
MEDIA_TYPE = f'application/ld+json;profile="{CONTEXT}"'
WHOLE = "tablet"  # the face name used for the registered model of the whole tablet

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
RIGHTS_PREFIXES = ("http://creativecommons.org/", "http://rightsstatements.org/")

# Model files offered for download: name → (IIIF type, format, label).
RENDERINGS = (
    ("mesh.ply", "Model", "application/ply", "Mesh (PLY, millimetres)"),
    ("height.npy", "Dataset", "application/octet-stream", "Height map (NumPy float32, µm)"),
    ("normals.npy", "Dataset", "application/octet-stream", "Normal map (NumPy float32)"),
    ("albedo.png", "Image", "image/png", "Albedo (sRGB)"),
)


@dataclass(frozen=True)
class FaceModel:
    """The model version shown for one face: its id, version and asset URLs by file name."""

    face: str
    model_id: int
    version: int
    asset_urls: Mapping[str, str]


def lang(value: str, language: str = "none") -> dict[str, list[str]]:
    return {language: [value]}


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


def _scene(manifest_id: str, face_model: FaceModel) -> dict[str, Any]:
    base = manifest_id.rsplit("/", 1)[0]
    scene_id = f"{base}/scene/{face_model.face}"
    urls = face_model.asset_urls
    label = "whole tablet" if face_model.face == WHOLE else face_model.face
    annotation = {
        "id": f"{scene_id}/annotation/1",
        "type": "Annotation",
        "motivation": "painting",
        "body": {
            "id": urls["model.glb"],
            "type": "Model",
            "format": "model/gltf-binary",
            "label": lang(f"{label}, model version {face_model.version}", "en"),
        },
        "target": scene_id,
    }
    scene: dict[str, Any] = {
        "id": scene_id,
        "type": "Scene",
        "label": lang(label, "en"),
        "items": [{"id": f"{scene_id}/page/1", "type": "AnnotationPage", "items": [annotation]}],
    }
    renderings = [
        {"id": urls[name], "type": kind, "label": lang(text, "en"), "format": fmt}
        for name, kind, fmt, text in RENDERINGS
        if name in urls
    ]
    if renderings:
        scene["rendering"] = renderings
    if "thumbnail.png" in urls:
        scene["thumbnail"] = [_thumbnail(urls["thumbnail.png"])]
    return scene


def _thumbnail(url: str) -> dict[str, str]:
    return {"id": url, "type": "Image", "format": "image/png"}


def build_manifest(
    *,
    manifest_id: str,
    fields: Mapping[str, Any],
    face_models: Sequence[FaceModel],
    homepage: str | None = None,
    institution: str | None = None,
) -> dict[str, Any]:
    """The Manifest for a tablet whose catalogue ``fields`` and shown ``face_models`` are given.

    ``face_models`` must not be empty (a Manifest needs at least one item); the whole-tablet
    model, if any, comes first.
    """
    if not face_models:
        raise ValueError("face_models must hold at least one model")
    ordered = sorted(face_models, key=lambda f: (f.face != WHOLE, f.face))
    manifest: dict[str, Any] = {
        "@context": CONTEXT,
        "id": manifest_id,
        "type": "Manifest",
        "label": lang(str(fields.get("designation") or "tablet")),
        "metadata": metadata_entries(fields),
        "items": [_scene(manifest_id, f) for f in ordered],
    }
    thumbs = [f.asset_urls["thumbnail.png"] for f in ordered if "thumbnail.png" in f.asset_urls]
    if thumbs:
        manifest["thumbnail"] = [_thumbnail(thumbs[0])]
    rights = (fields.get("extra") or {}).get("rights")
    if isinstance(rights, str) and rights.startswith(RIGHTS_PREFIXES):
        manifest["rights"] = rights
    holder = fields.get("owner") or institution
    if holder:
        manifest["requiredStatement"] = {
            "label": lang("Attribution", "en"),
            "value": lang(f"Courtesy of {holder}", "en"),
        }
    if homepage:
        manifest["homepage"] = [
            {
                "id": homepage,
                "type": "Text",
                "label": lang(str(fields.get("designation"))),
                "format": "text/html",
            }
        ]
    return manifest


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
