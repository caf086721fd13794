"""Fatcross plates as CDLI lays them out, rendered orthographically from the merged surface.

Layout (CDLI's "fatcross"): the obverse in the centre, the top edge above it, the bottom edge
below it, the left and right edges beside it, the reverse below the bottom edge. Each edge is
seen as if folded out from the obverse (the obverse's side of the edge touches the obverse),
and the reverse is the tablet turned over its bottom edge (so the reverse is upright when the
tablet is turned top-over-bottom, as CDLI shows it). Suffixes: ``_o _r _te _be _le _re``.

Rendering: one orthographic ray per pixel (Open3D ``RaycastingScene``, Embree) along the view
axis, at the data's resolution; colour and normal are interpolated barycentrically from the
mesh's vertices, then replaced, where a scan saw the point, by that scan's own full-resolution
normal and albedo (:class:`FaceMaps`, blended over the scans that face the view, weighted by
cos⁴ of the angle between the scan's and the view's axes). Plates are then reduced to the
output resolution with an area-then-Lanczos filter (:func:`reduce_image`), so that detail
finer than the output pixel is averaged, not aliased.

Natural colour: the albedo lit by one distant light from the upper left at a raking angle, the
same for every view (Lambert: L = ρ·(a + k·max(0, n·l)), l at polar 70° from the view axis,
azimuth toward the upper left, as tablets are photographed for publication).
Curvature: the mean curvature of the rendered normal field minus a heavily smoothed one (a
band-pass, normalized convolution inside the mask), so the tablet's overall shape is removed
and only the signs carry contrast.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageDraw, ImageFont
from scipy import ndimage

from worker.recon.shading_maps import encode_signed8, robust_scale
from worker.register.o3d import o3d

__all__ = [
    "FATCROSS_VIEWS",
    "RAKING_AZIMUTH_DEG",
    "RAKING_POLAR_DEG",
    "FaceMaps",
    "add_scale_bar",
    "compose_fatcross",
    "curvature_shading",
    "detail_curvature_per_um",
    "encode_curvature",
    "fatcross_layout",
    "mean_curvature_from_normals_per_um",
    "natural_colour",
    "raking_light",
    "reduce_image",
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

RAKING_POLAR_DEG = 70.0
# Azimuth in the image plane, measured from +x (right) toward +y (down): 225° is up-left.
RAKING_AZIMUTH_DEG = 225.0


def raking_light(
    polar_deg: float = RAKING_POLAR_DEG, azimuth_deg: float = RAKING_AZIMUTH_DEG
) -> np.ndarray:
    """Unit vector toward a distant light in the view frame (x right, y down, the camera on
    −z): ``polar_deg`` from the view axis, ``azimuth_deg`` in the image plane (225° = upper
    left)."""
    if not (0.0 <= polar_deg < 90.0):
        raise ValueError(f"polar_deg must be in [0, 90), got {polar_deg!r}")
    t, a = np.radians(polar_deg), np.radians(azimuth_deg)
    return np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), -np.cos(t)])


@dataclass(frozen=True, eq=False)
class FaceMaps:
    """One scan's full-resolution maps and where the registration put it.

    tablet_from_scan: (4, 4), X_tablet = R·X_scan + t in mm (scan frame of SCAN_BUNDLE.md:
    pixel (r, c) sees (c·s, r·s, −h) µm); normals (H, W, 3) unit in the scan frame, toward the
    camera; albedo_rgb8 (H, W, 3) uint8 sRGB or None; mask (H, W) bool; height_um (H, W).
    """

    tablet_from_scan: np.ndarray
    normals: np.ndarray
    albedo_rgb8: np.ndarray | None
    mask: np.ndarray
    height_um: np.ndarray
    pixel_size_um: float


def _sample_face_maps(
    points_mm: np.ndarray,
    view_dir: np.ndarray,
    faces: list[FaceMaps],
    *,
    depth_tol_um: float,
    min_cos: float = 0.5,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals (tablet frame) and sRGB colours in [0, 1] of ``points_mm`` (tablet frame) from
    the scans that saw them, blended with weights cos⁴(scan axis, view axis); a scan counts
    where the point projects inside its mask (all four bilinear neighbours) and lies within
    ``depth_tol_um`` of its height map. Returns (normals, rgb, has_normal, has_rgb)."""
    n_acc = np.zeros((len(points_mm), 3))
    c_acc = np.zeros((len(points_mm), 3))
    w_n = np.zeros(len(points_mm))
    w_c = np.zeros(len(points_mm))
    for f in faces:
        rot = np.asarray(f.tablet_from_scan, float)[:3, :3]
        t = np.asarray(f.tablet_from_scan, float)[:3, 3]
        cos = float(rot @ np.array([0.0, 0.0, 1.0]) @ view_dir)
        if cos < min_cos:
            continue
        p = (points_mm - t) @ rot  # R.T (X − t), row-wise
        s_mm = f.pixel_size_um / 1000.0
        col, row = p[:, 0] / s_mm, p[:, 1] / s_mm
        rows, cols = f.mask.shape
        inside = (col >= 0) & (row >= 0) & (col < cols - 1) & (row < rows - 1)
        idx = np.flatnonzero(inside)
        r0 = np.floor(row[idx]).astype(np.int64)
        c0 = np.floor(col[idx]).astype(np.int64)
        fr, fc = (row[idx] - r0)[:, None], (col[idx] - c0)[:, None]
        ok = f.mask[r0, c0] & f.mask[r0 + 1, c0] & f.mask[r0, c0 + 1] & f.mask[r0 + 1, c0 + 1]

        def bilinear(a: np.ndarray, r0=r0, c0=c0, fr=fr, fc=fc) -> np.ndarray:
            a = np.asarray(a, np.float64).reshape(a.shape[0], a.shape[1], -1)
            return (
                a[r0, c0] * (1 - fr) * (1 - fc)
                + a[r0, c0 + 1] * (1 - fr) * fc
                + a[r0 + 1, c0] * fr * (1 - fc)
                + a[r0 + 1, c0 + 1] * fr * fc
            )

        h = bilinear(f.height_um)[:, 0]
        ok &= np.abs(h - (-p[idx, 2] * 1000.0)) <= depth_tol_um
        n = bilinear(f.normals) @ rot.T
        ok &= np.all(np.isfinite(n), axis=1) & np.isfinite(h)
        idx, n = idx[ok], n[ok]
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        w = cos**4
        n_acc[idx] += w * n
        w_n[idx] += w
        if f.albedo_rgb8 is not None:
            c_acc[idx] += w * bilinear(np.asarray(f.albedo_rgb8)[..., :3])[ok] / 255.0
            w_c[idx] += w
    has_n, has_c = w_n > 0, w_c > 0
    n_acc[has_n] /= np.linalg.norm(n_acc[has_n], axis=1, keepdims=True)
    c_acc[has_c] /= w_c[has_c, None]
    return n_acc, c_acc, has_n, has_c


