"""Fatcross plates as CDLI lays them out, rendered orthographically from the merged surface.

Layout (CDLI's "fatcross"): the obverse in the centre, the top edge above it, the bottom edge
below it, the left and right edges beside it, the reverse below the bottom edge. Each edge is
seen as if folded out from the obverse (the obverse's side of the edge touches the obverse),
and the reverse is the tablet turned over its bottom edge (so the reverse is upright when the
tablet is turned top-over-bottom, as CDLI shows it). Suffixes: ``_o _r _te _be _le _re``.

Rendering: one orthographic ray per output pixel (Open3D ``RaycastingScene``, Embree) along
the view axis; colour and normal are interpolated barycentrically from the mesh's vertices.
Natural colour: the albedo lit by one distant light from the upper left (as tablets are
photographed), L = ρ·(0.2 + 0.8·max(0, n·l)/(n₀·l)) with n₀ the normal facing the camera.
Curvature shading: the mean curvature of the rendered depth map (worker.recon.shading_maps).
"""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from worker.recon.shading_maps import encode_signed8, mean_curvature_per_um, robust_scale
from worker.register.o3d import o3d

__all__ = [
    "FATCROSS_VIEWS",
    "add_scale_bar",
    "compose_fatcross",
    "curvature_shading",
    "natural_colour",
    "render_orthographic",
]

# suffix → rotation tablet → view (tablet frame: obverse toward −z, x right, y down).
FATCROSS_VIEWS: dict[str, np.ndarray] = {
    "o": np.eye(3),
    "te": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
    "be": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
    "le": np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]),
    "re": np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]),
    "r": np.diag([1.0, -1.0, -1.0]),
}

_LIGHT = np.array([-0.5, -0.5, -1.0]) / np.linalg.norm([-0.5, -0.5, -1.0])


def render_orthographic(
    vertices_mm: np.ndarray,
    triangles: np.ndarray,
    vertex_rgb8: np.ndarray,
    vertex_normals: np.ndarray,
    rotation: np.ndarray,
    *,
    px_per_mm: float,
) -> dict[str, np.ndarray]:
    """Orthographic view of a mesh through ``rotation`` (tablet → view), framed on the mesh's
    bounding box in the view, at ``px_per_mm``. Returns rgb (H, W, 3) float in [0, 1] (sRGB),
    normals (H, W, 3) in the view frame (toward the camera, n_z < 0), height_um (H, W) toward
    the camera, mask (H, W) bool; NaN off the mesh."""
    if not (np.isfinite(px_per_mm) and px_per_mm > 0):
        raise ValueError(f"px_per_mm must be > 0, got {px_per_mm!r}")
    v = np.asarray(vertices_mm, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64)
    rot = np.asarray(rotation, dtype=np.float64)
    view = v @ rot.T
    lo, hi = view.min(axis=0), view.max(axis=0)
    width = int(np.ceil((hi[0] - lo[0]) * px_per_mm)) + 1
    height = int(np.ceil((hi[1] - lo[1]) * px_per_mm)) + 1
    xs = lo[0] + (np.arange(width) + 0.5) / px_per_mm
    ys = lo[1] + (np.arange(height) + 0.5) / px_per_mm
    gx, gy = np.meshgrid(xs, ys)
    z0 = lo[2] - 1.0
    origins_view = np.stack([gx, gy, np.full_like(gx, z0)], -1).reshape(-1, 3)
    origins = origins_view @ rot  # rot.T @ o, row-wise
    direction = np.broadcast_to(rot.T @ np.array([0.0, 0.0, 1.0]), origins.shape)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(tri.astype(np.uint32))
    )
    rays = o3d.core.Tensor(np.concatenate([origins, direction], 1).astype(np.float32))
    ans = scene.cast_rays(rays)
    ids = ans["primitive_ids"].numpy().astype(np.int64)
    hit = ids != o3d.t.geometry.RaycastingScene.INVALID_ID
    uv = ans["primitive_uvs"].numpy().astype(np.float64)
    t_hit = ans["t_hit"].numpy().astype(np.float64)
    corners = tri[ids[hit]]
    w = np.stack([1.0 - uv[hit, 0] - uv[hit, 1], uv[hit, 0], uv[hit, 1]], -1)[..., None]
    rgb = np.full((len(ids), 3), np.nan)
    rgb[hit] = np.sum(np.asarray(vertex_rgb8, np.float64)[corners, :3] * w, axis=1) / 255.0
    nrm = np.full((len(ids), 3), np.nan)
    n = np.sum(np.asarray(vertex_normals, np.float64)[corners] * w, axis=1) @ rot.T
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[n[:, 2] > 0] *= -1  # seen from the camera; a flipped Poisson normal must not go dark
    nrm[hit] = n
    h = np.full(len(ids), np.nan)
    h[hit] = -(z0 + t_hit[hit]) * 1000.0
    return {
        "rgb": rgb.reshape(height, width, 3),
        "normals": nrm.reshape(height, width, 3),
        "height_um": h.reshape(height, width),
        "mask": hit.reshape(height, width),
    }


