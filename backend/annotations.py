"""Annotations of signs as W3C Web Annotations (https://www.w3.org/TR/annotation-model/).

Pure functions from plain values to JSON-LD (context http://www.w3.org/ns/anno.jsonld):

- the *body* is up to three ``TextualBody`` s: the ATF-style reference (purpose
  ``identifying``, e.g. ``o 2 3``), the reading (``describing``) and the comment
  (``commenting``); the annotation's motivation is ``commenting`` when it has a comment, else
  ``tagging`` (IIIF Presentation 3 takes both for non-painting annotations);
- the *target* is the region twice: on the model version (its ``model.glb``, the scan frame
  in mm) by a ``WktSelector`` holding a ``POLYGON Z`` (the selector of the IIIF 3D community
  group's Presentation 4 draft), and, when known, on the face's image (``albedo.png``, the
  image grid in pixels) by an ``SvgSelector`` (a ``<polygon>``) with its bounding box as a
  Media Fragments ``FragmentSelector`` (``xywh=pixel:x,y,w,h``) for clients that read no SVG.

Frame: a pixel (row r, column c) of a face's image grid is the point (c·s, r·s) µm of the
scan frame (SCAN_BUNDLE.md), so a face model's polygon in pixels follows from the one in mm
(:func:`polygon_px_from_mm`).
"""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence
from datetime import datetime
from typing import Any

ANNO_CONTEXT = "http://www.w3.org/ns/anno.jsonld"
MEDIA_TYPE = f'application/ld+json; profile="{ANNO_CONTEXT}"'
MEDIA_FRAGMENTS = "http://www.w3.org/TR/media-frags/"
SVG_NS = "http://www.w3.org/2000/svg"
GLB_HEADER_BYTES = 20  # glTF 2.0 §4.4: magic, version, length, then the JSON chunk's header
MAX_GLB_JSON_BYTES = 16 * 1024 * 1024
SCAN_FRAME_KEY = "scan_frame"  # the root node's extras (worker/recon/gltf_frame.py)


def polygon_px_from_mm(
    polygon_mm: Sequence[Sequence[float]], pixel_size_um: float
) -> list[list[float]]:
    """[[col, row], ...] of a face's image grid for points [[x, y, z], ...] in mm.

    SCAN_BUNDLE.md: pixel (r, c) is the point (c·s, r·s) µm, so c = 1000·x/s, r = 1000·y/s.
    """
    if not pixel_size_um > 0:
        raise ValueError(f"pixel_size_um must be > 0, got {pixel_size_um}")
    scale = 1000.0 / pixel_size_um
    return [[round(p[0] * scale, 2), round(p[1] * scale, 2)] for p in polygon_mm]


def wkt_polygon_z(polygon: Sequence[Sequence[float]], *, decimals: int = 4) -> str:
    """``POLYGON Z ((x y z, ..., x y z))``, the ring closed (OGC Simple Features / WKT)."""
    ring = [list(p) for p in polygon]
    if ring and ring[0] != ring[-1]:
        ring.append(ring[0])
    return "POLYGON Z ((" + ", ".join(" ".join(f"{v:.{decimals}f}" for v in p) for p in ring) + "))"


def glb_json_length(header: bytes) -> int | None:
    """Length of a GLB's JSON chunk from its first 20 bytes (glTF 2.0 §4.4), else None."""
    if len(header) < GLB_HEADER_BYTES or header[:4] != b"glTF":
        return None
    version, _total = struct.unpack_from("<II", header, 4)
    length, kind = struct.unpack_from("<I4s", header, 12)
    if version != 2 or kind != b"JSON" or not 0 < length <= MAX_GLB_JSON_BYTES:
        return None
    return length


def scan_to_scene_matrix(gltf_json: bytes) -> list[list[float]] | None:
    """The 4×4 matrix (row-major) of the root node that carries the scan frame → glTF scene
    transform (SCAN_BUNDLE.md; its ``extras`` name ``scan_frame``), or None.

    Our model.glb keeps the mesh in scan-frame (or tablet-frame) millimetres under that one
    root node; its matrix takes those points to the scene's metres, +Y up."""
    try:
        document = json.loads(gltf_json)
    except (UnicodeDecodeError, json.JSONDecodeError):
        return None
    nodes = document.get("nodes") if isinstance(document, dict) else None
    for node in nodes if isinstance(nodes, list) else []:
        extras = node.get("extras") if isinstance(node, dict) else None
        matrix = node.get("matrix") if isinstance(node, dict) else None
        if (
            isinstance(extras, dict)
            and SCAN_FRAME_KEY in extras
            and isinstance(matrix, list)
            and len(matrix) == 16
            and all(isinstance(v, int | float) for v in matrix)
        ):
            # glTF matrices are column-major (glTF 2.0 §5.25).
            return [[float(matrix[col * 4 + row]) for col in range(4)] for row in range(4)]
    return None


def transform_points(
    matrix: Sequence[Sequence[float]], points: Sequence[Sequence[float]]
) -> list[list[float]]:
    """``matrix`` (4×4, row-major, affine) applied to 3-D ``points``."""
    return [
        [sum(matrix[r][c] * p[c] for c in range(3)) + matrix[r][3] for r in range(3)]
        for p in points
    ]


