"""The hammurabi command: exit 2 with one clear line on errors; the token secret on stdout."""

from __future__ import annotations

import io
import os

import pytest

from backend import crud
from backend.cli import main
from backend.db import make_engine, make_sessionmaker, session_scope
from backend.tables import Role, Tablet


@pytest.fixture
def env(monkeypatch, tmp_path):
    for name in (
        "HAMMURABI_DATABASE_URL",
        "HAMMURABI_ENVIRONMENT",
        "HAMMURABI_SECRET_KEY",
        "HAMMURABI_PUBLIC_URL",
    ):
        # set, then removed: recorded as unset, so whatever a command writes into os.environ
        # (serve writes the public URL) is removed after the test
        monkeypatch.setenv(name, "")
        monkeypatch.delenv(name)
    monkeypatch.setenv("HAMMURABI_DATA_DIR", str(tmp_path / "var"))
    monkeypatch.chdir(tmp_path)  # no stray .env file is read
    return tmp_path / "var" / "hammurabi.db"


def _session(db_path):
    engine = make_engine(f"sqlite:///{db_path}")
    return engine, make_sessionmaker(engine)


def test_create_user_and_token(env, capsys, monkeypatch):
    assert main(["migrate"]) == 0
    monkeypatch.setattr("sys.stdin", io.StringIO("long enough\nignored second line\n"))
    assert main(["create-user", "Ann@Example.org", "--role", "staff", "--institution", "BM",
                 "--password-stdin"]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["create-token", "ann@example.org", "--name", "rig 1"]) == 0
    out, err = capsys.readouterr()
    secret = out.strip()
    assert secret.startswith("hmr_") and "shown only once" in err
    engine, factory = _session(env)
    with session_scope(factory) as session:
        user = crud.user_for_token(session, secret=secret)
        assert (user.email, user.role, user.institution.name) == (
            "ann@example.org",
            Role.staff,
            "BM",
        )
        assert crud.authenticate(session, email="ann@example.org", password="long enough")
    engine.dispose()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["create-user", "a@b.org", "--role", "staff", "--no-password"],
            "--institution is required",
        ),
        (["create-user", "a@b.org", "--role", "reader", "--password-stdin"], "no password"),
        (["create-user", "a@b.org", "--role", "reader"], "--password-stdin"),
        (["create-user", "a@b.org", "--role", "reader", "--password", "long enough"], "`ps`"),
        (["create-token", "nobody@b.org", "--name", "x"], "no user nobody@b.org"),
        (["import-catalogue", "missing.csv"], "missing.csv: no such file"),
    ],
)
def test_errors_exit_2_with_a_clear_line(env, capsys, monkeypatch, argv, message):
    monkeypatch.setattr("sys.stdin", io.StringIO(""))  # no terminal, nothing piped
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_duplicate_user_is_refused(env, capsys):
    assert main(["create-user", "a@b.org", "--role", "reader", "--no-password"]) == 0
    assert main(["create-user", "A@b.org", "--role", "reader", "--no-password"]) == 2
    assert "already exists" in capsys.readouterr().err


def test_production_without_secret_refuses(env, capsys, monkeypatch):
    monkeypatch.setenv("HAMMURABI_ENVIRONMENT", "production")
    assert main(["migrate"]) == 2
    err = capsys.readouterr().err
    assert "HAMMURABI_SECRET_KEY" in err and "HAMMURABI_PUBLIC_URL" in err


def test_import_catalogue_command(env, capsys, tmp_path):
    source = tmp_path / "cat.csv"
    source.write_text("id_text,designation,height\nP000001,BM 1,4 cm\n,nothing,\n")
    assert main(["import-catalogue", str(source), "--institution", "BM", "--public"]) == 0
    err = capsys.readouterr().err
    assert "1 inserted" in err and "1 skipped" in err and "no P-number" in err
    engine, factory = _session(env)
    with session_scope(factory) as session:
        tablet = session.query(Tablet).one()
        assert (tablet.is_public, tablet.institution.name, tablet.height_mm) == (True, "BM", 40.0)
    engine.dispose()


