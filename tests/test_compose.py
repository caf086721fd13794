"""docker-compose.yml: valid with .env.example (Debian's docker-compose 1.29, no engine needed),
refuses to start without a secret and names it, and passes only settings that exist."""

from __future__ import annotations

import os
import secrets
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml
from pydantic import ValidationError

from backend.settings import Settings

REPO = Path(__file__).resolve().parent.parent
COMPOSE = REPO / "docker-compose.yml"
ENV_EXAMPLE = REPO / ".env.example"
SECRETS = ("HAMMURABI_SECRET_KEY", "POSTGRES_PASSWORD", "MINIO_ROOT_USER", "MINIO_ROOT_PASSWORD")


def _compose(env_file: Path, cwd: Path) -> subprocess.CompletedProcess:
    exe = shutil.which("docker-compose")
    assert exe, "docker-compose is not installed (scripts/setup.sh installs Debian's)"
    # A clean environment: values must come from the env file, not from this shell.
    env = {k: v for k, v in os.environ.items() if k not in SECRETS and not k.startswith("S3_")}
    return subprocess.run(
        [exe, "--env-file", str(env_file), "-f", str(COMPOSE), "config"],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )


def _env_lines(drop: str | None = None) -> str:
    lines = ENV_EXAMPLE.read_text().splitlines()
    return "\n".join(x for x in lines if not (drop and x.startswith(f"{drop}="))) + "\n"


def test_config_is_valid_with_env_example(tmp_path):
    result = _compose(ENV_EXAMPLE, tmp_path)
    assert result.returncode == 0, result.stderr
    config = yaml.safe_load(result.stdout)
    assert {"postgres", "redis", "minio", "minio-init", "backend", "worker"} <= set(
        config["services"]
    )
    # The worker scales (--scale worker=N): no fixed container name or host port.
    worker = config["services"]["worker"]
    assert "container_name" not in worker and "ports" not in worker
    for name in ("postgres", "redis", "minio", "backend", "worker"):
        assert "healthcheck" in config["services"][name], name


@pytest.mark.parametrize("secret", SECRETS)
def test_a_missing_secret_fails_and_is_named(tmp_path, secret):
    env_file = tmp_path / ".env"
    env_file.write_text(_env_lines(drop=secret))
    result = _compose(env_file, tmp_path)
    assert result.returncode != 0
    assert secret in result.stderr


def test_environment_names_are_settings_fields():
    config = yaml.safe_load(COMPOSE.read_text())
    fields = set(Settings.model_fields)
    names = set()
    for service in config["services"].values():
        env = service.get("environment") or {}
        names |= {k for k in (env if isinstance(env, dict) else [e.split("=")[0] for e in env])}
    for line in ENV_EXAMPLE.read_text().splitlines():
        if "=" in line and not line.lstrip().startswith("#"):
            names.add(line.split("=", 1)[0].strip())
    ours = {n for n in names if n.startswith("HAMMURABI_")}
    assert ours, "the compose file configures the service through HAMMURABI_* variables"
    unknown = sorted(n for n in ours if n.removeprefix("HAMMURABI_").lower() not in fields)
    assert unknown == [], f"not fields of backend.settings.Settings: {unknown}"


def _library_environment(env_file: Path, tmp_path: Path) -> dict[str, str]:
    result = _compose(env_file, tmp_path)
    assert result.returncode == 0, result.stderr
    env = yaml.safe_load(result.stdout)["services"]["backend"]["environment"]
    return {k: str(v) for k, v in env.items()}


def _settings_from(env: dict[str, str], monkeypatch) -> Settings:
    for name in [n for n in os.environ if n.startswith("HAMMURABI_")]:
        monkeypatch.delenv(name)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    return Settings(_env_file=None)


def test_env_example_is_refused_by_the_library(tmp_path, monkeypatch):
    """`cp .env.example .env && docker compose up` must not start with its placeholders."""
    env = _library_environment(ENV_EXAMPLE, tmp_path)
    assert env["HAMMURABI_ENVIRONMENT"] == "production"
    with pytest.raises(ValidationError) as caught:
        _settings_from(env, monkeypatch)
    message = str(caught.value)
    for name in ("HAMMURABI_SECRET_KEY", "HAMMURABI_S3_SECRET_ACCESS_KEY", "DATABASE_URL"):
        assert name in message


def test_generated_secrets_are_accepted_by_the_library(tmp_path, monkeypatch):
    values = {
        "HAMMURABI_SECRET_KEY": secrets.token_urlsafe(48),
        "POSTGRES_PASSWORD": secrets.token_urlsafe(24),
        "MINIO_ROOT_PASSWORD": secrets.token_urlsafe(24),
    }
    lines = [
        f"{line.split('=')[0]}={values[line.split('=')[0]]}"
        if line.split("=")[0] in values
        else line
        for line in _env_lines().splitlines()
    ]
    env_file = tmp_path / ".env"
    env_file.write_text("\n".join(lines) + "\n")
    settings = _settings_from(_library_environment(env_file, tmp_path), monkeypatch)
    assert settings.signing_secret == values["HAMMURABI_SECRET_KEY"]


def test_every_secret_value_of_env_example_is_refused():
    """The policy's own list must cover the file it ships with (read here, never in code)."""
    from backend.secret_policy import secret_problem

    for line in ENV_EXAMPLE.read_text().splitlines():
        name, _, value = line.partition("=")
        if not line.startswith("#") and any(w in name for w in ("SECRET", "PASSWORD")):
            problem = secret_problem(value)
            assert problem is not None and "placeholder" in problem, (name, value)
