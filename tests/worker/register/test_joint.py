"""Silhouette consistency (worker.register.joint) on the simulator's true heights: a face
sunk into the tablet stays inside every silhouette (the visual hull) but puts its neighbours'
points in front of its own view's surface, which the score counts (issue 8's one wrong-pose
case that the hull alone accepted: the reverse tilted 16.8° into the tablet)."""

from __future__ import annotations

import dataclasses

import numpy as np

from worker.register.joint import silhouette_consistency

from .synthetic import simulated_scans


def _blind(scan):
    """The scan without heights: only its silhouette is compared (the visual hull alone)."""
    g = scan.grid
    return dataclasses.replace(scan, grid=dataclasses.replace(g, height_um=g.height_um * np.nan))


def test_a_face_sunk_into_the_tablet_is_inconsistent():
    _, scans, truths, pixel_um = simulated_scans(size=(160, 128))
    k = [s.face for s in scans].index("reverse")
    # +z of a view is away from its camera: the reverse 5 pixels deep into the tablet, more
    # than the 2-pixel tolerance, so the edges' points along its rim lie in front of it.
    sunk = list(truths)
    shift = np.eye(4)
    shift[2, 3] = 5 * pixel_um / 1000
    sunk[k] = truths[k] @ shift
    blind = [_blind(s) for s in scans]

    def score(s, t):
        return silhouette_consistency(s, t, k, tolerance_px=2.0)

    # The hull alone does not see it (its points move inward, the outline does not change)...
    assert score(blind, sunk) >= score(blind, truths)
    # ...the views' surfaces do: the neighbours' rim bands (a few pixels wide on each of the
    # four edges, a few % of the points compared) are now in front of the reverse.
    assert score(scans, sunk) < score(scans, truths) - 0.01
