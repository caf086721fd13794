"""Seams blended where the whole tablet's faces overlap (`worker.register.blend`): two faces
hold the same normals and albedo wherever they overlap (so the viewer's change of face shows no
seam), a face lends nothing to a surface it did not see (no double relief), and away from
the overlaps each face keeps its own measurement."""

from __future__ import annotations

import numpy as np
import pytest

from worker.register.blend import FaceGrid, blend_faces, face_weight
from worker.simulate.acquisition import pixel_size_for
from worker.simulate.tablet import FACE_POSES, make_tablet
from worker.simulate.view import render_view

from .synthetic import truth_transform

SIZE = (128, 104)


@pytest.fixture(scope="module")
def views():
    tablet = make_tablet(0)
    pixel = pixel_size_for(*SIZE)
    out = {}
    for face in ("obverse", "top", "reverse"):
        view = render_view(
            tablet,
            FACE_POSES[face],
            width=SIZE[0],
            height=SIZE[1],
            pixel_size_um=pixel,
            supersample=2,
        )
        out[face] = (view, view.ground_truth())
    return out


def _grid(view, gt, *, albedo_gain: float = 1.0) -> FaceGrid:
    albedo = 255.0 * np.clip(np.nan_to_num(gt["albedo"]), 0, 1) ** (1 / 2.2) * albedo_gain
    return FaceGrid(
        gt["height"],
        gt["normals"],
        gt["mask"],
        albedo,
        view.pixel_size_um,
        truth_transform(view.pose, view.translation_um),
    )


def _overlap(view_a, gt_a, view_b, gt_b):
    """Pixels of A that B saw, and where on B's grid (nearest pixel), from the simulator's own
    poses (X_view = pose·X + t): independent of the blend's transforms."""
    s = view_a.pixel_size_um
    rows, cols = np.nonzero(gt_a["mask"])
    p_view = np.stack([cols * s, rows * s, -gt_a["height"][rows, cols]], 1)
    x_tab = (p_view - view_a.translation_um) @ view_a.pose  # pose is a rotation: inverse = ᵀ
    q = x_tab @ view_b.pose.T + view_b.translation_um
    rb, cb = np.rint(q[:, 1] / s).astype(int), np.rint(q[:, 0] / s).astype(int)
    inside = (rb >= 0) & (rb < SIZE[1]) & (cb >= 0) & (cb < SIZE[0])
    rows, cols, rb, cb, depth = rows[inside], cols[inside], rb[inside], cb[inside], -q[inside, 2]
    seen = gt_b["mask"][rb, cb] & (np.abs(gt_b["height"][rb, cb] - depth) < 2 * s)
    return rows[seen], cols[seen], rb[seen], cb[seen]


def test_overlapping_faces_agree_so_the_change_of_face_shows_no_seam(views):
    (va, ga), (vb, gb) = views["obverse"], views["top"]
    # The top was exposed brighter (a quarter more): a hard seam would show that step.
    a, b = _grid(va, ga), _grid(vb, gb, albedo_gain=1.25)
    (na, alb_a), (nb, alb_b) = blend_faces([a, b])
    wa = face_weight(ga["normals"], ga["mask"], pixel_size_um=va.pixel_size_um)
    wb = face_weight(gb["normals"], gb["mask"], pixel_size_um=vb.pixel_size_um)
    rows, cols, rb, cb = _overlap(va, ga, vb, gb)
    both = (wa[rows, cols] > 0.05) & (wb[rb, cb] > 0.05)  # where either face may be drawn
    assert both.sum() > 40, "the obverse and the top edge should overlap on the rim"
    rows, cols, rb, cb = rows[both], cols[both], rb[both], cb[both]

    # Unblended, the faces differ there by the exposure step: what a hard seam shows.
    step = np.abs(a.albedo[rows, cols] - b.albedo[rb, cb]).mean()
    assert step > 10
    # Blended, both faces carry the same albedo and normals there (nearest-pixel lookup
    # and a steep rim leave a few levels and degrees).
    diff = np.abs(alb_a[rows, cols] - alb_b[rb, cb]).mean(axis=1)
    assert np.median(diff) < 0.2 * step and np.percentile(diff, 90) < 0.4 * step
    to_a = vb.pose @ va.pose.T  # top's view frame → the obverse's: normals compared in A
    nb_in_a = nb[rb, cb] @ to_a
    angle = np.degrees(np.arccos(np.clip(np.sum(na[rows, cols] * nb_in_a, axis=1), -1, 1)))
    assert np.median(angle) < 3.0

    # Far from the overlap each face keeps its own measurement.
    centre = (slice(40, 60), slice(50, 80))
    np.testing.assert_allclose(alb_a[centre], a.albedo[centre], atol=1e-9)
    np.testing.assert_allclose(na[centre], ga["normals"][centre], atol=1e-6)


def test_a_face_lends_nothing_to_a_surface_it_did_not_see(views):
    # The reverse's grid lies right "under" the obverse's: every obverse point projects
    # into it, but the reverse saw the other side. Blending them must leave the obverse's
    # relief alone (no second inscription showing through).
    (va, ga), (vr, gr) = views["obverse"], views["reverse"]
    a, r = _grid(va, ga), _grid(vr, gr)
    (na, alb_a), _ = blend_faces([a, r])
    wa = face_weight(ga["normals"], ga["mask"], pixel_size_um=va.pixel_size_um)
    face_on = wa > 0.1
    assert face_on.sum() > 0.3 * ga["mask"].sum()
    np.testing.assert_allclose(na[face_on], ga["normals"][face_on], atol=1e-6)
    np.testing.assert_allclose(alb_a[face_on], a.albedo[face_on], atol=1e-9)


def test_blend_refuses_mismatched_grids(views):
    va, ga = views["obverse"]
    a = _grid(va, ga)
    bad = FaceGrid(a.height_um[:-1], a.normals, a.mask, None, a.pixel_size_um, a.transform)
    with pytest.raises(ValueError, match="share one"):
        blend_faces([a, bad])
    with pytest.raises(ValueError, match="one per face"):
        blend_faces([a], weights=[])
