"""Bundles that conform to the spec but cannot be reconstructed exit 2 with a message naming
what is wrong (`worker.measure.checks`), never a traceback, and leave OUTDIR untouched."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from worker.reconstruct import main
from worker.simulate import simulate_scan


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny")
    simulate_scan(out, seed=2, preset="quick", noise="default", size=(96, 72))
    return out / "bundle"


def _variant(tiny, tmp_path, edit):
    d = tmp_path / "bundle"
    shutil.copytree(tiny, d)
    manifest = json.loads((d / "manifest.json").read_text())
    edit(d, manifest)
    (d / "manifest.json").write_text(json.dumps(manifest))
    return d


def _saturate(d, m):
    for f in m["frames"]:
        if f.get("target", "object") == "object" and f["kind"] != "dark":
            path = str(d / f["file"])
            img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
            cv2.imwrite(path, np.full_like(img, 2 ** m["camera"]["bit_depth"] - 1))


def _one_azimuth(d, m):
    for f in m["frames"]:
        if f["kind"] == "photometric":
            f["azimuth_deg"] = 0.0


def _no_fringes(d, m):
    m["frames"] = [f for f in m["frames"] if f["kind"] != "fringe"]


def _no_photometric(d, m):
    m["frames"] = [f for f in m["frames"] if f["kind"] not in ("photometric", "color")]


def _shuffled_references(d, m):
    refs = [f for f in m["frames"] if f["kind"] == "fringe" and f.get("target") == "reference"]
    files = [f["file"] for f in refs]
    np.random.default_rng(0).shuffle(files)
    for f, name in zip(refs, files, strict=True):
        f["file"] = name


@pytest.mark.parametrize(
    ("edit", "args", "words"),
    [
        (_saturate, [], ["saturated", "top code"]),
        (_one_azimuth, [], ["lights do not span 3-D", "azimuths [0.0]"]),
        (_no_fringes, ["--surface", "fringe"], ["surface 'fringe'", "no fringe sets"]),
        (_no_photometric, ["--surface", "normals"], ["surface 'normals'", "photometric"]),
        (_shuffled_references, [], ["reference fringe frames do not match"]),
    ],
    ids=["saturated", "one-azimuth", "no-fringe", "no-photometric", "foreign-reference"],
)
def test_bad_bundle_exits_2_naming_the_culprit(tiny, tmp_path, capsys, edit, args, words):
    bundle = _variant(tiny, tmp_path, edit)
    out = tmp_path / "model"
    assert main([str(bundle), str(out), "--quiet", *args]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    for w in words:
        assert w in err, err
    assert not out.exists()


def test_the_checks_pass_a_good_bundle(tiny, tmp_path, capsys):
    out = tmp_path / "model"
    assert main([str(tiny), str(out), "--quiet"]) == 0
    assert (out / "height.npy").exists()
