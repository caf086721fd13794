"""Acquisition plans as data: which lights, in which order, expanded into shots.

A plan file (JSON or TOML) holds the fields of :class:`Plan`; missing fields take the
defaults of the paper's standard acquisition (SCAN_BUNDLE.md, "The standard
acquisition"): photometric frames at 8 azimuths, red/green/blue at 4 azimuths,
fringes at 4 azimuths with periods doubling from a quarter of a period across the
projector to 128 periods across it, 4 phase steps each, and a dark frame per
exposure. The same plan run on the white reference target is the calibration.

Shots are ordered to keep the stage still as long as possible (darks first, then
azimuth by azimuth); the first photometric light is shot once more at the very end
as a *check* frame (not part of the bundle) to detect a tablet that moved.
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, NamedTuple

from rig_agent.patterns import CHANNELS, Pattern, ProjectorGeometry

TARGETS = ("object", "reference")


class PlanError(ValueError):
    """A plan file or field is invalid; the message names the field."""


class Light(NamedTuple):
    """One light of a plan; fringe periods as a count across the projector."""

    azimuth_deg: float
    kind: str
    exposure: float
    channel: str | None = None
    periods_across: float | None = None
    phase_deg: float | None = None


@dataclass(frozen=True)
class Plan:
    """The lights of one acquisition (angles in degrees, exposures relative)."""

    name: str = "standard"
    photometric_azimuths_deg: tuple[float, ...] = (0, 45, 90, 135, 180, 225, 270, 315)
    color_azimuths_deg: tuple[float, ...] = (0, 90, 180, 270)
    color_channels: tuple[str, ...] = ("red", "green", "blue")
    fringe_azimuths_deg: tuple[float, ...] = (0, 90, 180, 270)
    fringe_periods_across: tuple[float, ...] = tuple(0.25 * 2**k for k in range(10))
    fringe_phases_deg: tuple[float, ...] = (0, 90, 180, 270)
    fringe_modulation: float = 1.0
    exposure: dict[str, float] = field(
        default_factory=lambda: {"photometric": 1.0, "color": 1.0, "fringe": 1.0}
    )
    averaging: int = 1
    check_frame: bool = True

    def __post_init__(self) -> None:
        _check_plan(self)

    def lights(self) -> list[Light]:
        """Every light of the plan, grouped by azimuth (ascending) in capture order."""
        by_azimuth: dict[float, list[Light]] = {}
        for az in self.photometric_azimuths_deg:
            by_azimuth.setdefault(az, []).append(
                Light(az, "photometric", self.exposure["photometric"])
            )
        for az in self.color_azimuths_deg:
            for channel in self.color_channels:
                by_azimuth.setdefault(az, []).append(
                    Light(az, "color", self.exposure["color"], channel=channel)
                )
        for az in self.fringe_azimuths_deg:
            for across in self.fringe_periods_across:
                for phase in self.fringe_phases_deg:
                    by_azimuth.setdefault(az, []).append(
                        Light(
                            az,
                            "fringe",
                            self.exposure["fringe"],
                            periods_across=across,
                            phase_deg=phase,
                        )
                    )
        return [light for az in sorted(by_azimuth) for light in by_azimuth[az]]

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


@dataclass(frozen=True)
class Shot:
    """One frame to capture: the bundle frame fields plus the spool's bookkeeping."""

    index: int
    key: str  # stable id in the spool's journal
    file: str  # relative POSIX path, as the bundle will name it
    kind: str
    target: str
    azimuth_deg: float | None
    exposure: float
    channel: str | None = None
    period_um: float | None = None
    phase_deg: float | None = None
    modulation: float = 1.0
    role: str = "bundle"  # "bundle" or "check" (kept in the spool, not in the bundle)

    @property
    def pattern(self) -> Pattern:
        if self.kind == "dark":
            return Pattern("dark")
        if self.kind == "photometric":
            return Pattern("white")
        return Pattern(
            self.kind,
            channel=self.channel,
            period_um=self.period_um,
            phase_deg=self.phase_deg,
            modulation=self.modulation,
        )

    def light_key(self) -> tuple:
        """The spec's matching key (kind, azimuth, channel, period, phase) without target."""
        az = None if self.azimuth_deg is None else round(self.azimuth_deg % 360.0, 6)
        period = None if self.period_um is None else round(self.period_um, 6)
        phase = None if self.phase_deg is None else round(self.phase_deg % 360.0, 6)
        return (self.kind, az, self.channel, period, phase)

    def manifest_frame(self) -> dict[str, Any]:
        """The frame entry of manifest.json for this shot."""
        frame: dict[str, Any] = {"file": self.file, "kind": self.kind, "target": self.target}
        if self.kind != "dark":
            frame["azimuth_deg"] = self.azimuth_deg
        if self.channel is not None:
            frame["channel"] = self.channel
        if self.kind == "fringe":
            frame["period_um"] = self.period_um
            frame["phase_deg"] = self.phase_deg
        frame["exposure"] = self.exposure
        return frame

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Shot:
        return cls(**{f.name: data[f.name] for f in fields(cls) if f.name in data})


def _slug(value: float) -> str:
    return f"{value:.3f}".rstrip("0").rstrip(".").replace("-", "m")