def render_orthographic(
    vertices_mm: np.ndarray,
    triangles: np.ndarray,
    vertex_rgb8: np.ndarray,
    vertex_normals: np.ndarray,
    rotation: np.ndarray,
    *,
    px_per_mm: float,
    faces: list[FaceMaps] | None = None,
    depth_tol_um: float = 300.0,
) -> dict[str, np.ndarray]:
    """Orthographic view of a mesh through ``rotation`` (tablet → view), framed on the mesh's
    bounding box in the view, at ``px_per_mm``. Returns rgb (H, W, 3) float in [0, 1] (sRGB),
    normals (H, W, 3) in the view frame (toward the camera, n_z < 0), height_um (H, W) toward
    the camera, mask (H, W) bool; NaN off the mesh. With ``faces``, normal and colour come
    from the scans' own maps wherever a scan saw the point (module docstring); ``from_scans``
    (H, W) bool says where."""
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
    view_dir = rot.T @ np.array([0.0, 0.0, 1.0])
    direction = np.broadcast_to(view_dir, origins.shape)
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
    rgb_hit = np.sum(np.asarray(vertex_rgb8, np.float64)[corners, :3] * w, axis=1) / 255.0
    n_tab = np.sum(np.asarray(vertex_normals, np.float64)[corners] * w, axis=1)
    from_scans = np.zeros(len(ids), bool)
    if faces:
        points = origins[hit] + t_hit[hit, None] * view_dir
        n_s, c_s, has_n, has_c = _sample_face_maps(
            points, view_dir, faces, depth_tol_um=depth_tol_um
        )
        n_tab[has_n] = n_s[has_n]
        rgb_hit[has_c] = c_s[has_c]
        from_scans[np.flatnonzero(hit)[has_n]] = True
    n = n_tab @ rot.T
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[n[:, 2] > 0] *= -1  # seen from the camera; a flipped Poisson normal must not go dark
    rgb = np.full((len(ids), 3), np.nan)
    rgb[hit] = rgb_hit
    nrm = np.full((len(ids), 3), np.nan)
    nrm[hit] = n
    h = np.full(len(ids), np.nan)
    h[hit] = -(z0 + t_hit[hit]) * 1000.0
    return {
        "rgb": rgb.reshape(height, width, 3),
        "normals": nrm.reshape(height, width, 3),
        "height_um": h.reshape(height, width),
        "mask": hit.reshape(height, width),
        "from_scans": from_scans.reshape(height, width),
    }


