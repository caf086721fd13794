"""A seeded synthetic cuneiform tablet: body, inscription, chips and clay colour.

The tablet frame (µm): x right, y down (toward the bottom edge), z through the tablet;
the obverse faces -z. ``FACE_POSES[face]`` is the rotation from the tablet frame into
the view frame of a scan of that face (the face's outward normal maps to -z, toward
the camera).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from worker.simulate.carvings import Polyhedron, Wedge, chip, groove_segment, wedge
from worker.simulate.pillow import Pillow, make_pillow
from worker.simulate.raycast import Cavities, cast_rays

__all__ = [
    "FACE_POSES",
    "FACES",
    "Albedo",
    "Tablet",
    "check_size_mm",
    "make_tablet",
    "surface_points",
]

FACE_POSES: dict[str, np.ndarray] = {
    "obverse": np.eye(3),
    "reverse": np.diag([-1.0, 1.0, -1.0]),
    "top": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
    "bottom": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
    "left": np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]),
    "right": np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]),
}
FACES = tuple(FACE_POSES)


@dataclass(frozen=True)
class Albedo:
    """Solid texture of the clay: linear RGB reflectance at any tablet-frame point.

    rho(x) = base · (1 + Σ brightness waves) · (1 + hue waves · (1, 0, -1)) · stains
    """

    base_rgb: np.ndarray  # (3,)
    waves: np.ndarray  # (K, 3) rad/µm
    wave_amp: np.ndarray  # (K,)
    wave_phase: np.ndarray  # (K,)
    hue_waves: np.ndarray  # (J, 3)
    hue_amp: np.ndarray  # (J,)
    hue_phase: np.ndarray  # (J,)
    stain_centres_um: np.ndarray  # (M, 3)
    stain_radii_um: np.ndarray  # (M,)
    stain_rgb: np.ndarray  # (M, 3) multiplicative tint at the stain centre

    def __call__(self, points_um: np.ndarray) -> np.ndarray:
        """Reflectance (N, 3) in [0.02, 0.95] at points (N, 3) µm."""
        shade = np.ones(len(points_um))
        for k, a, p in zip(self.waves, self.wave_amp, self.wave_phase, strict=True):
            shade += a * np.sin(points_um @ k + p)
        hue = np.zeros(len(points_um))
        for k, a, p in zip(self.hue_waves, self.hue_amp, self.hue_phase, strict=True):
            hue += a * np.sin(points_um @ k + p)
        rgb = self.base_rgb * shade[:, None] * (1 + hue[:, None] * np.array([1.0, 0.0, -1.0]))
        for c, r, tint in zip(
            self.stain_centres_um, self.stain_radii_um, self.stain_rgb, strict=True
        ):
            w = np.exp(-np.sum((points_um - c) ** 2, axis=1) / (2 * r * r))
            rgb *= 1 + w[:, None] * (tint - 1)
        return np.clip(rgb, 0.02, 0.95)


@dataclass(frozen=True)
class Tablet:
    """Body + cavities + inscription + colour; everything in the tablet frame, µm."""

    pillow: Pillow
    cavities: Cavities
    wedges: tuple[Wedge, ...]
    albedo: Albedo


def surface_points(
    pillow: Pillow, origins_um: np.ndarray, dirs: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points, outward normals and hit flags where rays meet the uncarved rough body."""
    hits = cast_rays(pillow, Cavities.empty(), origins_um, dirs, lambda i: np.zeros(0, int))
    d = dirs if dirs.ndim == 2 else dirs[None, :]
    points = origins_um + np.where(hits.hit, hits.t_um, 0)[:, None] * d
    return points, hits.normals, hits.hit


def _face_points(pillow: Pillow, face: str, uv_um: np.ndarray):
    """Surface points (N, 3), outward normals (N, 3) at face coordinates uv (N, 2), one cast."""
    rot = FACE_POSES[face]
    right, down, outward = rot[0], rot[1], -rot[2]
    uv_um = np.asarray(uv_um, float).reshape(-1, 2)
    origins = uv_um[:, :1] * right + uv_um[:, 1:] * down + outward * 2 * pillow.bounding_radius_um
    p, n, hit = surface_points(pillow, origins, -outward)
    if not hit.all():
        raise ValueError(f"no surface at {face} {uv_um[~hit][0]}")
    return p, n


