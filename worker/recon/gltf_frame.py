"""model.glb in glTF's own convention (SCAN_BUNDLE.md, "Reconstruction output").

glTF 2.0 §3.4 ("Coordinate System and Units"): metres, +Y up, and a default camera on +Z
looking toward −Z. Our scan frame (SCAN_BUNDLE.md, "Frame of reference") is millimetres with
x along the image columns (right), y along the rows (down) and z away from the camera. The
tablet's scanned side faces the camera, i.e. −z, so in glTF it must face +Z:

    X = x / 1000,   Y = −y / 1000,   Z = −z / 1000

a rotation by 180° about x (determinant +1, so triangle winding and "front" are kept)
scaled to metres. The mesh data stays in scan-frame millimetres under ONE root node that
carries this transform (plus a translation that puts the bounding box's centre at the
origin, so viewers that do not frame the scene still show the tablet in view); the scan
frame is recorded in that node's `extras` so that our own viewer, and anyone else, can go
back to scan coordinates (undo the root's matrix).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import pygltflib

__all__ = [
    "EXTRAS_KEY",
    "gltf_root_matrix",
    "root_node",
    "scan_frame_extras",
    "wrap_scene_in_gltf_frame",
]

# The key of the root node's extras that marks it as the scan → glTF transform.
EXTRAS_KEY = "scan_frame"

_SCAN_TO_GLTF = np.diag([1e-3, -1e-3, -1e-3])


def gltf_root_matrix(min_mm: np.ndarray, max_mm: np.ndarray) -> np.ndarray:
    """4×4 matrix taking scan-frame millimetres to glTF metres (+Y up, facing +Z), with the
    centre of the box [min_mm, max_mm] (scan frame, mm) moved to the origin."""
    centre_mm = (np.asarray(min_mm, float) + np.asarray(max_mm, float)) / 2
    m = np.eye(4)
    m[:3, :3] = _SCAN_TO_GLTF
    m[:3, 3] = -_SCAN_TO_GLTF @ centre_mm
    return m


def scan_frame_extras(matrix: np.ndarray) -> dict:
    """The root node's extras: what the children's coordinates are and how to get back."""
    return {
        EXTRAS_KEY: {
            "units": "millimetre",
            "axes": "x along image columns (right), y along image rows (down), "
            "z away from the camera; the scanned surface faces -z",
            "definition": "SCAN_BUNDLE.md, Frame of reference",
            "to_gltf_matrix_column_major": _column_major(matrix),
        }
    }


def _column_major(matrix: np.ndarray) -> list[float]:
    # glTF node matrices are column-major (glTF 2.0 §5.25, node.matrix).
    return [float(x) for x in np.asarray(matrix, float).T.reshape(-1)]


def root_node(matrix: np.ndarray, children: list[int], *, name: str) -> pygltflib.Node:
    """The one root node carrying the scan → glTF transform."""
    import pygltflib  # on first use: ~0.1 s of the CLI's start-up

    return pygltflib.Node(
        name=name, matrix=_column_major(matrix), children=children, extras=scan_frame_extras(matrix)
    )


def wrap_scene_in_gltf_frame(glb: bytes, *, name: str = "tablet") -> bytes:
    """Put every root node of a scan-frame (mm) GLB's default scene under one new root node
    carrying the scan → glTF transform; returns the new GLB. The bounding box is that of the
    POSITION accessors' min/max after each node's own transform (what trimesh writes)."""
    import pygltflib  # on first use: ~0.1 s of the CLI's start-up

    gltf = pygltflib.GLTF2.load_from_bytes(glb)
    scene_index = gltf.scene or 0
    scene = gltf.scenes[scene_index]
    lo, hi = _scene_bounds_mm(gltf, scene.nodes)
    root = root_node(gltf_root_matrix(lo, hi), list(scene.nodes), name=name)
    gltf.nodes.append(root)
    scene.nodes = [len(gltf.nodes) - 1]
    gltf.scene = scene_index
    return b"".join(gltf.save_to_bytes())


def _node_matrix(node: pygltflib.Node) -> np.ndarray:
    if node.matrix:
        return np.asarray(node.matrix, float).reshape(4, 4).T
    m = np.eye(4)
    if node.scale:
        m = np.diag([*node.scale, 1.0])
    if node.rotation:
        x, y, z, w = node.rotation
        r = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )
        m = np.block([[r, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]) @ m
    if node.translation:
        t = np.eye(4)
        t[:3, 3] = node.translation
        m = t @ m
    return m


def _scene_bounds_mm(gltf: pygltflib.GLTF2, roots: list[int]) -> tuple[np.ndarray, np.ndarray]:
    corners = []
    stack = [(i, np.eye(4)) for i in roots]
    while stack:
        i, parent = stack.pop()
        node = gltf.nodes[i]
        world = parent @ _node_matrix(node)
        if node.mesh is not None:
            for prim in gltf.meshes[node.mesh].primitives:
                acc = gltf.accessors[prim.attributes.POSITION]
                if acc.min is None or acc.max is None:
                    continue
                box = np.array(np.meshgrid(*zip(acc.min, acc.max, strict=True))).reshape(3, -1)
                corners.append((world[:3, :3] @ box + world[:3, 3:]).T)
        stack.extend((c, world) for c in node.children or [])
    if not corners:
        raise ValueError("the GLB's scene has no mesh with POSITION bounds")
    pts = np.concatenate(corners)
    return pts.min(axis=0), pts.max(axis=0)
