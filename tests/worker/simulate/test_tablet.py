"""Synthetic tablet geometry: ground truth consistency, poses, determinism, mesh."""

from __future__ import annotations

import numpy as np
import pytest

from worker.simulate.mesh import tablet_mesh
from worker.simulate.tablet import FACE_POSES, make_tablet
from worker.simulate.view import render_view

S_UM = 26.8  # the paper's pixel


@pytest.fixture(scope="module")
def tablet():
    return make_tablet(2)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def test_gt_normals_agree_with_finite_differences_of_gt_height(tablet):
    # A 2.6 × 2.1 mm window of the obverse at the paper's pixel, with wedges and a ruling.
    view = render_view(
        tablet,
        FACE_POSES["obverse"],
        width=96,
        height=80,
        pixel_size_um=S_UM,
        supersample=2,
        centre_um=(-3000.0, -2000.0),
    )
    gt = view.ground_truth()
    assert gt["mask"].all()
    h, n = gt["height"].astype(np.float64), gt["normals"].astype(np.float64)
    gx = (h[1:-1, 2:] - h[1:-1, :-2]) / (2 * S_UM)
    gy = (h[2:, 1:-1] - h[:-2, 1:-1]) / (2 * S_UM)
    fd = np.stack([-gx, -gy, -np.ones_like(gx)], -1)
    fd /= np.linalg.norm(fd, axis=-1, keepdims=True)
    centre = n[1:-1, 1:-1]
    # Across a crease (wedge edge) a central difference straddles two facets and legitimately
    # differs from the pixel's mean slope: leave out pixels whose neighbours' normals jump > 3°.
    crease = np.zeros(centre.shape[:2], bool)
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        neighbour = n[1 + dy : n.shape[0] - 1 + dy, 1 + dx : n.shape[1] - 1 + dx]
        crease |= _angle_deg(centre, neighbour) > 3.0
    assert crease.mean() < 0.3  # most of the window is tested
    assert crease.mean() > 0.01  # and it does hold wedges
    err = _angle_deg(fd, centre)[~crease]
    # Bound: for a roughness term a·sin(kx) the central difference of box means and the box
    # mean of the slope differ by a·k·(ks)²/6; with a·k <= 0.0126 and λ >= 300 µm (ks <= 0.56)
    # that is <= 6.7e-4 rad per term, <= 0.011 rad = 0.6° for all 16 terms together.
    assert err.max() < 0.6


@pytest.mark.parametrize("face", list(FACE_POSES))
def test_each_face_is_seen_with_h0_midway(tablet, face):
    view = render_view(
        tablet, FACE_POSES[face], width=40, height=32, pixel_size_um=857.6, supersample=1
    )
    h = view.height_ss_um[view.tablet_ss]
    assert 0.15 < view.tablet_ss.mean() < 0.95
    assert h.max() == pytest.approx(-h.min(), abs=1.0)
    assert np.all(view.normals_ss[..., 2] < 0)  # every visible normal faces the camera
    # The face's outward normal maps to -z: the visible centre of the face is its highest part.
    centre_h = view.height_ss_um[16, 20]
    assert centre_h > np.percentile(h, 60)
    assert np.all(view.height_ss_um[~view.tablet_ss] < h.min())  # support lies behind


def test_same_seed_same_tablet_other_seed_other_tablet():
    a, b, c = make_tablet(5), make_tablet(5), make_tablet(6)
    assert np.array_equal(a.cavities.offsets_um, b.cavities.offsets_um)
    assert len(a.wedges) == len(b.wedges) > 20
    assert a.cavities.offsets_um.shape != c.cavities.offsets_um.shape or not np.array_equal(
        a.cavities.offsets_um, c.cavities.offsets_um
    )


def test_wedges_are_within_spec_ranges(tablet):
    widths = np.array([w.width_um for w in tablet.wedges])
    depths = np.array([w.depth_um for w in tablet.wedges])
    assert widths.min() >= 1000 and widths.max() <= 3000
    assert depths.min() >= 100 and depths.max() <= 600
    for w in tablet.wedges[:10]:  # the apex lies depth_um below the tangent plane at the centre
        assert (w.centre_um - w.apex_um) @ w.normal == pytest.approx(w.depth_um)


def test_mesh_is_closed_and_tablet_sized(tablet):
    mesh = tablet_mesh(tablet, resolution=20)
    assert mesh.is_watertight
    extents = mesh.bounding_box.extents  # mm
    assert extents[0] == pytest.approx(28.0, abs=1.0)
    assert extents[1] == pytest.approx(22.0, abs=1.0)
    assert 0 < mesh.volume < 28 * 22 * 13
