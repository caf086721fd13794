"""The rig agent's one settings object: a TOML file, then ``RIG_AGENT_*`` environment variables.

Precedence (later wins): defaults < config file < environment. The config file is
``--config PATH``, else ``$RIG_AGENT_CONFIG``, else ``~/.config/rig-agent/config.toml``
if it exists. Every field ``name`` can be set by ``RIG_AGENT_<NAME>`` (upper case).
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

ENV_PREFIX = "RIG_AGENT_"
DEFAULT_CONFIG = Path("~/.config/rig-agent/config.toml")


class SettingsError(ValueError):
    """A setting is invalid; the message names it and where it came from."""


@dataclass(frozen=True)
class Settings:
    # where scans are kept until the library confirms them
    spool_dir: str = "~/rig-agent-spool"
    # devices: "sim" runs the GRBL emulator, the simulated camera and a headless projector
    devices: str = "hardware"
    stage_url: str = "/dev/ttyACM0"
    azimuth_axis: str = "X"
    elevation_axis: str = "Z"
    elevation_mm: float = 0.0
    motion_timeout_s: float = 120.0
    camera_device: str = "0"
    camera_width: int = 1280
    camera_height: int = 1024
    camera_base_exposure: float = 100.0
    pixel_size_um: float = 26.8
    polar_deg: float = 45.0
    projector_width: int = 1280
    projector_height: int = 800
    projector_pixel_size_um: float = 30.0
    projector_bit_depth: int = 8
    projector_gamma: float = 2.2
    # "window": a borderless fullscreen window on display projector_screen (0 = the first);
    # "none": no output (a light engine driven by other software). The sim rig has none.
    projector_display: str = "window"
    projector_screen: int = 1
    projector_settle_ms: float = 100.0  # after the frame is handed over, before the camera
    reference_reflectance: float = 0.99
    # acquisition plan: "standard", "quick", or the path of a .json/.toml plan file
    plan: str = "standard"
    # the library
    library_url: str = "http://localhost:8000"
    api_token: str = ""
    upload_retries: int = 8
    upload_backoff_s: float = 0.5
    upload_timeout_s: float = 60.0
    # simulated devices
    sim_seed: int = 0
    sim_noise: str = "default"
    sim_mesh: str = ""  # a mesh file (PLY/OBJ/STL, mm) to scan instead of a synthetic tablet

    def __post_init__(self) -> None:
        checks = {
            "devices": self.devices in ("hardware", "sim"),
            "camera_width": self.camera_width > 0,
            "camera_height": self.camera_height > 0,
            "pixel_size_um": self.pixel_size_um > 0,
            "polar_deg": 0 < self.polar_deg < 90,
            "projector_bit_depth": 1 <= self.projector_bit_depth <= 16,
            "projector_display": self.projector_display in ("window", "none"),
            "projector_screen": self.projector_screen >= 0,
            "projector_settle_ms": self.projector_settle_ms >= 0,
            "reference_reflectance": 0 < self.reference_reflectance <= 1,
            "upload_retries": self.upload_retries >= 0,
            "upload_backoff_s": self.upload_backoff_s >= 0,
        }
        for name, ok in checks.items():
            if not ok:
                raise SettingsError(f"setting {name} has an invalid value {getattr(self, name)!r}")

    @property
    def spool_path(self) -> Path:
        return Path(self.spool_dir).expanduser()


def _coerce(name: str, kind: Any, value: Any, source: str) -> Any:
    target = {"int": int, "float": float, "str": str}[
        kind if isinstance(kind, str) else kind.__name__
    ]
    try:
        if isinstance(value, bool) or (target is int and isinstance(value, float)):
            raise TypeError
        return target(value)
    except (TypeError, ValueError):
        raise SettingsError(
            f"setting {name} from {source} must be {target.__name__}, got {value!r}"
        ) from None


def load_settings(
    config: str | Path | None = None, *, environ: dict[str, str] | None = None
) -> Settings:
    """Build the settings from defaults, the config file and the environment."""
    env = dict(os.environ if environ is None else environ)
    types = {f.name: f.type for f in fields(Settings)}
    values: dict[str, Any] = {}
    path = config or env.get(ENV_PREFIX + "CONFIG")
    if path is None and DEFAULT_CONFIG.expanduser().is_file():
        path = DEFAULT_CONFIG.expanduser()
    if path is not None:
        path = Path(path).expanduser()
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except OSError as exc:
            raise SettingsError(
                f"cannot read the config file {str(path)!r}: {exc.strerror}"
            ) from exc
        except tomllib.TOMLDecodeError as exc:
            raise SettingsError(f"the config file {str(path)!r} is not valid TOML: {exc}") from exc
        for key, value in data.items():
            if key not in types:
                raise SettingsError(f"unknown setting {key!r} in {str(path)!r}")
            values[key] = _coerce(key, types[key], value, str(path))
    for key, value in env.items():
        if key.startswith(ENV_PREFIX) and key != ENV_PREFIX + "CONFIG":
            name = key[len(ENV_PREFIX) :].lower()
            if name not in types:
                raise SettingsError(f"unknown setting in environment variable {key}")
            values[name] = _coerce(name, types[name], value, f"${key}")
    return dataclasses.replace(Settings(), **values)