def expand(plan: Plan, geometry: ProjectorGeometry, *, target: str) -> list[Shot]:
    """The ordered shots of ``plan`` on ``target`` for a projector of ``geometry``."""
    if target not in TARGETS:
        raise ValueError(f"target must be one of {TARGETS}, got {target!r}")
    shots: list[Shot] = []

    def add(kind: str, azimuth: float | None, exposure: float, role: str = "bundle", **kw):
        parts = [kind]
        if azimuth is not None:
            parts.append("a" + _slug(azimuth))
        if kw.get("channel"):
            parts.append(kw["channel"])
        if kind == "fringe":
            parts += ["p" + _slug(kw["period_um"]), "d" + _slug(kw["phase_deg"])]
        if kind == "dark" or exposure != 1.0:
            parts.append("e" + _slug(exposure))
        if role == "check":
            parts.append("check")
        key = "_".join(parts)
        index = len(shots)
        shots.append(
            Shot(
                index=index,
                key=key,
                file=f"{target}/{index:04d}_{key}.png",
                kind=kind,
                target=target,
                azimuth_deg=None if azimuth is None else float(azimuth),
                exposure=float(exposure),
                role=role,
                **kw,
            )
        )

    lights = plan.lights()
    for exposure in sorted({light.exposure for light in lights}):
        add("dark", None, exposure)
    for light in lights:
        if light.kind == "fringe":
            period_um = geometry.period_um_for(light.periods_across, azimuth_deg=light.azimuth_deg)
            add(
                "fringe",
                light.azimuth_deg,
                light.exposure,
                period_um=round(period_um, 3),
                phase_deg=float(light.phase_deg),
                modulation=plan.fringe_modulation,
            )
        else:
            add(light.kind, light.azimuth_deg, light.exposure, channel=light.channel)
    if plan.check_frame and target == "object" and plan.photometric_azimuths_deg:
        first = min(plan.photometric_azimuths_deg)
        add("photometric", first, plan.exposure["photometric"], role="check")
    return shots


def load_plan(path: str | Path) -> Plan:
    """Read a plan from a ``.json`` or ``.toml`` file; :class:`PlanError` names the culprit."""
    path = Path(path)
    try:
        text = path.read_bytes()
    except OSError as exc:
        raise PlanError(f"cannot read the plan file {str(path)!r}: {exc.strerror}") from exc
    try:
        if path.suffix.lower() == ".toml":
            data = tomllib.loads(text.decode("utf-8"))
        else:
            data = json.loads(text)
    except (ValueError, UnicodeDecodeError) as exc:
        raise PlanError(f"the plan file {str(path)!r} is not valid: {exc}") from exc
    return plan_from_dict(data, where=str(path))


def plan_from_dict(data: Any, *, where: str = "plan") -> Plan:
    if not isinstance(data, dict):
        raise PlanError(f"{where}: a plan must be an object/table of fields")
    known = {f.name for f in fields(Plan)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise PlanError(
            f"{where}: unknown field {unknown[0]!r} (known: {', '.join(sorted(known))})"
        )
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
    if "exposure" in values:
        values["exposure"] = {**Plan().exposure, **values["exposure"]}
    try:
        return Plan(**values)
    except PlanError as exc:
        raise PlanError(f"{where}: {exc}") from None


def _check_plan(plan: Plan) -> None:
    def numbers(name: str, *, positive: bool = False) -> None:
        values = getattr(plan, name)
        if not isinstance(values, tuple):
            raise PlanError(f"{name} must be a list of numbers")
        for v in values:
            ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
            if not ok or (positive and v <= 0):
                raise PlanError(
                    f"{name} must hold finite {'positive ' if positive else ''}numbers, got {v!r}"
                )
        if len(set(values)) != len(values):
            raise PlanError(f"{name} holds a value twice")

    for name in ("photometric_azimuths_deg", "color_azimuths_deg", "fringe_azimuths_deg"):
        numbers(name)
    numbers("fringe_periods_across", positive=True)
    numbers("fringe_phases_deg")
    if plan.fringe_azimuths_deg and plan.fringe_periods_across:
        phases = sorted(p % 360 for p in plan.fringe_phases_deg)
        if phases != [0, 90, 180, 270]:
            raise PlanError("fringe_phases_deg must be 0, 90, 180 and 270 (SCAN_BUNDLE.md)")
    for channel in plan.color_channels:
        if channel not in CHANNELS:
            raise PlanError(f"color_channels: {channel!r} is not one of {tuple(CHANNELS)}")
    if not isinstance(plan.exposure, dict):
        raise PlanError("exposure must be a table of kind = relative exposure")
    for kind in ("photometric", "color", "fringe"):
        value = plan.exposure.get(kind)
        if not isinstance(value, int | float) or isinstance(value, bool) or not value > 0:
            raise PlanError(f"exposure.{kind} must be a number > 0, got {value!r}")
    if not 0 < plan.fringe_modulation <= 1:
        raise PlanError(f"fringe_modulation must be in (0, 1], got {plan.fringe_modulation!r}")
    if (
        isinstance(plan.averaging, bool)
        or not isinstance(plan.averaging, int)
        or plan.averaging < 1
    ):
        raise PlanError(f"averaging must be a positive integer, got {plan.averaging!r}")


def quick_plan() -> Plan:
    """A small plan for tests and the simulated rig: 4 photometric, 1 colour set, 2×3 fringe sets."""
    return Plan(
        name="quick",
        photometric_azimuths_deg=(0, 90, 180, 270),
        color_azimuths_deg=(0,),
        fringe_azimuths_deg=(0, 90),
        fringe_periods_across=(2.0, 8.0, 32.0),
    )
