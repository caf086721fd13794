"""``make demo`` headless: catalogue → service + worker → six simulated faces uploaded like a
rig → reconstructed → the printed viewer URL answers (``--exit-when-ready``)."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from worker.demo import CATALOGUE_FILE, find_catalogue, free_port

REPO = Path(__file__).resolve().parents[2]


def test_find_catalogue_prefers_the_environment(tmp_path, monkeypatch):
    (tmp_path / CATALOGUE_FILE).write_text("key,designation\nP1,x\n")
    monkeypatch.setenv("HAMMURABI_DEMO_CATALOGUE", str(tmp_path))
    assert find_catalogue() == tmp_path / CATALOGUE_FILE


@pytest.mark.slow
def test_demo_reconstructs_a_whole_tablet_and_prints_a_working_url(tmp_path):
    real = find_catalogue()
    assert real is not None, "the ORACC catalogue is expected at ../shared/data/oracc-catalogue"
    # The first records of the real catalogue: same format, a fraction of the import time.
    small = tmp_path / "catalogue.csv"
    with real.open(encoding="utf-8") as fh:
        head = [next(fh) for _ in range(300)]
    small.write_text("".join(head), encoding="utf-8")
    env = {k: v for k, v in os.environ.items() if not k.startswith("HAMMURABI_")}
    env["HAMMURABI_DEMO_CATALOGUE"] = str(small)
    data_dir = tmp_path / "demo"
    result = subprocess.run(
        [sys.executable, "-m", "worker.demo", "--exit-when-ready", "--data-dir", str(data_dir)]
        + ["--port", str(free_port()), "--width", "64", "--height", "80", "--timeout", "400"],
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
    assert "[7/7] ready" in result.stdout  # the progress display went through every step
    with sqlite3.connect(data_dir / "hammurabi.db") as db:
        states = db.execute(
            "SELECT kind, state, count(*) FROM jobs GROUP BY kind, state ORDER BY kind"
        ).fetchall()
        faces = {f for (f,) in db.execute("SELECT DISTINCT face FROM scans")}
        face_models = db.execute("SELECT count(*) FROM models WHERE scan_id IS NOT NULL")
        tablet_models = db.execute("SELECT count(*) FROM models WHERE scan_id IS NULL")
        models = (face_models.fetchone()[0], tablet_models.fetchone()[0])
    # Six face reconstructions, then the whole-tablet registration the worker starts by itself.
    assert states == [("reconstruct", "succeeded", 6), ("register", "succeeded", 1)]
    assert faces == {"obverse", "reverse", "top", "bottom", "left", "right"}
    assert models == (6, 1)
