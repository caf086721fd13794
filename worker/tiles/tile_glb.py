"""The GLB of one tile, its geometry compressed with meshoptimizer (EXT_meshopt_compression).

Layout (the one gltfpack writes, EXT_meshopt_compression's README): buffer 0 is the GLB's
binary chunk with the compressed vertex/index streams and the images; buffer 1 is the
"fallback" buffer, which has no data: each compressed bufferView points into it and names
its compressed bytes in buffer 0 through the extension. The extension is *required*
(three.js' GLTFLoader decodes it with `MeshoptDecoder`, the viewer's 3d-tiles-renderer too).

Positions are scan-frame millimetres as in model.glb's mesh. 3D Tiles runtimes turn glTF
content from +Y up to +Z up (3D Tiles 1.1 §"glTF transforms": a rotation of +90° about x);
the GLB's one node carries the inverse rotation, so that the tileset's root transform
(scan frame → glTF metres, `worker.recon.gltf_frame.gltf_root_matrix`) applies to the
scan-frame coordinates themselves.

Material: baseColorTexture = the tile's albedo; the viewer's other maps of the same texel
rectangle are textures named in material.extras.dh_maps (object-space normals, lossless
PNG, RGBA on a whole tablet's faces with the face's weight in alpha; curvature;
accessibility; gloss where the scan measured one, its scale in material.extras.dh_gloss).
"""

from __future__ import annotations

import json
import struct

import meshopt
import numpy as np

from worker.tiles.tile_mesh import TileMesh

__all__ = ["OPTIONAL_MAPS", "Y_UP_TO_Z_UP_INVERSE", "glb_container", "tile_glb_bytes"]

# Maps a tile carries only when the model has them (worker/photos.py's gloss.png).
OPTIONAL_MAPS = ("gloss",)

# glTF 2.0 constants (§5.23 sampler, §5.11 bufferView target, §3.6.2.2 componentType).
LINEAR, LINEAR_MIPMAP_LINEAR, CLAMP_TO_EDGE = 9729, 9987, 33071
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
FLOAT, UNSIGNED_SHORT, UNSIGNED_INT = 5126, 5123, 5125

EXT = "EXT_meshopt_compression"
# Column-major 4×4: (x, y, z) → (x, z, −y), the inverse of the runtime's y-up → z-up
# rotation (x, y, z) → (x, −z, y).
Y_UP_TO_Z_UP_INVERSE = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0, 0, 0, 1.0]


def _pad4(data: bytes) -> bytes:
    return data + b"\0" * (-len(data) % 4)