def test_unknown_command_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["frobnicate"])
    assert exc.value.code == 2


def test_serve_migrates_then_runs_uvicorn(env, monkeypatch):
    from fastapi import FastAPI

    calls = []
    monkeypatch.setattr("uvicorn.run", lambda app, **options: calls.append((app, options)))
    assert main(["serve", "--port", "8123"]) == 0
    assert main(["serve", "--port", "8124", "--workers", "3"]) == 0
    assert env.exists()  # migrated before serving
    (one, one_options), (many, many_options) = calls
    assert isinstance(one, FastAPI) and one_options["port"] == 8123
    one.state.engine.dispose()
    # several processes: each builds its app from the environment
    assert many == "backend.main:create_app"
    assert many_options == {
        "host": "127.0.0.1",
        "port": 8124,
        "log_level": "info",
        "factory": True,
        "workers": 3,
        "timeout_worker_healthcheck": 60,
    }


@pytest.mark.parametrize(
    ("host", "expected"),
    [("127.0.0.1", "http://127.0.0.1:8123"), ("0.0.0.0", "http://127.0.0.1:8123"),
     ("::1", "http://[::1]:8123"), ("lib.local", "http://lib.local:8123")],
)  # fmt: skip
def test_serve_defaults_the_public_url_to_its_address(env, monkeypatch, host, expected):
    from backend.cli import _with_dev_public_url
    from backend.settings import Settings

    settings = _with_dev_public_url(Settings(_env_file=None), host=host, port=8123)
    assert settings.resolved_public_url == expected
    assert os.environ["HAMMURABI_PUBLIC_URL"] == expected  # for --workers processes
    configured = Settings(_env_file=None, public_url="https://lib.example.org/")
    assert _with_dev_public_url(configured, host=host, port=1).public_url == (
        "https://lib.example.org"
    )


def _user(env, email):
    assert main(["migrate"]) == 0
    engine, factory = _session(env)
    with session_scope(factory) as session:
        user = crud.get_user_by_email(session, email=email)
        found = (user is not None) and crud.password_matches(user, "long enough")
    engine.dispose()
    return found


def test_password_from_the_prompt_asked_twice(env, monkeypatch):
    answers = iter(["long enough", "long enough"])
    monkeypatch.setattr("sys.stdin.isatty", lambda: True)
    monkeypatch.setattr("getpass.getpass", lambda prompt: next(answers))
    assert main(["create-user", "a@b.org", "--role", "reader"]) == 0
    assert _user(env, "a@b.org")


def test_prompt_answers_must_match(env, capsys, monkeypatch):
    answers = iter(["long enough", "long enouhg"])
    monkeypatch.setattr("sys.stdin.isatty", lambda: True)
    monkeypatch.setattr("getpass.getpass", lambda prompt: next(answers))
    assert main(["create-user", "a@b.org", "--role", "reader"]) == 2
    assert "differ" in capsys.readouterr().err


def test_short_password_from_stdin_is_refused(env, capsys, monkeypatch):
    monkeypatch.setattr("sys.stdin", io.StringIO("short\n"))
    assert main(["create-user", "a@b.org", "--role", "reader", "--password-stdin"]) == 2
    assert "at least 8" in capsys.readouterr().err
    assert not _user(env, "a@b.org")


def test_password_on_the_command_line_is_refused_and_nothing_created(env, capsys):
    argv = ["create-user", "a@b.org", "--role", "reader", "--password", "long enough"]
    assert main(argv) == 2
    assert "shell history" in capsys.readouterr().err
    assert not _user(env, "a@b.org")


def test_password_stdin_through_a_real_pipe(env, tmp_path):
    import subprocess
    import sys

    result = subprocess.run(
        [sys.executable, "-m", "backend.cli", "create-user", "p@b.org", "--role", "reader",
         "--password-stdin"],
        input="long enough\n", capture_output=True, text=True, timeout=120, cwd=tmp_path,
        env={**os.environ, "HAMMURABI_DATA_DIR": str(tmp_path / "var")},
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "long enough" not in result.stdout + result.stderr
    assert _user(env, "p@b.org")