def _sign_requests(rng: np.random.Generator, u0: float, v0: float, row_um: float) -> list[tuple]:
    """One sign: 1-3 wedges in a box from (u0, v0 = row top): (u, v, du, dv, w, depth, tail)."""
    out = []
    for _ in range(int(rng.integers(1, 4))):
        kind = rng.choice(["horizontal", "vertical", "winkelhaken"], p=[0.45, 0.35, 0.2])
        w = rng.uniform(1.2, 2.6) if kind != "winkelhaken" else rng.uniform(1.0, 1.8)
        w = min(w * 1000.0, 0.5 * row_um)
        depth = float(np.clip(w * rng.uniform(0.14, 0.24), 100.0, 600.0))
        if kind == "horizontal":
            du, dv, tail = 1.0, 0.0, w * rng.uniform(0.6, 1.6)
            u, v = u0 + 0.5 * w + rng.uniform(0, 600), v0 + rng.uniform(0.35, 0.65) * row_um
        elif kind == "vertical":
            du, dv, tail = 0.0, 1.0, max(row_um - 1.3 * w, 0.2 * w)
            u, v = u0 + 0.5 * w + rng.uniform(0, 1600), v0 + 0.5 * w + 150.0
        else:
            du, dv, tail = 1.0, 1.0, 0.0
            u, v = u0 + 0.5 * w + rng.uniform(0, 1600), v0 + rng.uniform(0.3, 0.7) * row_um
        out.append((u, v, du, dv, w, depth, tail))
    return out


def _build_wedges(pillow: Pillow, face: str, requests: list[tuple]) -> list[Wedge]:
    if not requests:
        return []
    req = np.array(requests, dtype=float)
    points, normals = _face_points(pillow, face, req[:, :2])
    right, down = FACE_POSES[face][0], FACE_POSES[face][1]
    return [
        wedge(face, s, n, du * right + dv * down, width_um=w, depth_um=depth, tail_um=tail)
        for s, n, (_, _, du, dv, w, depth, tail) in zip(points, normals, req, strict=True)
    ]


