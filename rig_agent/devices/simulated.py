"""Simulated camera: renders what the current light and pattern would show.

:class:`SimulatedCamera` asks the stage where the light arm is (``position()`` — over
the serial link when the stage is the GRBL emulator) and the projector what it shows,
and hands both to a renderer. :class:`SimulatorScene` is the renderer built on
``worker.simulate`` (the same forward model the simulator's bundles use): a synthetic
tablet (or a flat white reference target) seen by an orthographic camera.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from rig_agent.devices.base import Camera, DeviceError, Stage
from rig_agent.devices.projector import PatternProjector
from rig_agent.patterns import Pattern

Renderer = Callable[..., np.ndarray]
_KIND = {"white": "photometric", "color": "color", "fringe": "fringe", "dark": "dark"}


class SimulatedCamera(Camera):
    """A camera whose frames are rendered for the stage's azimuth and the projector's pattern.

    ``renderer(pattern=, azimuth_deg=, target=, exposure=, rng=)`` returns stored values
    (H, W); ``target`` is what lies on the stage (``object`` or ``reference``).
    """

    def __init__(
        self,
        *,
        stage: Stage,
        projector: PatternProjector,
        renderer: Renderer,
        width: int,
        height: int,
        bit_depth: int,
        target: str = "object",
        seed: int = 0,
    ) -> None:
        self.stage, self.projector, self.renderer = stage, projector, renderer
        self.width, self.height, self.bit_depth = width, height, bit_depth
        self.target = target
        self.exposure = 1.0
        self.rng = np.random.default_rng(seed)
        self.frames_taken = 0

    def set_exposure(self, exposure: float) -> None:
        if not exposure > 0:
            raise ValueError(f"exposure must be > 0, got {exposure!r}")
        self.exposure = float(exposure)

    def capture(self) -> np.ndarray:
        pattern = self.projector.current
        if pattern is None:
            raise DeviceError("the simulated camera needs the projector to show a pattern first")
        azimuth_deg = self.stage.position().azimuth_deg
        self.frames_taken += 1
        return self.renderer(
            pattern=pattern,
            azimuth_deg=azimuth_deg,
            target=self.target,
            exposure=self.exposure,
            rng=self.rng,
        )

    def close(self) -> None:
        pass


class SimulatorScene:
    """Renderer on ``worker.simulate``: a synthetic tablet of ``seed`` — or the triangle mesh
    file ``mesh`` (mm) — with ``face`` toward the camera, and the white reference target
    (rendered by the simulator's own reference model).

    Image size and sampling as the camera settings; ``noise`` is a preset of
    ``worker.simulate`` (``clean``, ``default``, ``hard``).
    """

    def __init__(
        self,
        *,
        width: int,
        height: int,
        pixel_size_um: float,
        polar_deg: float,
        seed: int = 0,
        noise: str = "default",
        supersample: int = 2,
        face: str = "obverse",
        mesh: str | None = None,
    ) -> None:
        from worker.simulate.noise import noise_model
        from worker.simulate.rig import Rig

        self.polar_deg = polar_deg
        self.noise = noise_model(noise)
        self.bit_depth = self.noise.bit_depth
        self.rig = Rig(
            seed,
            width * pixel_size_um,
            height * pixel_size_um,
            irradiance_variation=self.noise.irradiance_variation,
        )
        self.reflectance = self.rig.reflectance_reference
        self._geometry = (width, height, pixel_size_um, supersample)
        self._seed = seed
        self._face = face
        self._mesh = mesh
        self._views: dict[str, Any] = {}

    def view(self, target: str) -> Any:
        if target not in self._views:
            from worker.simulate.view import flat_view

            width, height, pixel_size_um, supersample = self._geometry
            if target == "reference":
                self._views[target] = flat_view(
                    width, height, pixel_size_um, supersample, albedo=self.reflectance
                )
            else:
                self._views[target] = self._object_view()
        return self._views[target]

    def _object_view(self) -> Any:
        from worker.simulate.tablet import FACE_POSES

        width, height, pixel_size_um, supersample = self._geometry
        pose = FACE_POSES.get(self._face, np.eye(3))
        grid = {"width": width, "height": height, "pixel_size_um": pixel_size_um}
        if self._mesh is not None:
            from worker.simulate.meshview import load_mesh, render_mesh_view

            return render_mesh_view(load_mesh(self._mesh), pose, supersample=supersample, **grid)
        from worker.simulate.tablet import make_tablet
        from worker.simulate.view import render_view

        return render_view(make_tablet(self._seed), pose, supersample=supersample, **grid)

    def __call__(
        self,
        *,
        pattern: Pattern,
        azimuth_deg: float,
        target: str,
        exposure: float,
        rng: np.random.Generator,
    ) -> np.ndarray:
        from worker.simulate.rig import FrameSpec, render_frame

        kind = _KIND[pattern.kind]
        spec = FrameSpec(
            kind=kind,
            target=target,
            azimuth_deg=None if kind == "dark" else float(azimuth_deg),
            polar_deg=self.polar_deg,
            channel=pattern.channel,
            period_um=pattern.period_um,
            phase_deg=pattern.phase_deg,
            exposure=exposure,
        )
        return render_frame(self.view(target), spec, self.noise, rng, rig=self.rig)