def svg_polygon(polygon_px: Sequence[Sequence[float]]) -> str:
    """An SVG document with one ``<polygon>`` (image-grid pixels), as SvgSelector wants."""
    points = " ".join(f"{p[0]:g},{p[1]:g}" for p in polygon_px)
    return f'<svg xmlns="{SVG_NS}"><polygon points="{points}"/></svg>'


def xywh(polygon_px: Sequence[Sequence[float]]) -> str:
    """``xywh=pixel:x,y,w,h``: the polygon's bounding box in whole pixels (Media Fragments)."""
    cols = [p[0] for p in polygon_px]
    rows = [p[1] for p in polygon_px]
    x, y = int(min(cols)), int(min(rows))
    w = max(1, int(-(-max(cols) // 1)) - x)
    h = max(1, int(-(-max(rows) // 1)) - y)
    return f"xywh=pixel:{x},{y},{w},{h}"


def bodies(reference: str, reading: str | None, comment: str | None) -> list[dict[str, Any]]:
    """The TextualBodies: reference (identifying), reading (describing), comment."""
    out = [_text(reference, "identifying")]
    if reading:
        out.append(_text(reading, "describing"))
    if comment:
        out.append(_text(comment, "commenting"))
    return out


def _text(value: str, purpose: str) -> dict[str, Any]:
    return {"type": "TextualBody", "purpose": purpose, "value": value, "format": "text/plain"}


def motivation(comment: str | None) -> str:
    return "commenting" if comment else "tagging"


def image_selectors(polygon_px: Sequence[Sequence[float]]) -> list[dict[str, Any]]:
    """The image-grid region: the exact polygon, then its bounding box (the fallback)."""
    return [
        {"type": "SvgSelector", "value": svg_polygon(polygon_px)},
        {"type": "FragmentSelector", "conformsTo": MEDIA_FRAGMENTS, "value": xywh(polygon_px)},
    ]


def web_annotation(
    *,
    annotation_id: str,
    reference: str,
    reading: str | None,
    comment: str | None,
    polygon_mm: Sequence[Sequence[float]],
    polygon_px: Sequence[Sequence[float]] | None,
    model_source: dict[str, Any],
    image_source: dict[str, Any] | None,
    creator: dict[str, Any] | None,
    created: datetime,
    modified: datetime,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """One annotation as W3C Web Annotation JSON-LD.

    ``model_source`` / ``image_source``: ``{"id", "type", "format", "label"}`` of the model
    file and of the face's image; no image target when ``polygon_px`` or the image is unknown.
    ``extra``: plain-JSON facts for our own clients (model id and version, the parsed
    reference); JSON-LD processors ignore terms the context does not define.
    """
    targets: list[dict[str, Any]] = [
        {
            "type": "SpecificResource",
            "source": model_source,
            "selector": [{"type": "WktSelector", "value": wkt_polygon_z(polygon_mm)}],
        }
    ]
    if polygon_px and image_source is not None:
        targets.append(
            {
                "type": "SpecificResource",
                "source": image_source,
                "selector": image_selectors(polygon_px),
            }
        )
    document: dict[str, Any] = {
        "@context": ANNO_CONTEXT,
        "id": annotation_id,
        "type": "Annotation",
        "motivation": motivation(comment),
        "created": created.isoformat(),
        "modified": modified.isoformat(),
        "body": bodies(reference, reading, comment),
        "target": targets,
    }
    if creator is not None:
        document["creator"] = creator
    document.update(extra or {})
    return document


def iiif_annotation(
    *,
    annotation_id: str,
    canvas_id: str,
    reference: str,
    reading: str | None,
    comment: str | None,
    polygon_px: Sequence[Sequence[float]],
) -> dict[str, Any]:
    """The annotation as IIIF Presentation 3 puts it on a canvas (region in canvas pixels)."""
    return {
        "id": annotation_id,
        "type": "Annotation",
        "motivation": motivation(comment),
        "body": bodies(reference, reading, comment),
        "target": {
            "type": "SpecificResource",
            "source": {"id": canvas_id, "type": "Canvas"},
            "selector": image_selectors(polygon_px)[0],
        },
    }


def scene_annotation(
    *,
    annotation_id: str,
    scene_id: str,
    reference: str,
    reading: str | None,
    comment: str | None,
    polygon_scene_m: Sequence[Sequence[float]],
) -> dict[str, Any]:
    """The annotation on a Scene of the 3-D (Presentation 4 draft) manifest: the region as a
    ``WktSelector`` in the scene's coordinates (metres, the model painted at the origin)."""
    return {
        "id": annotation_id,
        "type": "Annotation",
        "motivation": [motivation(comment)],
        "body": bodies(reference, reading, comment),
        "target": {
            "type": "SpecificResource",
            "source": {"id": scene_id, "type": "Scene"},
            "selector": [
                {"type": "WktSelector", "value": wkt_polygon_z(polygon_scene_m, decimals=6)}
            ],
        },
    }