def _inscribe_face(pillow: Pillow, face: str, rng: np.random.Generator):
    """Rulings and rows of signs on a broad face; returns (wedges, ruling polyhedra)."""
    a, b, _ = pillow.half_size_um
    r = pillow.edge_radius_um
    u_max, v_max = a - 0.45 * r, b - 0.45 * r
    pitch = rng.uniform(4200.0, 5000.0)
    rulings = np.arange(-v_max + pitch, v_max - 0.5 * pitch, pitch)
    rows = np.concatenate([[-v_max], rulings])
    pieces: list[Polyhedron] = []
    # Rulings follow the face in straight segments short enough (<= 2 mm) that the
    # convex surface rises < 10 µm above each chord, and stop before the rounded edge.
    u_rule = a - 1.0 * r
    us = np.linspace(-u_rule, u_rule, int(2 * u_rule // 2000) + 2)
    for v in rulings:
        depth = rng.uniform(50.0, 110.0)
        points, normals = _face_points(pillow, face, np.stack([us, np.full_like(us, v)], -1))
        ends = [(s - depth * n, n) for s, n in zip(points, normals, strict=True)]
        for (p0, n0), (p1, n1) in zip(ends[:-1], ends[1:], strict=True):
            axis = (p1 - p0) / np.linalg.norm(p1 - p0)
            pieces.append(
                groove_segment(
                    p0 - 200 * axis,
                    p1 + 200 * axis,
                    n0 + n1,
                    half_angle_deg=65.0,
                    top_um=(p0 + p1) / 2 + depth * (n0 + n1) / 2,
                )
            )
    requests: list[tuple] = []
    for v_top in rows:
        row_um = min(pitch, v_max - v_top) - 300.0
        if row_um < 1500:
            continue
        u = -u_max + rng.uniform(0, 800)
        while u < u_max - 2500:
            if rng.uniform() < 0.9:
                requests += _sign_requests(rng, u, v_top + 250.0, row_um)
            u += rng.uniform(2800.0, 4200.0)
    return _build_wedges(pillow, face, requests), pieces


def _inscribe_edge(pillow: Pillow, face: str, rng: np.random.Generator) -> list[Wedge]:
    """A short line of small wedges along the middle of an edge."""
    a, b, _ = pillow.half_size_um
    r = pillow.edge_radius_um
    along_u = face in ("top", "bottom")
    half = (a if along_u else b) - 0.8 * r
    requests = []
    for t in np.arange(-half, half, rng.uniform(2500, 3500)):
        if rng.uniform() < 0.35:
            continue
        w = rng.uniform(1000.0, 1500.0)
        depth, tail = w * rng.uniform(0.12, 0.2), w * rng.uniform(0.0, 1.2)
        if along_u:
            requests.append((t, 0.0, 1.0, 0.0, w, depth, tail))
        else:
            requests.append((0.0, t, 0.0, 1.0, w, depth, tail))
    return _build_wedges(pillow, face, requests)


def _chips(pillow: Pillow, rng: np.random.Generator, count: int) -> list[Polyhedron]:
    out = []
    for _ in range(count):
        direction = rng.normal(size=3) * np.array([1.0, 1.0, 0.5])
        direction /= np.linalg.norm(direction)
        origin = direction * 2 * pillow.bounding_radius_um
        p, n, hit = surface_points(pillow, origin[None], -direction)
        if hit[0]:
            out.append(
                chip(
                    p[0], n[0], rng, size_um=rng.uniform(2000, 4000), depth_um=rng.uniform(300, 800)
                )
            )
    return out


def _make_albedo(rng: np.random.Generator, pillow: Pillow) -> Albedo:
    def waves(n: int, lo: float, hi: float):
        lam = np.exp(rng.uniform(np.log(lo), np.log(hi), n))
        dirs = rng.normal(size=(n, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        return dirs * (2 * np.pi / lam)[:, None], rng.uniform(0, 2 * np.pi, n)

    k_waves, p_waves = waves(10, 400.0, 15_000.0)
    k_hue, p_hue = waves(4, 3000.0, 20_000.0)
    n_stains = int(rng.integers(3, 7))
    stain_dirs = rng.normal(size=(n_stains, 3))
    stain_dirs /= np.linalg.norm(stain_dirs, axis=1, keepdims=True)
    centres = stain_dirs * pillow.half_size_um * 0.9
    dark = rng.uniform(0.5, 0.85, (n_stains, 1))
    tint = dark * np.array([1.0, 0.95, 0.85]) ** rng.uniform(0.5, 2.0, (n_stains, 1))
    return Albedo(
        base_rgb=np.array([0.46, 0.34, 0.23]) * rng.uniform(0.85, 1.1, 3),
        waves=k_waves,
        wave_amp=rng.uniform(0.01, 0.04, 10),
        wave_phase=p_waves,
        hue_waves=k_hue,
        hue_amp=rng.uniform(0.02, 0.06, 4),
        hue_phase=p_hue,
        stain_centres_um=centres,
        stain_radii_um=rng.uniform(1000.0, 4000.0, n_stains),
        stain_rgb=tint,
    )


SHAPES = ("standard", "flat", "curved", "broken")
# Outer sizes a tablet may have (mm): from the smallest school tablets and labels to large
# ones; the thickness at most the smaller face side, so that the body stays a tablet.
SIZE_MM_RANGE = (8.0, 120.0)
THICKNESS_MM_RANGE = (4.0, 60.0)


def check_size_mm(size_mm) -> None:
    """ValueError naming what is wrong with a tablet size (width, height, thickness) in mm."""
    try:
        w, h, t = (float(v) for v in size_mm)
    except (TypeError, ValueError):
        raise ValueError(f"tablet size: expected three numbers (mm), got {size_mm!r}") from None
    lo, hi = SIZE_MM_RANGE
    if not (lo <= w <= hi and lo <= h <= hi):
        raise ValueError(
            f"tablet size: width and height must be {lo:g}..{hi:g} mm, got {w:g} × {h:g}"
        )
    t_lo, t_hi = THICKNESS_MM_RANGE
    if not (t_lo <= t <= min(t_hi, w, h)):
        raise ValueError(
            f"tablet size: thickness must be {t_lo:g} mm .. min(width, height, {t_hi:g} mm), got {t:g}"
        )


def _reshape(pillow: Pillow, shape: str) -> Pillow:
    """``flat``: faces that hardly bulge and half the roughness; ``curved``: faces that
    bulge 3-4 times more (2-3.4 mm on the obverse). The inscription then follows the face."""
    if shape == "flat":
        return dataclasses.replace(
            pillow,
            bulge_obverse_um=0.1 * pillow.bulge_obverse_um,
            bulge_reverse_um=0.1 * pillow.bulge_reverse_um,
            amplitudes_um=0.5 * pillow.amplitudes_um,
        )
    if shape == "curved":
        return dataclasses.replace(
            pillow,
            bulge_obverse_um=4.0 * pillow.bulge_obverse_um,
            bulge_reverse_um=3.0 * pillow.bulge_reverse_um,
        )
    return pillow


def _break(pillow: Pillow, rng: np.random.Generator) -> list[Polyhedron]:
    """A broken tablet: one side cut off by a fracture of 2-4 planar facets (a jagged,
    roughly planar break through the whole thickness), removing 15-35 % of the width or
    height. Each facet is the part of a box around the tablet beyond a tilted plane."""
    # Inside the ray caster's bounding box (which holds the whole body): a ray that leaves
    # the cavity there is marched on and misses, instead of stopping on the box.
    half = pillow.bounding_half_um - 0.5
    axis = int(rng.integers(0, 2))
    side = float(rng.choice([-1.0, 1.0]))
    depth = rng.uniform(0.15, 0.35) * 2 * pillow.half_size_um[axis]
    cut = side * (pillow.half_size_um[axis] - depth)
    pieces = []
    n_facets = int(rng.integers(2, 5))
    along = 1 - axis
    edges = np.linspace(-half[along], half[along], n_facets + 1)
    for k in range(n_facets):
        normal = np.zeros(3)
        normal[axis] = side
        normal[along] = rng.uniform(-0.35, 0.35)
        normal[2] = rng.uniform(-0.3, 0.3)
        normal /= np.linalg.norm(normal)
        centre = np.zeros(3)
        centre[axis] = cut + rng.uniform(-800.0, 800.0)
        centre[along] = 0.5 * (edges[k] + edges[k + 1])
        lo, hi = -half.copy(), half.copy()
        lo[along], hi[along] = edges[k] - (k > 0) * 1.0, edges[k + 1] + (k < n_facets - 1) * 1.0
        normals = [-normal, *np.eye(3), *(-np.eye(3))]
        offsets = [float(-normal @ centre), *hi, *(-lo)]
        pieces.append(Polyhedron(np.array(normals), np.array(offsets)))
    return pieces


def _inside(pieces: list[Polyhedron], point_um: np.ndarray) -> bool:
    return any(np.all(p.normals @ point_um <= p.offsets) for p in pieces)


def make_tablet(
    seed: int, *, shape: str = "standard", size_mm: tuple[float, float, float] | None = None
) -> Tablet:
    """The synthetic tablet of ``seed``: the same seed always gives the same tablet.

    ``shape`` (``SHAPES``) changes the body: ``flat``, ``curved`` or ``broken`` (one side
    broken off; its wedges go with it). ``standard`` is the tablet of the seed unchanged.
    ``size_mm``: the body's outer width, height and thickness (default 28 × 22 × 12 mm);
    the wedges keep their real size (1-2.6 mm), so a smaller tablet carries fewer signs.
    """
    if shape not in SHAPES:
        raise ValueError(f"shape: unknown {shape!r}; choose from {SHAPES}")
    rng = np.random.default_rng([seed, 0x7AB1E7])
    if size_mm is None:
        body = make_pillow(rng)
    else:
        check_size_mm(size_mm)
        w, h, t = (1000.0 * float(v) for v in size_mm)
        body = make_pillow(rng, width_um=w, height_um=h, thickness_um=t)
    pillow = _reshape(body, shape)
    wedges: list[Wedge] = []
    pieces: list[Polyhedron] = []
    for face in ("obverse", "reverse"):
        w, p = _inscribe_face(pillow, face, rng)
        wedges += w
        pieces += p
    for face in ("top", "bottom", "left", "right"):
        wedges += _inscribe_edge(pillow, face, rng)
    pieces += _chips(pillow, rng, int(rng.integers(2, 5)))
    pieces = [pc for wd in wedges for pc in wd.pieces] + pieces
    if shape == "broken":
        # Drawn from its own stream so that the rest of the tablet stays the seed's.
        breaks = _break(pillow, np.random.default_rng([seed, 0xB4EA]))
        wedges = [w for w in wedges if not any(_inside(breaks, p) for p in (w.apex_um, *w.rim_um))]
        pieces += breaks
    spheres = [pc.bounding_sphere() for pc in pieces]
    cavities = Cavities.from_polyhedra(
        [(pc.normals, pc.offsets) for pc in pieces],
        np.array([c for c, _ in spheres]),
        np.array([r for _, r in spheres]),
    )
    return Tablet(
        pillow=pillow, cavities=cavities, wedges=tuple(wedges), albedo=_make_albedo(rng, pillow)
    )
