"""Cuneiform wedges, ruling lines and chips as convex cavities (planar facets).

A wedge is the impression of a stylus corner: a triangular-pyramid head (three planar
facets meeting at the deepest point) and, for most wedges, a V-groove tail that rises
to the surface along the wedge direction. Ruling lines are shallow V-grooves that
follow the face in short straight segments; chips are flakes bounded by a fracture
plane and flaring walls. Each piece is a convex polyhedron ``{x : n_k·x <= c_k}``
whose top is capped a little above the surface, so its facets are exact planes with
exact normals and sharp edges.

Inputs are a surface point S (µm, tablet frame), its outward unit normal N and a unit
tangent direction d; all lengths in µm.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

__all__ = ["Polyhedron", "Wedge", "chip", "groove_segment", "wedge"]

_CAP_UM = 300.0  # cap height above S: above any surface point inside a cavity's rim


@dataclass(frozen=True)
class Polyhedron:
    """Half-spaces ``normals @ x <= offsets``: normals (P, 3) unit, offsets (P,) µm."""

    normals: np.ndarray
    offsets: np.ndarray

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        """Centre (3,) and radius of a sphere around all vertices of the (bounded) polyhedron."""
        triples = np.array(list(itertools.combinations(range(len(self.offsets)), 3)))
        a = self.normals[triples]  # (T, 3, 3)
        ok = np.abs(np.linalg.det(a)) > 1e-9
        v = np.linalg.solve(a[ok], self.offsets[triples[ok]][..., None])[..., 0]
        verts = v[np.all(v @ self.normals.T <= self.offsets + 1e-6, axis=1)]
        if len(verts) < 4:
            raise ValueError("polyhedron is not bounded")
        verts = np.array(verts)
        centre = verts.mean(axis=0)
        return centre, float(np.max(np.linalg.norm(verts - centre, axis=1)) + 1.0)


@dataclass(frozen=True)
class Wedge:
    """One wedge impression (tablet frame, µm) and the polyhedra that carve it."""

    face: str
    centre_um: np.ndarray  # S, on the surface
    normal: np.ndarray  # N, outward
    direction: np.ndarray  # d, tangent, from head toward tail
    width_um: float
    depth_um: float  # apex below the tangent plane at S, along N
    apex_um: np.ndarray
    rim_um: np.ndarray  # (3, 3): back-left, back-right, front vertex of the head
    tail_end_um: np.ndarray | None
    pieces: tuple[Polyhedron, ...]


def _plane_through(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray, inside: np.ndarray):
    """Unit normal and offset of the plane through p0, p1, p2, with ``inside`` on the <= side."""
    n = np.cross(p1 - p0, p2 - p0)
    n /= np.linalg.norm(n)
    if n @ inside > n @ p0:
        n = -n
    return n, float(n @ p0)


def _cap(surface: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, float]:
    return normal, float(normal @ surface + _CAP_UM)


def _frame(normal: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = normal / np.linalg.norm(normal)
    d = direction - (direction @ n) * n
    d /= np.linalg.norm(d)
    return n, d, np.cross(n, d)


def groove_segment(
    start_um: np.ndarray,
    end_um: np.ndarray,
    normal: np.ndarray,
    *,
    half_angle_deg: float,
    cap_start: bool = True,
    cap_end: bool = True,
    top_um: np.ndarray | None = None,
) -> Polyhedron:
    """V-groove whose bottom is the segment start→end; walls at ±half_angle from ``normal``.

    The groove ends in planes perpendicular to the segment at each end (``cap_*``); its
    top is capped above ``top_um`` (default: the higher end point).
    """
    axis = end_um - start_um
    axis /= np.linalg.norm(axis)
    up = normal - (normal @ axis) * axis
    up /= np.linalg.norm(up)
    side = np.cross(axis, up)
    psi = np.radians(half_angle_deg)
    normals = [side * np.cos(psi) - up * np.sin(psi), -side * np.cos(psi) - up * np.sin(psi)]
    offsets = [float(normals[0] @ start_um), float(normals[1] @ start_um)]
    if cap_start:
        normals.append(-axis)
        offsets.append(float(-axis @ start_um))
    if cap_end:
        normals.append(axis)
        offsets.append(float(axis @ end_um))
    top = top_um if top_um is not None else (start_um if up @ start_um > up @ end_um else end_um)
    n_cap, c_cap = _cap(top, normal / np.linalg.norm(normal))
    normals.append(n_cap)
    offsets.append(c_cap)
    return Polyhedron(np.array(normals), np.array(offsets))


def wedge(
    face: str,
    surface_um: np.ndarray,
    normal: np.ndarray,
    direction: np.ndarray,
    *,
    width_um: float,
    depth_um: float,
    tail_um: float,
) -> Wedge:
    """A wedge whose head (width_um wide, as long) is centred on ``surface_um``.

    The head rim: back edge at -0.45·w along d, front vertex at +0.55·w; the apex sits
    depth_um below the tangent plane at -0.15·w. A tail of length ``tail_um`` (0: none,
    a Winkelhaken) starts inside the head at 0.6·depth and rises to the surface.
    """
    if width_um <= 0 or depth_um <= 0 or tail_um < 0:
        raise ValueError("width_um and depth_um must be > 0, tail_um >= 0")
    n, d, e = _frame(normal, direction)
    s = np.asarray(surface_um, float)
    w = width_um
    b1 = s - 0.45 * w * d + 0.5 * w * e
    b2 = s - 0.45 * w * d - 0.5 * w * e
    f = s + 0.55 * w * d
    apex = s - 0.15 * w * d - depth_um * n
    inside = (b1 + b2 + f) / 3 - 0.25 * depth_um * n
    planes = [
        _plane_through(apex, b1, b2, inside),
        _plane_through(apex, b2, f, inside),
        _plane_through(apex, f, b1, inside),
        _cap(s, n),
    ]
    head = Polyhedron(np.array([p[0] for p in planes]), np.array([p[1] for p in planes]))
    pieces = [head]
    tail_end = None
    if tail_um > 0:
        start = s - 0.6 * depth_um * n
        tail_end = s + (0.55 * w + tail_um) * d + 0.02 * depth_um * n
        # End the groove a little past the tail end, where its bottom is already above
        # the surface, so that its end wall is in the air.
        past_end = tail_end + 0.15 * (tail_end - start)
        pieces.append(groove_segment(start, past_end, n, half_angle_deg=50.0, top_um=s))
    return Wedge(
        face=face,
        centre_um=s,
        normal=n,
        direction=d,
        width_um=float(w),
        depth_um=float(depth_um),
        apex_um=apex,
        rim_um=np.array([b1, b2, f]),
        tail_end_um=tail_end,
        pieces=tuple(pieces),
    )


def chip(
    surface_um: np.ndarray,
    normal: np.ndarray,
    rng: np.random.Generator,
    *,
    size_um: float,
    depth_um: float,
) -> Polyhedron:
    """A flake broken off at S: a tilted fracture plane depth_um deep and flaring walls."""
    n, t1, t2 = _frame(normal, rng.normal(size=3))
    tilt = np.radians(rng.uniform(5, 20))
    phi = rng.uniform(0, 2 * np.pi)
    fracture_n = -(n * np.cos(tilt) + np.sin(tilt) * (np.cos(phi) * t1 + np.sin(phi) * t2))
    bottom = surface_um - depth_um * n
    normals = [fracture_n]
    offsets = [float(fracture_n @ bottom)]
    n_walls = int(rng.integers(4, 7))
    alpha = np.radians(rng.uniform(25, 45))
    for k in range(n_walls):
        ang = 2 * np.pi * (k + rng.uniform(-0.2, 0.2)) / n_walls
        t = np.cos(ang) * t1 + np.sin(ang) * t2
        wall = t * np.cos(alpha) - n * np.sin(alpha)
        reach = size_um * rng.uniform(0.35, 0.6)
        normals.append(wall)
        offsets.append(float(wall @ (surface_um + reach * t)))
    cap_n, cap_c = _cap(surface_um, n)
    normals.append(cap_n)
    offsets.append(cap_c + depth_um)
    return Polyhedron(np.array(normals), np.array(offsets))
