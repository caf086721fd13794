"""What the orthographic camera sees of a tablet from one pose, on a supersampled grid.

View frame = the spec's frame: the centre of pixel (r, c) images (c·s, r·s), the camera
looks along +z and a visible surface point is (x, y, -h). A tablet point X maps to
``pose @ X + translation_um``. Each pixel is sampled at ``supersample``² points
(centres of a regular sub-grid). ``View.ground_truth`` is the box average over them,
normals from the averaged slopes so that they agree with the averaged heights:
``n ∝ (-mean ∂h/∂x, -mean ∂h/∂y, -1)``; the ground truth written beside a bundle is the
point sample at each pixel centre (``scan.point_truth``, SCAN_BUNDLE.md's output).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from worker.simulate.raycast import cast_rays
from worker.simulate.tablet import Tablet

__all__ = [
    "View",
    "assemble_view",
    "box_mean",
    "cast_grid",
    "flat_view",
    "render_view",
    "sample_coords_um",
]

BACKGROUND_REFLECTANCE = 0.03  # black velvet support
BACKGROUND_GAP_UM = 3000.0  # support plane below the lowest visible tablet point
_MAX_SLOPE = 20.0  # |∂h/∂x| cap for near-vertical samples when averaging slopes


@dataclass(frozen=True, eq=False)
class View:
    """One camera view, supersampled. Arrays (Hs, Ws[, 3]) with Hs = height·supersample.

    height_ss_um: h of the first surface seen (tablet or support), float32;
    normals_ss: unit normals in the view frame (n_z < 0), float32;
    albedo_ss: linear RGB reflectance, float32; tablet_ss: True on the tablet.
    pose: (3, 3) rotation tablet→view; translation_um: (3,) so that X_view = pose·X + t.
    """

    width: int
    height: int
    pixel_size_um: float
    supersample: int
    height_ss_um: np.ndarray
    normals_ss: np.ndarray
    albedo_ss: np.ndarray
    tablet_ss: np.ndarray
    pose: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation_um: np.ndarray = field(default_factory=lambda: np.zeros(3))
    cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        shape = (self.height * self.supersample, self.width * self.supersample)
        for name in ("height_ss_um", "tablet_ss"):
            if getattr(self, name).shape != shape:
                raise ValueError(f"{name} must have shape {shape}")
        for name in ("normals_ss", "albedo_ss"):
            if getattr(self, name).shape != (*shape, 3):
                raise ValueError(f"{name} must have shape {(*shape, 3)}")
        if self.pixel_size_um <= 0 or self.supersample < 1:
            raise ValueError("pixel_size_um must be > 0 and supersample >= 1")

    @property
    def sample_step_um(self) -> float:
        return self.pixel_size_um / self.supersample

    def ground_truth(self) -> dict[str, np.ndarray]:
        """Pixel ground truth: height (H, W) µm, normals (H, W, 3), albedo (H, W, 3), mask.

        A pixel is in the mask when all its samples are on the tablet; outside, NaN.
        """
        ss = self.supersample
        mask = box_mean(self.tablet_ss.astype(np.float32), ss) == 1.0
        height = box_mean(self.height_ss_um, ss)
        nz = np.minimum(self.normals_ss[..., 2], -1.0 / _MAX_SLOPE)
        slope_x = np.clip(self.normals_ss[..., 0] / nz, -_MAX_SLOPE, _MAX_SLOPE)
        slope_y = np.clip(self.normals_ss[..., 1] / nz, -_MAX_SLOPE, _MAX_SLOPE)
        g = np.stack([-box_mean(slope_x, ss), -box_mean(slope_y, ss), -np.ones_like(height)], -1)
        normals = g / np.linalg.norm(g, axis=-1, keepdims=True)
        albedo = box_mean(self.albedo_ss, ss)
        nan = ~mask
        height[nan] = np.nan
        normals[nan] = np.nan
        albedo[nan] = np.nan
        return {
            "height": height.astype(np.float32),
            "normals": normals.astype(np.float32),
            "albedo": albedo.astype(np.float32),
            "mask": mask,
        }


def sample_coords_um(n_pixels: int, pixel_size_um: float, supersample: int) -> np.ndarray:
    """Object-plane coordinate (µm) of each sample along one axis, (n_pixels·supersample,).

    Pixel i spans [(i - 1/2)·s, (i + 1/2)·s]; its samples sit at the centres of
    ``supersample`` equal parts.
    """
    k = np.arange(n_pixels * supersample)
    return ((k + 0.5) / supersample - 0.5) * pixel_size_um


def box_mean(a: np.ndarray, factor: int) -> np.ndarray:
    """Mean over factor×factor blocks of the first two axes: (H·f, W·f, ...) → (H, W, ...)."""
    if factor == 1:
        return np.array(a, dtype=np.float64 if a.dtype == np.float64 else np.float32)
    h, w = a.shape[0] // factor, a.shape[1] // factor
    return a.reshape(h, factor, w, factor, *a.shape[2:]).mean(axis=(1, 3))


def flat_view(
    width: int,
    height: int,
    pixel_size_um: float,
    supersample: int,
    *,
    height_ss_um: np.ndarray | float = 0.0,
    normals_ss: np.ndarray | None = None,
    albedo: np.ndarray | float = 0.5,
) -> View:
    """A view of a given height field (default flat), for tests and the reference target.

    normals default to those of the height field by central differences.
    """
    shape = (height * supersample, width * supersample)
    h = np.broadcast_to(np.asarray(height_ss_um, np.float32), shape).copy()
    if normals_ss is None:
        gy, gx = np.gradient(h.astype(np.float64), pixel_size_um / supersample)
        g = np.stack([-gx, -gy, -np.ones_like(gx)], -1)
        normals_ss = g / np.linalg.norm(g, axis=-1, keepdims=True)
    alb = np.broadcast_to(
        np.asarray(albedo, np.float32)[..., None]
        if np.ndim(albedo) < 3
        else np.asarray(albedo, np.float32),
        (*shape, 3),
    ).copy()
    return View(
        width,
        height,
        pixel_size_um,
        supersample,
        h,
        np.asarray(normals_ss, np.float32),
        alb,
        np.ones(shape, bool),
    )


def render_view(
    tablet: Tablet,
    pose: np.ndarray,
    *,
    width: int,
    height: int,
    pixel_size_um: float,
    supersample: int,
    centre_um: tuple[float, float] = (0.0, 0.0),
    rows_per_chunk: int = 0,
) -> View:
    """Ray-cast the tablet seen through ``pose`` (rotation tablet→view).

    The tablet origin is imaged ``centre_um`` (x, y) away from the image centre; h = 0 is put
    midway between the highest and lowest visible tablet points; the support plane lies
    BACKGROUND_GAP_UM below the lowest.
    """
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (3, 3) or not np.allclose(pose @ pose.T, np.eye(3), atol=1e-6):
        raise ValueError("pose must be a 3×3 rotation matrix")
    if width < 1 or height < 1 or supersample < 1 or pixel_size_um <= 0:
        raise ValueError("width, height, supersample must be >= 1 and pixel_size_um > 0")
    xs = sample_coords_um(width, pixel_size_um, supersample)
    ys = sample_coords_um(height, pixel_size_um, supersample)
    t_xy = np.array(
        [
            (width - 1) / 2 * pixel_size_um + centre_um[0],
            (height - 1) / 2 * pixel_size_um + centre_um[1],
            0.0,
        ]
    )
    z, normals = cast_grid(tablet, pose, xs, ys, t_xy, pixel_size_um / supersample, rows_per_chunk)
    return assemble_view(
        width, height, pixel_size_um, supersample, z, normals, tablet.albedo, pose, t_xy
    )


def cast_grid(
    tablet: Tablet,
    pose: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    t_xy: np.ndarray,
    step: float,
    rows_per_chunk: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Orthographic rays along +z through view points (xs, ys) µm, the tablet at pose·X + t_xy.

    Returns z (len(ys), len(xs)) µm of the first hit in the view frame (inf: none) and the
    view-frame normals there (NaN: none); ``step`` is the grid spacing (for cavity windows).
    """
    hs, ws = len(ys), len(xs)
    d_tab = pose.T @ np.array([0.0, 0.0, 1.0])
    cav = tablet.cavities
    centres_view = cav.centres_um @ pose.T + t_xy
    chunk = rows_per_chunk or max(1, 400_000 // ws)
    z0 = 2.0 * tablet.pillow.bounding_radius_um  # rays start in front of the tablet
    z = np.full((hs, ws), np.inf)
    normals = np.full((hs, ws, 3), np.nan)
    for r0 in range(0, hs, chunk):
        r1 = min(hs, r0 + chunk)
        gx, gy = np.meshgrid(xs, ys[r0:r1])
        view_pts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, -z0)], -1)
        origins = (view_pts - t_xy) @ pose  # rows of pose.T @ (p - t)
        n_cols = ws

        def candidates(i: int, r0=r0, r1=r1, n_cols=n_cols) -> np.ndarray:
            cx, cy, _ = centres_view[i]
            rad = cav.radii_um[i]
            c_lo = max(0, int(np.floor((cx - rad - xs[0]) / step)))
            c_hi = min(n_cols, int(np.ceil((cx + rad - xs[0]) / step)) + 1)
            q_lo = max(r0, int(np.floor((cy - rad - ys[0]) / step)))
            q_hi = min(r1, int(np.ceil((cy + rad - ys[0]) / step)) + 1)
            if c_lo >= c_hi or q_lo >= q_hi:
                return np.zeros(0, int)
            rows = np.arange(q_lo, q_hi) - r0
            return (rows[:, None] * n_cols + np.arange(c_lo, c_hi)[None, :]).ravel()

        hits = cast_rays(tablet.pillow, cav, origins, d_tab, candidates)
        z[r0:r1] = hits.t_um.reshape(r1 - r0, ws) - z0
        normals[r0:r1] = (hits.normals @ pose.T).reshape(r1 - r0, ws, 3)
    return z, normals


