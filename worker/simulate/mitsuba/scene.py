"""The scene of one scan as plain arrays and Mitsuba 3 plugin dictionaries.

Scene units are millimetres in the spec's frame (SCAN_BUNDLE.md): the centre of pixel
(r, c) images (c·s, r·s), the camera looks along +z, a surface point of height h is at
z = -h. Everything here is numpy except the dictionaries handed to ``mi.load_dict``.

Sensor: Mitsuba's ``orthographic`` camera maps film uv ∈ [0, 1]² to camera-space
x = 1 - 2u, y = (1 - 2v)/aspect (``ortographic_projection``: scale(-1/2, -aspect/2)·
translate(-1, -1/aspect)), so a 180° turn about z and a scale of W·s/2 put pixel (r, c)'s
centre at (c·s, r·s). The film's reconstruction filter is the camera PSF: samples are
drawn uniformly over a pixel and splatted with the filter, i.e. the pixel box convolved
with a Gaussian of σ = ``psf_sigma_px`` (a box filter when σ = 0), as ``rig.frame_radiance``.

Sources: a collimated source whose irradiance varies over the reference plane is a
``projector`` emitter (a textured pinhole) ``DISTANCE_MM`` away with a field of view of a
few millidegrees. Its texel (i, j) is lit along the ray through the pinhole and
uv = ((j + ½)/Nx, (i + ½)/Ny) (``perspective_projection``: camera x = (1 - 2u)·t,
y = (1 - 2v)·t/aspect at z = 1, t = tan(fov/2)); the texture holds the spec's pattern
evaluated where that ray meets the plane h = 0, so a point at height h is lit with the
value of p' = p - h·tanθ·u (SCAN_BUNDLE.md) up to the beam's divergence, |x|/D < 2e-5 rad
(a relative height error below 1e-4). The texture's x axis runs along the source's
horizontal direction u so that a 1-D sinusoid needs many texels along x only; the
emitter's to_world stretches its y axis to cover the field with a few texel rows.
The projector's irradiance is ``π·scale·T/z_local²`` (projector.cpp), so
``scale = source_radiance·D²`` makes a white diffuser facing the beam under texel value T
have radiance ``source_radiance·T`` (the native rig's units).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "DISTANCE_MM",
    "Source",
    "collimated_source",
    "heightfield_mesh",
    "projector_dict",
    "sensor_dict",
    "write_ply",
]

DISTANCE_MM = 1.0e6  # the projector pinhole's distance: collimated to 2e-5 rad over 34 mm
_TEXELS_PER_PERIOD = 32  # bilinear texels per finest period: cos error (2π/32)²/8 ≈ 0.5 %
_TEXEL_ROWS = 64  # across u the texture only carries the smooth irradiance E(p')


def heightfield_mesh(
    height_um: np.ndarray, pixel_size_um: float, supersample: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangle mesh of a sampled height field (Hs, Ws): vertices (mm), faces, uv.

    Vertex (j, k) sits at the sample (x_k, y_j, -h) of ``view.sample_coords_um`` (the
    native View's supersampled grid, so pixel centres fall inside quads, never on edges);
    each quad is split along the diagonal whose heights differ least (wedge edges stay
    sharp) and wound so that right-hand normals face the camera (n_z < 0). uv maps the
    image area onto [0, 1]² (texel centres on the samples). Steps between tablet and
    support samples become the walls of the extruded silhouette.
    """
    hs, ws = height_um.shape
    step = pixel_size_um / supersample
    xs = ((np.arange(ws) + 0.5) * step - 0.5 * pixel_size_um) / 1000.0
    ys = ((np.arange(hs) + 0.5) * step - 0.5 * pixel_size_um) / 1000.0
    gx, gy = np.meshgrid(xs, ys)
    vertices = np.stack([gx, gy, -np.asarray(height_um, float) / 1000.0], -1).reshape(-1, 3)
    uv = np.stack(
        [
            np.broadcast_to((np.arange(ws) + 0.5) / ws, (hs, ws)),
            np.broadcast_to(((np.arange(hs) + 0.5) / hs)[:, None], (hs, ws)),
        ],
        -1,
    )
    idx = np.arange(hs * ws).reshape(hs, ws)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]  # d c / a b, y down
    h = np.asarray(height_um, float)
    ac = np.abs(h[:-1, :-1] - h[1:, 1:]) <= np.abs(h[:-1, 1:] - h[1:, :-1])
    # x right, y down, -z toward the camera: (a, d, c) turns so that its normal has n_z < 0.
    t1 = np.where(ac[..., None], np.stack([a, d, c], -1), np.stack([a, d, b], -1))
    t2 = np.where(ac[..., None], np.stack([a, c, b], -1), np.stack([b, d, c], -1))
    faces = np.concatenate([t1.reshape(-1, 3), t2.reshape(-1, 3)])
    return vertices, faces, uv.reshape(-1, 2)