def tile_glb_bytes(
    mesh: TileMesh,
    textures: dict[str, tuple[bytes, str]],
    *,
    extras: dict,
    material_extras: dict | None = None,
) -> bytes:
    """Encode the tile: `textures` maps "albedo", "normals", "curvature", "accessibility"
    (and optionally those of OPTIONAL_MAPS) to (encoded image bytes, MIME type); `extras` goes
    to the scene's extras (dh_tile), `material_extras` to the material's beside dh_maps."""
    indices, remap, unique = meshopt.reorder_mesh(mesh.indices, triangles=True, optsize=False)
    order = np.argsort(remap)[:unique]  # new place → old vertex
    n = int(unique)
    pos = np.ascontiguousarray(mesh.positions_mm[order], np.float32)
    nor = np.ascontiguousarray(mesh.normals[order], np.float32)
    uv = np.ascontiguousarray(mesh.uv[order], np.float32)
    index_dtype = np.uint16 if n <= 65535 else np.uint32
    indices = indices.astype(index_dtype)

    streams = [  # (raw array, mode, stride, target)
        (pos, "ATTRIBUTES", 12, ARRAY_BUFFER),
        (nor, "ATTRIBUTES", 12, ARRAY_BUFFER),
        (uv, "ATTRIBUTES", 8, ARRAY_BUFFER),
        (indices, "TRIANGLES", indices.itemsize, ELEMENT_ARRAY_BUFFER),
    ]
    bin_parts: list[bytes] = []
    bin_size = 0
    fallback_size = 0
    views: list[dict] = []
    for raw, mode, stride, target in streams:
        packed = meshopt.encode_gltf_buffer(
            raw.reshape(len(raw), -1) if mode == "ATTRIBUTES" else raw.astype(np.uint32), mode
        )
        length = raw.nbytes
        view = {
            "buffer": 1,
            "byteOffset": fallback_size,
            "byteLength": length,
            "target": target,
            "extensions": {
                EXT: {
                    "buffer": 0,
                    "byteOffset": bin_size,
                    "byteLength": len(packed),
                    "byteStride": stride,
                    "count": len(raw) if mode == "ATTRIBUTES" else int(raw.size),
                    "mode": mode,
                }
            },
        }
        if mode == "ATTRIBUTES":
            view["byteStride"] = stride
        views.append(view)
        padded = _pad4(packed)
        bin_parts.append(padded)
        bin_size += len(padded)
        fallback_size += length + (-length % 4)
    # The four maps every tile has, then the optional ones (gloss: a scan's measured gloss).
    names = ["albedo", "normals", "curvature", "accessibility"]
    names += [n for n in OPTIONAL_MAPS if n in textures]
    images = []
    for name in names:
        data, mime = textures[name]
        views.append({"buffer": 0, "byteOffset": bin_size, "byteLength": len(data)})
        images.append({"bufferView": len(views) - 1, "mimeType": mime, "name": name})
        padded = _pad4(data)
        bin_parts.append(padded)
        bin_size += len(padded)
    data = b"".join(bin_parts)
    accessors = [
        {
            "bufferView": 0,
            "componentType": FLOAT,
            "count": n,
            "type": "VEC3",
            "min": [float(v) for v in pos.min(axis=0)],
            "max": [float(v) for v in pos.max(axis=0)],
        },
        {"bufferView": 1, "componentType": FLOAT, "count": n, "type": "VEC3"},
        {"bufferView": 2, "componentType": FLOAT, "count": n, "type": "VEC2"},
        {
            "bufferView": 3,
            "componentType": UNSIGNED_SHORT if index_dtype == np.uint16 else UNSIGNED_INT,
            "count": int(indices.size),
            "type": "SCALAR",
        },
    ]
    gltf = {
        "asset": {"version": "2.0", "generator": "Digital Hammurabi worker.tiles"},
        "extensionsUsed": [EXT],
        "extensionsRequired": [EXT],
        "scene": 0,
        "scenes": [{"nodes": [0], "extras": extras}],
        "nodes": [
            {
                "mesh": 0,
                "name": "tile (scan frame, mm)",
                "matrix": Y_UP_TO_Z_UP_INVERSE,
                "extras": {
                    "why": "undoes the 3D Tiles runtime's y-up to z-up rotation of glTF "
                    "content: the tileset's root transform applies to scan-frame mm"
                },
            }
        ],
        "meshes": [
            {
                "primitives": [
                    {
                        "attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
                        "indices": 3,
                        "material": 0,
                    }
                ]
            }
        ],
        "materials": [
            {
                "name": "clay",
                "pbrMetallicRoughness": {
                    "baseColorTexture": {"index": 0},
                    "metallicFactor": 0.0,
                    "roughnessFactor": 1.0,
                },
                # The skirts are seen from either side.
                "doubleSided": True,
                "extras": {
                    "dh_maps": {name: i for i, name in enumerate(names) if i > 0},
                    **(material_extras or {}),
                },
            }
        ],
        "samplers": [
            {
                "magFilter": LINEAR,
                "minFilter": LINEAR_MIPMAP_LINEAR,
                "wrapS": CLAMP_TO_EDGE,
                "wrapT": CLAMP_TO_EDGE,
            }
        ],
        "images": images,
        "textures": [{"sampler": 0, "source": i} for i in range(len(images))],
        "buffers": [
            {"byteLength": len(data)},
            {"byteLength": fallback_size, "extensions": {EXT: {"fallback": True}}},
        ],
        "bufferViews": views,
        "accessors": accessors,
    }
    return glb_container(gltf, data)


def glb_container(gltf: dict, data: bytes) -> bytes:
    """The GLB file (glTF 2.0 §4.4): header, JSON chunk padded with spaces, BIN chunk
    padded with zeros, every chunk 4-byte aligned."""
    text = json.dumps(gltf, separators=(",", ":"), allow_nan=False).encode("utf-8")
    text += b" " * (-len(text) % 4)
    data = _pad4(data)
    total = 12 + 8 + len(text) + 8 + len(data)
    return b"".join(
        [
            struct.pack("<4sII", b"glTF", 2, total),
            struct.pack("<I4s", len(text), b"JSON"),
            text,
            struct.pack("<I4s", len(data), b"BIN\0"),
            data,
        ]
    )
