"""One settings object: defaults < config file < RIG_AGENT_* environment variables."""

from __future__ import annotations

import pytest

from rig_agent.settings import Settings, SettingsError, load_settings


def test_defaults_without_a_file(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    assert load_settings(environ={}) == Settings()


def test_file_then_environment(tmp_path):
    config = tmp_path / "rig.toml"
    config.write_text('stage_url = "/dev/ttyUSB1"\npolar_deg = 40\ncamera_width = 640\n')
    settings = load_settings(config, environ={"RIG_AGENT_POLAR_DEG": "35.5", "OTHER": "x"})
    assert settings.stage_url == "/dev/ttyUSB1"
    assert settings.camera_width == 640
    assert settings.polar_deg == 35.5


def test_projector_output_settings(tmp_path):
    config = tmp_path / "rig.toml"
    config.write_text('projector_display = "none"\nprojector_settle_ms = 250\n')
    settings = load_settings(config, environ={"RIG_AGENT_PROJECTOR_SCREEN": "2"})
    assert settings.projector_display == "none"
    assert settings.projector_screen == 2
    assert settings.projector_settle_ms == 250.0
    # A real rig shows its patterns in a window on the second display by default.
    assert (Settings().projector_display, Settings().projector_screen) == ("window", 1)


def test_config_path_from_the_environment(tmp_path):
    config = tmp_path / "rig.toml"
    config.write_text('api_token = "secret"\n')
    assert load_settings(environ={"RIG_AGENT_CONFIG": str(config)}).api_token == "secret"


@pytest.mark.parametrize(
    ("text", "env", "culprit"),
    [
        ("polar_deg = 95\n", {}, "polar_deg"),
        ("camera_widht = 5\n", {}, "camera_widht"),
        ("camera_width = 1.5\n", {}, "camera_width"),
        ("", {"RIG_AGENT_CAMERA_WIDTH": "wide"}, "RIG_AGENT_CAMERA_WIDTH"),
        ("", {"RIG_AGENT_NOPE": "1"}, "RIG_AGENT_NOPE"),
        ("devices = 'virtual'\n", {}, "devices"),
        ("projector_display = 'hdmi'\n", {}, "projector_display"),
        ("", {"RIG_AGENT_PROJECTOR_SCREEN": "-1"}, "projector_screen"),
        ("projector_settle_ms = -5\n", {}, "projector_settle_ms"),
        ("polar_deg = \n", {}, "not valid TOML"),
    ],
)
def test_bad_settings_name_the_culprit(tmp_path, text, env, culprit):
    config = tmp_path / "rig.toml"
    config.write_text(text)
    with pytest.raises(SettingsError, match=culprit):
        load_settings(config, environ=env)


def test_missing_config_file(tmp_path):
    with pytest.raises(SettingsError, match="cannot read"):
        load_settings(tmp_path / "none.toml", environ={})
