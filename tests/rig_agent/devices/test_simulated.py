"""The simulated camera renders, through worker.simulate, what the stage and projector set up."""

from __future__ import annotations

import numpy as np
import pytest

from rig_agent.devices.base import DeviceError
from rig_agent.devices.grbl_emulator import GrblEmulator
from rig_agent.devices.projector import HeadlessProjector
from rig_agent.devices.simulated import SimulatedCamera, SimulatorScene
from rig_agent.devices.stage import GrblStage
from rig_agent.devices.transport import SerialLink
from rig_agent.patterns import Pattern, ProjectorGeometry
from worker.simulate.noise import noise_model
from worker.simulate.rig import FrameSpec, Rig, render_frame
from worker.simulate.view import flat_view

W, H, PIXEL_UM = 32, 24, 500.0


@pytest.fixture
def rig():
    with GrblEmulator() as emulator:
        stage = GrblStage(SerialLink(emulator.port), poll_interval_s=0.002)
        stage.connect()
        stage.home()
        projector = HeadlessProjector(ProjectorGeometry(width=40, height=30, pixel_size_um=400.0))
        scene = SimulatorScene(width=W, height=H, pixel_size_um=PIXEL_UM, polar_deg=40.0, seed=3)
        camera = SimulatedCamera(
            stage=stage,
            projector=projector,
            renderer=scene,
            width=W,
            height=H,
            bit_depth=scene.bit_depth,
            target="reference",
            seed=5,
        )
        yield stage, projector, camera
        stage.close()


def test_frames_are_the_simulators_for_the_stage_azimuth_and_the_pattern(rig):
    stage, projector, camera = rig
    stage.move_to(azimuth_deg=135.0, elevation_mm=0.0)
    pattern = Pattern("fringe", period_um=4000.0, phase_deg=90.0)
    projector.show(pattern, azimuth_deg=135.0)
    camera.set_exposure(0.5)
    image = camera.capture()
    # The same frame rendered directly by worker.simulate with the same instrument and rng.
    noise = noise_model("default")
    instrument = Rig(3, W * PIXEL_UM, H * PIXEL_UM, irradiance_variation=noise.irradiance_variation)
    spec = FrameSpec(
        kind="fringe",
        target="reference",
        azimuth_deg=135.0,
        polar_deg=40.0,
        period_um=4000.0,
        phase_deg=90.0,
        exposure=0.5,
    )
    view = flat_view(W, H, PIXEL_UM, 2, albedo=instrument.reflectance_reference)
    expected = render_frame(view, spec, noise, np.random.default_rng(5), rig=instrument)
    np.testing.assert_array_equal(image, expected)
    assert projector.image.shape == (30, 40, 3)  # the pattern image was rendered too


def test_the_light_follows_the_arm(rig):
    stage, projector, camera = rig
    projector.show(Pattern("white"), azimuth_deg=0.0)
    frames = {}
    for azimuth in (0.0, 180.0):
        stage.move_to(azimuth_deg=azimuth, elevation_mm=0.0)
        frames[azimuth] = camera.capture().astype(float)

    # The source's irradiance falls off away from it (φ = 0 lights from +y, the bottom rows):
    # bottom/top contrast flips when the arm turns to 180°.
    def bottom_over_top(img):
        return img[-4:].mean() / img[:4].mean()

    assert bottom_over_top(frames[0.0]) > 1.0 > bottom_over_top(frames[180.0])


def test_capture_needs_a_pattern(rig):
    _, projector, camera = rig
    projector.current = None
    with pytest.raises(DeviceError, match="projector"):
        camera.capture()


def test_a_given_mesh_is_scanned(tmp_path):
    import trimesh

    # A 10 × 8 × 2 mm box: in a 32 × 24 px field of 0.5 mm it covers 20 × 16 px in the middle.
    path = tmp_path / "box.ply"
    trimesh.creation.box(extents=(10.0, 8.0, 2.0)).export(path)
    scene = SimulatorScene(
        width=W, height=H, pixel_size_um=PIXEL_UM, polar_deg=40.0, noise="clean", mesh=str(path)
    )
    image = scene(
        pattern=Pattern("white"),
        azimuth_deg=0.0,
        target="object",
        exposure=1.0,
        rng=np.random.default_rng(0),
    ).astype(float)
    # Clay (mean reflectance ≈ 0.34) against black velvet (0.03): the box is much brighter.
    centre, corner = image[8:16, 10:22].mean(), image[:3, :3].mean()
    assert centre > 3 * corner