def natural_colour(
    render: dict[str, np.ndarray],
    *,
    light: np.ndarray | None = None,
    ambient: float = 0.12,
    gain: float = 1.7,
) -> np.ndarray:
    """(H, W, 3) uint8 sRGB on black: the albedo lit by one distant light (default
    :func:`raking_light`), Lambert in linear RGB: ρ·(ambient + gain·max(0, n·l)); with the
    defaults a flat face toward the camera is at 0.70 of its albedo, slopes toward the light
    brighter, slopes away darker."""
    l_dir = raking_light() if light is None else np.asarray(light, float)
    l_dir = l_dir / np.linalg.norm(l_dir)
    mask = render["mask"]
    lin = np.nan_to_num(render["rgb"]) ** 2.2
    shade = np.clip(np.nan_to_num(render["normals"]) @ l_dir, 0.0, None)
    out = lin * (ambient + gain * shade)[..., None]
    out = np.clip(out, 0.0, 1.0) ** (1 / 2.2)
    out[~mask] = 0.0
    return np.rint(255 * out).astype(np.uint8)


def _masked_gaussian(values: np.ndarray, mask: np.ndarray, sigma_px: float) -> np.ndarray:
    """Normalized convolution (Knutsson & Westin 1993): G∗(v·m) / G∗m, so that the smoothing
    does not pull the surface toward the background at the rim."""
    m = mask.astype(np.float64)
    num = ndimage.gaussian_filter(
        np.where(mask, np.nan_to_num(values), 0.0), sigma_px, mode="constant"
    )
    den = ndimage.gaussian_filter(m, sigma_px, mode="constant")
    return np.where(den > 1e-6, num / np.maximum(den, 1e-6), 0.0)


def mean_curvature_from_normals_per_um(
    normals: np.ndarray, mask: np.ndarray, *, pixel_size_um: float, scale_um: float
) -> np.ndarray:
    """Mean curvature H (1/µm) of the surface whose unit normals (toward the camera, n_z < 0)
    are ``normals``: for z = −h, n = (−h_x, −h_y, −1)/√(1+|∇h|²), so the classical
    H = −½ ∇·(∇h/√(1+|∇h|²)) (do Carmo, Differential Geometry of Curves and Surfaces, 3.3)
    is ½ ∇·(n_x, n_y); n_x, n_y smoothed inside ``mask`` at σ = ``scale_um`` first. Ridges
    > 0. NaN off the mask."""
    sigma_px = scale_um / pixel_size_um
    nxy = [np.nan_to_num(normals[..., i]) for i in (0, 1)]
    if sigma_px > 0:
        nxy = [_masked_gaussian(c, mask, sigma_px) for c in nxy]
    div = np.gradient(nxy[0], pixel_size_um, axis=1) + np.gradient(nxy[1], pixel_size_um, axis=0)
    return np.where(mask, 0.5 * div, np.nan)


