"""``python -m worker.bundle validate PATH``: exit codes and messages, never a traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from worker.bundle.__main__ import main

REPO = Path(__file__).resolve().parents[3]


def test_valid_bundle_prints_one_line(written_bundle, capsys) -> None:
    path = written_bundle(as_zip=True)
    assert main(["validate", str(path)]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1
    assert (
        "valid scan bundle v1, face obverse, 16×12 px at 25 µm, 12 bit; 15 frames (2 color, 1 dark, 8 fringe, 4 photometric; 7 reference)"
        in out[0]
    )


def test_invalid_bundle_lists_problems(written_bundle, capsys) -> None:
    path = written_bundle()
    (path / "object/p0.png").write_bytes(b"nonsense")
    (path / "dark.png").unlink()
    assert main(["validate", str(path)]) == 2
    out = capsys.readouterr().out.splitlines()
    assert out[0].endswith("invalid scan bundle, 2 problem(s):")
    assert out[1:] == [
        "  dark.png: does not exist",
        "  object/p0.png: is not a PNG or TIFF image",
    ]


def test_unreadable_inputs_exit_2(tmp_path, capsys) -> None:
    corrupt = tmp_path / "corrupt.zip"
    corrupt.write_bytes(b"PK\x05\x06" + bytes(10))
    empty = tmp_path / "empty"
    empty.mkdir()
    for target, expected in (
        (tmp_path / "missing", "does not exist"),
        (empty, "manifest.json: does not exist"),
        (corrupt, "neither a bundle folder nor a ZIP"),
    ):
        assert main(["validate", str(target)]) == 2
        assert expected in capsys.readouterr().out


def test_cli_in_a_subprocess_never_shows_a_traceback(tmp_path) -> None:
    corrupt = tmp_path / "corrupt.zip"
    corrupt.write_bytes(b"PK\x03\x04" + bytes(40))
    run = subprocess.run(
        [sys.executable, "-m", "worker.bundle", "validate", str(corrupt)],
        cwd=REPO, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert run.returncode == 2, run
    assert "neither a bundle folder nor a ZIP" in run.stdout
    assert "Traceback" not in run.stdout + run.stderr


def test_an_internal_error_is_one_line(monkeypatch, capsys, tmp_path) -> None:
    import worker.bundle.__main__ as cli

    def broken(path):
        raise RuntimeError("boom")

    monkeypatch.setattr(cli, "validate_bundle", broken)
    assert main(["validate", str(tmp_path)]) == 1
    assert (
        capsys.readouterr().out.strip()
        == f"{tmp_path}: internal error while validating (RuntimeError: boom)"
    )