def write_ply(path: str | Path, vertices_mm: np.ndarray, faces: np.ndarray, uv: np.ndarray) -> None:
    """Binary PLY with float32 x, y, z, u, v and int32 triangles, for Mitsuba's ``ply`` shape."""
    n, f = len(vertices_mm), len(faces)
    vert = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("u", "<f4"), ("v", "<f4")])
    vert["x"], vert["y"], vert["z"] = np.asarray(vertices_mm, float).T
    vert["u"], vert["v"] = np.asarray(uv, float).T
    face = np.zeros(f, dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"] = 3
    face["i"] = faces
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
        "property float u\nproperty float v\n"
        f"element face {f}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    Path(path).write_bytes(header.encode() + vert.tobytes() + face.tobytes())


def sensor_dict(
    mi, width: int, height: int, pixel_size_um: float, psf_sigma_px: float, spp: int, z_mm: float
) -> dict:
    """The telecentric camera at z = ``z_mm`` (in front of everything) looking along +z."""
    s = pixel_size_um / 1000.0
    k = width * s / 2
    T = mi.ScalarTransform4f
    to_world = (
        T().translate([(width - 1) * s / 2, (height - 1) * s / 2, z_mm])
        @ T().rotate([0, 0, 1], 180.0)
        @ T().scale([k, k, 1.0])
    )
    rfilter = (
        {"type": "gaussian", "stddev": float(psf_sigma_px)} if psf_sigma_px > 0 else {"type": "box"}
    )
    return {
        "type": "orthographic",
        "to_world": to_world,
        "near_clip": 1e-3,
        "far_clip": 1e5,
        "film": {
            "type": "hdrfilm",
            "width": int(width),
            "height": int(height),
            "rfilter": rfilter,
            "pixel_format": "rgb",
            "sample_border": True,
        },
        # Stratified positions in the pixel: the box integral of a fringe converges as
        # spp^-3/4 instead of spp^-1/2.
        "sampler": {"type": "multijitter", "sample_count": int(spp)},
    }


@dataclass(frozen=True)
class Source:
    """A collimated source as a far projector: to_world (4×4), fov (deg) and its texels'
    points p' on the plane h = 0, ``points_um`` (Ny, Nx, 2) in the spec's frame."""

    azimuth_deg: float
    polar_deg: float
    to_world: np.ndarray
    fov_deg: float
    points_um: np.ndarray


def collimated_source(
    azimuth_deg: float,
    polar_deg: float,
    bounds_um: tuple[float, float, float, float],
    *,
    finest_period_um: float | None,
) -> Source:
    """The source lighting the plane rectangle ``bounds_um`` = (x0, x1, y0, y1) from (φ, θ).

    Texels along u: ``_TEXELS_PER_PERIOD`` per finest period (fringe sources) or 256.
    """
    phi, theta = np.radians(azimuth_deg), np.radians(polar_deg)
    u = np.array([np.sin(phi), np.cos(phi), 0.0])
    light = np.array([np.sin(theta) * u[0], np.sin(theta) * u[1], -np.cos(theta)])
    e_z = -light  # the beam's propagation
    e_x = np.array([np.cos(theta) * u[0], np.cos(theta) * u[1], np.sin(theta)])  # ⊥ e_z, along u
    e_y = np.cross(e_z, e_x)
    x0, x1, y0, y1 = (v / 1000.0 for v in bounds_um)
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    origin = centre - DISTANCE_MM * e_z
    corners = np.array([[x, y, 0.0] for x in (x0, x1) for y in (y0, y1)]) - centre
    z_local = DISTANCE_MM + corners @ e_z
    t = 1.02 * float(np.max(np.abs(corners @ e_x) / z_local))
    extent_u_mm = 2 * t * DISTANCE_MM / np.cos(theta)
    if finest_period_um is None:
        nx = 256
    else:
        nx = int(np.ceil(_TEXELS_PER_PERIOD * extent_u_mm * 1000.0 / finest_period_um))
        nx = max(256, min(nx, 1 << 15))
    ny = _TEXEL_ROWS
    aspect = nx / ny
    k = 1.02 * float(np.max(np.abs(corners @ e_y) / z_local)) * aspect / t
    to_world = np.eye(4)
    to_world[:3, 0], to_world[:3, 1], to_world[:3, 2], to_world[:3, 3] = e_x, k * e_y, e_z, origin
    uu = (np.arange(nx) + 0.5) / nx
    vv = (np.arange(ny) + 0.5) / ny
    cx = (1 - 2 * uu)[None, :] * t
    cy = (1 - 2 * vv)[:, None] * t / aspect
    d = cx[..., None] * e_x + (k * cy)[..., None] * e_y + e_z  # (Ny, Nx, 3), not unit
    lam = -origin[2] / d[..., 2]
    p = origin + lam[..., None] * d
    return Source(
        float(azimuth_deg),
        float(polar_deg),
        to_world,
        float(np.degrees(2 * np.arctan(t))),
        p[..., :2] * 1000.0,
    )


def projector_dict(mi, source: Source, texture: np.ndarray, radiance_scale: float) -> dict:
    """The ``projector`` emitter of ``source`` with ``texture`` (Ny, Nx) (linear, >= 0)."""
    tex = np.ascontiguousarray(np.asarray(texture, np.float32)[..., None])
    return {
        "type": "projector",
        "to_world": mi.ScalarTransform4f(source.to_world.tolist()),
        "fov": source.fov_deg,
        "fov_axis": "x",
        "scale": float(radiance_scale * DISTANCE_MM**2),
        "irradiance": {
            "type": "bitmap",
            "bitmap": mi.Bitmap(tex),
            "raw": True,
            "filter_type": "bilinear",
            "wrap_mode": "clamp",
        },
    }