def natural_colour(render: dict[str, np.ndarray]) -> np.ndarray:
    """(H, W, 3) uint8 sRGB on black: albedo lit from the upper left (module docstring)."""
    mask = render["mask"]
    lin = np.nan_to_num(render["rgb"]) ** 2.2
    shade = np.clip(np.nan_to_num(render["normals"]) @ _LIGHT, 0.0, None) / (-_LIGHT[2])
    out = lin * (0.2 + 0.8 * shade)[..., None]
    out = np.clip(out, 0.0, 1.0) ** (1 / 2.2)
    out[~mask] = 0.0
    return np.rint(255 * out).astype(np.uint8)


def curvature_shading(render: dict[str, np.ndarray], *, px_per_mm: float) -> np.ndarray:
    """(H, W, 3) uint8 grey on black: mean curvature of the depth map at a 1.5-pixel scale,
    ridges light, troughs dark (grey 128 = flat)."""
    pixel_um = 1000.0 / px_per_mm
    h = render["height_um"]
    if not render["mask"].any():
        raise ValueError("render: the mesh is not in view")
    k = mean_curvature_per_um(h, pixel_size_um=pixel_um, scale_um=1.5 * pixel_um)
    grey = encode_signed8(k, scale=robust_scale(k))
    grey[~render["mask"]] = 0
    return np.repeat(grey[..., None], 3, axis=-1)


def compose_fatcross(images: dict[str, np.ndarray], *, gap_px: int) -> np.ndarray:
    """The plate: obverse centred, te above, be below, le left, re right, r below be.

    Every view must be rendered by :func:`render_orthographic` of the same mesh at the same
    scale, so that the shared extents line up (the obverse's width is the width of te, be, r).
    """
    missing = [k for k in FATCROSS_VIEWS if k not in images]
    if missing:
        raise ValueError(f"images: missing views {missing}")
    o, te, be, le, re_, r = (images[k] for k in ("o", "te", "be", "le", "re", "r"))
    width = le.shape[1] + o.shape[1] + re_.shape[1] + 2 * gap_px
    height = te.shape[0] + o.shape[0] + be.shape[0] + r.shape[0] + 3 * gap_px
    plate = np.zeros((height, width, 3), np.uint8)
    x_o = le.shape[1] + gap_px
    y_o = te.shape[0] + gap_px

    def put(img: np.ndarray, y: int, x: int) -> None:
        plate[y : y + img.shape[0], x : x + img.shape[1]] = np.maximum(
            plate[y : y + img.shape[0], x : x + img.shape[1]], img
        )

    put(te, 0, x_o)
    put(o, y_o, x_o)
    put(le, y_o, 0)
    put(re_, y_o, x_o + o.shape[1] + gap_px)
    y_be = y_o + o.shape[0] + gap_px
    put(be, y_be, x_o)
    put(r, y_be + be.shape[0] + gap_px, x_o)
    return plate


def add_scale_bar(image: np.ndarray, *, px_per_mm: float) -> np.ndarray:
    """The image with a strip below it holding a white scale bar with 1 mm ticks and its
    length written beside it; the bar is the longest of 1, 2, 5, 10, 20, 50 mm that fits in
    60 % of the width."""
    img = np.asarray(image, dtype=np.uint8)
    usable = 0.6 * img.shape[1] / px_per_mm
    fits = [mm for mm in (1, 2, 5, 10, 20, 50) if mm <= usable]
    length_mm = fits[-1] if fits else 1
    bar_px = int(round(length_mm * px_per_mm))
    strip_h = max(24, int(round(2.5 * px_per_mm)))
    strip_w = max(img.shape[1], bar_px + 80)
    out = np.zeros((img.shape[0] + strip_h, strip_w, 3), np.uint8)
    out[: img.shape[0], : img.shape[1]] = img
    pil = Image.fromarray(out)
    draw = ImageDraw.Draw(pil)
    x0, y0 = 8, img.shape[0] + strip_h // 2
    thick = max(2, strip_h // 8)
    draw.rectangle([x0, y0, x0 + bar_px, y0 + thick], fill=(255, 255, 255))
    for mm in range(length_mm + 1):
        x = x0 + int(round(mm * px_per_mm))
        draw.line([x, y0 - thick, x, y0], fill=(255, 255, 255), width=1)
    draw.text(
        (x0 + bar_px + 8, y0 - 6),
        f"{length_mm} mm",
        fill=(255, 255, 255),
        font=ImageFont.load_default(),
    )
    return np.asarray(pil)
