"""Forward model of the scanner: synthetic tablets, frames per SCAN_BUNDLE.md, ground truth.

See docs/simulator.md. ``simulate_scan`` writes a bundle plus ground truth;
``render_frame`` renders one frame for the rig agent's simulated camera.
"""

from worker.simulate.noise import NOISE_PRESETS, NoiseModel, noise_model
from worker.simulate.physics import (
    PHYSICS_VARIANTS,
    Physics,
    draw_physics,
    physics_from_dict,
    physics_to_dict,
)
from worker.simulate.rig import FrameSpec, Rig, frame_radiance, render_frame
from worker.simulate.scan import SimulationResult, simulate_scan
from worker.simulate.tablet import FACE_POSES, FACES, Tablet, make_tablet
from worker.simulate.view import View, flat_view, render_view

__all__ = [
    "FACES",
    "FACE_POSES",
    "NOISE_PRESETS",
    "FrameSpec",
    "NoiseModel",
    "PHYSICS_VARIANTS",
    "Physics",
    "Rig",
    "SimulationResult",
    "Tablet",
    "View",
    "draw_physics",
    "flat_view",
    "frame_radiance",
    "make_tablet",
    "noise_model",
    "physics_from_dict",
    "physics_to_dict",
    "render_frame",
    "render_view",
    "simulate_scan",
]
