"""Open the rig's devices from the settings: real hardware or the simulated rig."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from rig_agent.devices.base import Camera, Projector, Stage
from rig_agent.devices.projector import HeadlessProjector
from rig_agent.devices.stage import GrblStage
from rig_agent.devices.transport import SerialLink
from rig_agent.patterns import ProjectorGeometry
from rig_agent.settings import Settings


@dataclass
class Devices:
    stage: Stage
    camera: Camera
    projector: Projector
    reference_reflectance: float | None = None  # known by a simulated rig
    owned: list[Any] = field(default_factory=list)  # e.g. the emulator to stop on close

    def close(self) -> None:
        for device in (self.projector, self.camera, self.stage, *self.owned):
            closer = getattr(device, "close", None) or device.stop
            closer()


def projector_geometry(settings: Settings) -> ProjectorGeometry:
    return ProjectorGeometry(
        width=settings.projector_width,
        height=settings.projector_height,
        pixel_size_um=settings.projector_pixel_size_um,
        bit_depth=settings.projector_bit_depth,
        gamma=settings.projector_gamma,
    )


def _stage(settings: Settings, url: str) -> GrblStage:
    return GrblStage(
        SerialLink(url),
        azimuth_axis=settings.azimuth_axis,
        elevation_axis=settings.elevation_axis,
        motion_timeout_s=settings.motion_timeout_s,
    )


def open_devices(settings: Settings, *, target: str, face: str | None = None) -> Devices:
    """Connect the stage, camera and projector; ``target`` and ``face`` matter to the
    simulated camera only (a real camera sees what lies on the stage)."""
    if settings.devices == "sim":
        return _open_simulated(settings, target=target, face=face or "obverse")
    from rig_agent.devices.camera import OpenCVCamera

    stage = _stage(settings, settings.stage_url)
    stage.connect()
    camera = None
    try:
        device = (
            int(settings.camera_device)
            if settings.camera_device.isdigit()
            else settings.camera_device
        )
        camera = OpenCVCamera(
            device,
            width=settings.camera_width,
            height=settings.camera_height,
            base_exposure=settings.camera_base_exposure,
        )
        projector = open_projector(settings)
    except BaseException:
        if camera is not None:
            camera.close()
        stage.close()
        raise
    return Devices(stage=stage, camera=camera, projector=projector)


def open_projector(settings: Settings) -> Projector:
    """The real rig's projector output, as ``projector_display`` says."""
    geometry = projector_geometry(settings)
    if settings.projector_display == "none":
        return HeadlessProjector(geometry)
    from rig_agent.devices.display import WindowProjector

    return WindowProjector(
        geometry,
        screen=settings.projector_screen,
        settle_s=settings.projector_settle_ms / 1000.0,
    )


def _open_simulated(settings: Settings, *, target: str, face: str) -> Devices:
    from rig_agent.devices.grbl_emulator import GrblEmulator
    from rig_agent.devices.simulated import SimulatedCamera, SimulatorScene

    scene = SimulatorScene(
        width=settings.camera_width,
        height=settings.camera_height,
        pixel_size_um=settings.pixel_size_um,
        polar_deg=settings.polar_deg,
        seed=settings.sim_seed,
        noise=settings.sim_noise,
        mesh=settings.sim_mesh or None,
        face=face
        if face in ("obverse", "reverse", "top", "bottom", "left", "right")
        else "obverse",
    )
    emulator = GrblEmulator().start()
    stage = _stage(settings, emulator.port)
    stage.poll_interval_s = 0.005
    stage.connect()
    projector = HeadlessProjector(projector_geometry(settings), render_images=False)
    camera = SimulatedCamera(
        stage=stage,
        projector=projector,
        renderer=scene,
        width=settings.camera_width,
        height=settings.camera_height,
        bit_depth=scene.bit_depth,
        target=target,
        seed=settings.sim_seed,
    )
    return Devices(
        stage=stage,
        camera=camera,
        projector=projector,
        reference_reflectance=scene.reflectance,
        owned=[emulator],
    )
