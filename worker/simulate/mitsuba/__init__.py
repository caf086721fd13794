"""A second, independent instrument: the scan rendered by Mitsuba 3's path tracer.

``render_scan_mitsuba`` writes the same bundle and ground truth as
``worker.simulate.simulate_scan``; only the light transport differs (docs/simulator.md,
"Mitsuba renderer"). Mitsuba itself is imported on first use (the optional extra
``mitsuba``); without it ``MitsubaUnavailable`` says how to install it.
"""

from worker.simulate.mitsuba.backend import VARIANTS, MitsubaUnavailable, load_mitsuba
from worker.simulate.mitsuba.scan import (
    Clay,
    clay_for,
    diffuse_factor,
    draw_clay,
    render_scan_mitsuba,
)

__all__ = [
    "VARIANTS",
    "Clay",
    "MitsubaUnavailable",
    "clay_for",
    "diffuse_factor",
    "draw_clay",
    "load_mitsuba",
    "render_scan_mitsuba",
]
