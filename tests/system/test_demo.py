"""``make demo`` headless: catalogue → service + worker → six simulated faces uploaded like a
rig → reconstructed → the printed viewer URL answers (``--exit-when-ready``)."""

from __future__ import annotations

import io
import json
import os
import socket
import sqlite3
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from PIL import Image

from worker.bundle import is_simulated
from worker.demo import (
    CATALOGUE_FILE,
    find_catalogue,
    free_port,
    main,
    mark_simulated,
    rewrite_manifest,
)

REPO = Path(__file__).resolve().parents[2]


def test_find_catalogue_prefers_the_environment(tmp_path, monkeypatch):
    (tmp_path / CATALOGUE_FILE).write_text("key,designation\nP1,x\n")
    monkeypatch.setenv("HAMMURABI_DEMO_CATALOGUE", str(tmp_path))
    assert find_catalogue() == tmp_path / CATALOGUE_FILE


def test_a_busy_port_gets_a_clear_message(tmp_path, capsys):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        code = main(["--port", str(port), "--data-dir", str(tmp_path / "demo")])
    err = capsys.readouterr().err
    assert code == 2
    assert f"port {port}" in err and "in use" in err and "make demo PORT=" in err
    assert not (tmp_path / "demo").exists()  # nothing done before the check


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--tablet-mm", "3x3x2"], "--tablet-mm"),
        (["--tablet-mm", "20x20x30"], "thickness"),
        (["--pixel-um", "0.5"], "--pixel-um"),
        (["--jobs", "0"], "--jobs"),
    ],
)
def test_impossible_demo_settings_get_a_clear_message(tmp_path, capsys, args, message):
    code = main(["--port", str(free_port()), "--data-dir", str(tmp_path / "demo"), *args])
    assert code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "demo").exists()


def test_simulated_bundles_say_so_in_free_metadata(tmp_path):
    src = tmp_path / "in.zip"
    with zipfile.ZipFile(src, "w") as z:
        z.writestr("manifest.json", json.dumps({"scan": {"id": "s", "face": "obverse"}}))
        z.writestr("frames/a.png", b"\x89PNG bytes")
    out = rewrite_manifest(src, tmp_path / "out.zip", mark_simulated)
    with zipfile.ZipFile(out) as z:
        manifest = json.loads(z.read("manifest.json"))
        assert z.read("frames/a.png") == b"\x89PNG bytes"
    assert manifest["scan"]["tablet"] == {"simulated": "true"}
    assert is_simulated(manifest["scan"]["tablet"])


@pytest.mark.slow
def test_demo_reconstructs_a_whole_tablet_and_prints_a_working_url(tmp_path):
    real = find_catalogue()
    assert real is not None, "the ORACC catalogue is expected at ../shared/data/oracc-catalogue"
    # The first records of the real catalogue: same format, a fraction of the import time.
    # 200 µm pixels run the default's code path (the small tablet, each face's frame
    # following it) at a size CI can afford; the default (the paper's 26.8 µm) is measured
    # by hand (docs/benchmarks.md, "make demo").
    small = tmp_path / "catalogue.csv"
    with real.open(encoding="utf-8") as fh:
        head = [next(fh) for _ in range(300)]
    small.write_text("".join(head), encoding="utf-8")
    env = {k: v for k, v in os.environ.items() if not k.startswith("HAMMURABI_")}
    env["HAMMURABI_DEMO_CATALOGUE"] = str(small)
    data_dir = tmp_path / "demo"
    result = subprocess.run(
        [sys.executable, "-m", "worker.demo", "--exit-when-ready", "--data-dir", str(data_dir)]
        + ["--port", str(free_port()), "--pixel-um", "200", "--timeout", "400"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    urls = [line.split()[1] for line in result.stdout.splitlines() if line.startswith("DEMO_URL")]
    assert len(urls) == 1 and "/tablet.html?id=" in urls[0]
    assert "CHECK viewer page 200, model.glb 200" in result.stdout
    assert "[6/6] ready" in result.stdout  # the progress display went through every step
    assert "whole tablet (simulated scan)" in result.stdout
    assert "log in as staff at http://127.0.0.1:" in result.stdout and "password" in result.stdout
    with sqlite3.connect(data_dir / "hammurabi.db") as db:
        states = db.execute(
            "SELECT kind, state, count(*) FROM jobs GROUP BY kind, state ORDER BY kind"
        ).fetchall()
        faces = {f for (f,) in db.execute("SELECT DISTINCT face FROM scans")}
        face_models = db.execute("SELECT count(*) FROM models WHERE scan_id IS NOT NULL")
        models = face_models.fetchone()[0]
    # Six face reconstructions, and ONE whole-tablet registration that the worker starts by
    # itself once the last of the six faces uploaded together is reconstructed.
    assert ("reconstruct", "succeeded", 6) in states
    assert ("register", "succeeded", 1) in states
    assert {kind for kind, _, _ in states} == {"reconstruct", "register"}
    assert all(state == "succeeded" for _, state, _ in states), states
    assert faces == {"obverse", "reverse", "top", "bottom", "left", "right"}
    assert models == 6
    with sqlite3.connect(data_dir / "hammurabi.db") as db:
        manifests = [json.loads(m) for (m,) in db.execute("SELECT manifest FROM scans")]
        whole_id, report = db.execute(
            "SELECT id, report FROM models WHERE scan_id IS NULL ORDER BY id DESC"
        ).fetchone()
    assert all(m["scan"]["tablet"]["simulated"] == "true" for m in manifests)
    assert json.loads(report)["simulated"] is True
    assert len(json.loads(report)["scans"]) == 6  # the printed whole tablet has every face
    assert urls[0].endswith(f"#m={whole_id}")  # the printed link opens the whole tablet
    plates = list(data_dir.rglob("*_fatcross_natural.png"))
    assert plates, "no natural-colour plate stored"
    with Image.open(io.BytesIO(plates[0].read_bytes())) as im:
        assert im.text["Simulated"] == "true" and "SIMULATED SCAN" in im.text["Description"]