def assemble_view(
    width: int,
    height: int,
    pixel_size_um: float,
    supersample: int,
    z_um: np.ndarray,
    normals: np.ndarray,
    albedo: Callable[[np.ndarray], np.ndarray] | np.ndarray,
    pose: np.ndarray,
    t_xy: np.ndarray,
) -> View:
    """A View from first-hit depths z (Hs, Ws) µm (inf: no hit) measured along +z.

    ``albedo`` is a function of tablet-frame points (N, 3) µm or an (Hs, Ws, 3) array;
    h = 0 goes midway through the visible tablet, the support BACKGROUND_GAP_UM below it.
    """
    on = np.isfinite(z_um)
    if not on.any():
        raise ValueError("the tablet is not in the field of view")
    z_ref = 0.5 * (z_um[on].min() + z_um[on].max())
    h = np.where(on, z_ref - z_um, 0.0)
    h[~on] = h[on].min() - BACKGROUND_GAP_UM
    normals = np.array(normals, dtype=np.float32)
    normals[~on] = (0.0, 0.0, -1.0)
    translation = np.array([t_xy[0], t_xy[1], -z_ref])
    out = np.full((*z_um.shape, 3), BACKGROUND_REFLECTANCE, dtype=np.float32)
    if callable(albedo):
        xs = sample_coords_um(width, pixel_size_um, supersample)
        ys = sample_coords_um(height, pixel_size_um, supersample)
        gx, gy = np.meshgrid(xs, ys)
        pts_view = np.stack([gx[on], gy[on], -h[on]], -1)
        out[on] = albedo((pts_view - translation) @ pose)
    else:
        out[on] = np.asarray(albedo)[on]
    return View(
        width,
        height,
        pixel_size_um,
        supersample,
        h.astype(np.float32),
        normals,
        out,
        on,
        pose,
        translation,
    )