def detail_curvature_per_um(
    render: dict[str, np.ndarray],
    *,
    px_per_mm: float,
    detail_scale_um: float | None = None,
    shape_scale_mm: float = 1.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Mean curvature (1/µm) of the surface detail and the pixels away from the rim.

    Computed from the rendered normals (the scans' own where they saw the surface, so the
    merged mesh's facets do not show): H(n − G_σ∗n) with σ = ``shape_scale_mm`` (a band-pass:
    normalized convolution inside the mask, the tablet's overall curvature removed) at
    ``detail_scale_um`` (default 1.5 pixels), :func:`mean_curvature_from_normals_per_um`.
    ``inner``: the mask eroded by 3 detail scales (at the rim the view grazes the surface and
    the curvature is the silhouette's, not a sign's). NaN off the mask."""
    pixel_um = 1000.0 / px_per_mm
    n = render["normals"]
    mask = render["mask"] & np.all(np.isfinite(n), axis=-1)
    if not mask.any():
        raise ValueError("render: the mesh is not in view")
    shape_px = shape_scale_mm * px_per_mm
    detail = np.stack(
        [np.nan_to_num(n[..., i]) - _masked_gaussian(n[..., i], mask, shape_px) for i in (0, 1)],
        -1,
    )
    scale_um = 1.5 * pixel_um if detail_scale_um is None else detail_scale_um
    k = mean_curvature_from_normals_per_um(detail, mask, pixel_size_um=pixel_um, scale_um=scale_um)
    rim_px = max(2, int(round(3 * scale_um / pixel_um)))
    return k, ndimage.binary_erosion(mask, iterations=rim_px)


def encode_curvature(k_per_um: np.ndarray, *, scale_per_um: float) -> np.ndarray:
    """(H, W, 3) uint8 grey on black: 128 + 127·tanh(H/scale), ridges light; NaN → black."""
    grey = encode_signed8(k_per_um, scale=scale_per_um)
    grey[~np.isfinite(k_per_um)] = 0
    return np.repeat(grey[..., None], 3, axis=-1)


def curvature_shading(
    render: dict[str, np.ndarray],
    *,
    px_per_mm: float,
    detail_scale_um: float | None = None,
    shape_scale_mm: float = 1.5,
) -> np.ndarray:
    """(H, W, 3) uint8 grey on black: :func:`detail_curvature_per_um` shown on its own display
    range (the 98th percentile of |H| away from the rim); grey 128 = the tablet's own shape,
    ridges light, troughs dark. A plate uses one range for all its views instead
    (:func:`worker.register.plates.fatcross_files`)."""
    k, inner = detail_curvature_per_um(
        render,
        px_per_mm=px_per_mm,
        detail_scale_um=detail_scale_um,
        shape_scale_mm=shape_scale_mm,
    )
    return encode_curvature(k, scale_per_um=robust_scale(k[inner] if inner.any() else k))


def reduce_image(image: np.ndarray, size_wh: tuple[int, int]) -> np.ndarray:
    """``image`` (H, W, 3) uint8 resized to ``size_wh``: when reducing, a box (area) filter to
    within a factor 2 and then Lanczos (Pillow's ``reducing_gap``), which suppresses what lies
    above the output's Nyquist frequency instead of folding it back (aliasing)."""
    img = Image.fromarray(np.asarray(image, np.uint8))
    if img.size == tuple(size_wh):
        return np.asarray(img)
    return np.asarray(img.resize(tuple(size_wh), Image.Resampling.LANCZOS, reducing_gap=2.0))


def fatcross_layout(
    shapes: dict[str, tuple[int, int]], *, gap_px: int
) -> tuple[dict[str, tuple[int, int]], tuple[int, int]]:
    """Top-left (y, x) of every view in the plate and the plate's (height, width), from the
    views' (height, width): obverse centred, te above, be below, le left, re right, r below
    be, ``gap_px`` between neighbours."""
    missing = [k for k in FATCROSS_VIEWS if k not in shapes]
    if missing:
        raise ValueError(f"images: missing views {missing}")
    (ho, wo), (hte, _), (hbe, _), (hle, wle), (_, wre), (hr, _) = (
        shapes[k][:2] for k in ("o", "te", "be", "le", "re", "r")
    )
    width = wle + wo + wre + 2 * gap_px
    height = hte + ho + hbe + hr + 3 * gap_px
    x_o, y_o = wle + gap_px, hte + gap_px
    y_be = y_o + ho + gap_px
    at = {
        "te": (0, x_o),
        "o": (y_o, x_o),
        "le": (y_o, 0),
        "re": (y_o, x_o + wo + gap_px),
        "be": (y_be, x_o),
        "r": (y_be + hbe + gap_px, x_o),
    }
    return at, (height, width)


def compose_fatcross(images: dict[str, np.ndarray], *, gap_px: int) -> np.ndarray:
    """The plate: obverse centred, te above, be below, le left, re right, r below be.

    Every view must be rendered by :func:`render_orthographic` of the same mesh at the same
    scale, so that the shared extents line up (the obverse's width is the width of te, be, r).
    """
    at, (height, width) = fatcross_layout(
        {k: v.shape[:2] for k, v in images.items()}, gap_px=gap_px
    )
    plate = np.zeros((height, width, 3), np.uint8)
    for k, (y, x) in at.items():
        img = images[k]
        region = plate[y : y + img.shape[0], x : x + img.shape[1]]
        region[...] = np.maximum(region, img)
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
