"""Projector patterns against the fringe formula of SCAN_BUNDLE.md."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rig_agent.patterns import (
    Pattern,
    ProjectorGeometry,
    fringe_intensity,
    render_pattern,
    to_levels,
)

GEOMETRY = ProjectorGeometry(width=64, height=48, pixel_size_um=50.0, bit_depth=8)


@pytest.mark.parametrize("azimuth_deg", [0.0, 30.0, 90.0, 225.0])
@pytest.mark.parametrize("phase_deg", [0.0, 90.0, 180.0, 270.0])
def test_fringe_levels_follow_the_spec_formula(azimuth_deg, phase_deg):
    period_um = 700.0
    pattern = Pattern("fringe", period_um=period_um, phase_deg=phase_deg, modulation=0.8)
    image = render_pattern(pattern, GEOMETRY, azimuth_deg=azimuth_deg)
    assert image.shape == (48, 64, 3) and image.dtype == np.uint8
    phi = math.radians(azimuth_deg)
    for r, c in [(0, 0), (5, 17), (47, 63), (30, 2)]:
        u_dot_q = math.sin(phi) * c * 50.0 + math.cos(phi) * r * 50.0
        expected = (
            255
            * (1 + 0.8 * math.cos(2 * math.pi * u_dot_q / period_um + math.radians(phase_deg)))
            / 2
        )
        # Rounding to integer levels: at most half a level off.
        assert abs(float(image[r, c, 0]) - expected) <= 0.5
        assert image[r, c, 0] == image[r, c, 1] == image[r, c, 2]


def test_fringes_vary_only_along_u():
    at_0 = fringe_intensity(GEOMETRY, azimuth_deg=0.0, period_um=400.0, phase_deg=0.0)
    at_90 = fringe_intensity(GEOMETRY, azimuth_deg=90.0, period_um=400.0, phase_deg=0.0)
    # φ = 0: u = (0, 1) — constant along each row; φ = 90°: u = (1, 0) — constant down columns.
    assert np.ptp(at_0, axis=1).max() < 1e-12 and np.ptp(at_0, axis=0).max() > 0.9
    assert np.ptp(at_90, axis=0).max() < 1e-12 and np.ptp(at_90, axis=1).max() > 0.9


def test_four_phase_steps_sum_to_a_constant():
    steps = [
        fringe_intensity(GEOMETRY, azimuth_deg=40.0, period_um=333.0, phase_deg=d, modulation=0.6)
        for d in (0, 90, 180, 270)
    ]
    # cos θ + cos(θ+π/2) + cos(θ+π) + cos(θ+3π/2) = 0, so Σ (1 + m cos)/2 = 2.
    np.testing.assert_allclose(sum(steps), 2.0, atol=1e-12)


def test_solid_patterns():
    white = render_pattern(Pattern("white"), GEOMETRY, azimuth_deg=0)
    assert (white == 255).all()
    green = render_pattern(Pattern("color", channel="green"), GEOMETRY, azimuth_deg=0)
    assert (green[..., 1] == 255).all() and (green[..., [0, 2]] == 0).all()
    assert not render_pattern(Pattern("dark"), GEOMETRY, azimuth_deg=0).any()


def test_sixteen_bit_and_gamma_precompensation():
    geometry = ProjectorGeometry(width=8, height=8, pixel_size_um=10.0, bit_depth=16, gamma=2.2)
    intensity = np.linspace(0, 1, 64).reshape(8, 8)
    levels = to_levels(intensity, geometry)
    assert levels.dtype == np.uint16
    emitted = (levels / 65535.0) ** 2.2
    # Half a level of rounding, through the display curve d(v^γ)/dv = γ·v^(γ−1) ≤ γ.
    assert np.abs(emitted - intensity).max() <= 2.2 * 0.5 / 65535


def test_periods_across_the_projector():
    # φ = 90°: u runs along the 64 columns, so the span is 64 · 50 µm.
    assert GEOMETRY.period_um_for(0.25, azimuth_deg=90) == pytest.approx(64 * 50 / 0.25)
    assert GEOMETRY.period_um_for(128, azimuth_deg=0) == pytest.approx(48 * 50 / 128)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"kind": "fringe", "period_um": 0, "phase_deg": 0}, "period_um"),
        ({"kind": "fringe", "period_um": 10, "phase_deg": None}, "phase_deg"),
        ({"kind": "fringe", "period_um": 10, "phase_deg": 0, "modulation": 1.5}, "modulation"),
        ({"kind": "color", "channel": "cyan"}, "channel"),
        ({"kind": "strobe"}, "kind"),
    ],
)
def test_bad_patterns_name_the_field(kwargs, name):
    with pytest.raises(ValueError, match=name):
        Pattern(**kwargs)


def test_bad_geometry_names_the_field():
    with pytest.raises(ValueError, match="bit_depth"):
        ProjectorGeometry(width=8, height=8, pixel_size_um=1.0, bit_depth=17)
    with pytest.raises(ValueError, match="width"):
        ProjectorGeometry(width=0, height=8, pixel_size_um=1.0)
