"""A tablet of a given size (``--tablet-mm``): its body has that size, and each face's frame
follows it at the given pixel size, so a small tablet at the paper's pixel gives small frames."""

from __future__ import annotations

import json

import numpy as np
import pytest

from worker.bundle import open_bundle, validate_bundle
from worker.simulate.__main__ import main
from worker.simulate.acquisition import FRAME_MARGIN_UM, PAPER_PIXEL_UM, frame_size_for
from worker.simulate.scan import face_grid, simulate_scan, view_extent_um
from worker.simulate.tablet import FACE_POSES, check_size_mm, make_tablet


def test_the_body_has_the_size_asked_for():
    small = make_tablet(3, size_mm=(12.0, 10.0, 6.0))
    big = make_tablet(3)
    a, b, _ = small.pillow.half_size_um
    assert (2 * a, 2 * b) == pytest.approx((12_000.0, 10_000.0))
    assert 2 * big.pillow.half_size_um[0] == pytest.approx(28_000.0)
    # The obverse's extent in its view is the body's width and height (plus roughness).
    w, h = view_extent_um(small, FACE_POSES["obverse"])
    assert 12_000 < w < 12_600 and 10_000 < h < 10_600
    # An edge view sees the width across and the thickness down.
    w, h = view_extent_um(small, FACE_POSES["top"])
    assert 12_000 < w < 12_600 and 6_000 < h < 7_800


def test_frames_follow_the_tablet_at_the_paper_pixel():
    tablet = make_tablet(1, size_mm=(12.0, 10.0, 6.0))
    (w, h), pixel = face_grid(
        tablet, FACE_POSES["obverse"], size=None, pixel_size_um=PAPER_PIXEL_UM, preset="quick"
    )
    assert pixel == PAPER_PIXEL_UM
    ext_w, ext_h = view_extent_um(tablet, FACE_POSES["obverse"])
    # The frame holds the tablet and the margin, no more than one pixel (+ evenness) over.
    assert ext_w + 2 * FRAME_MARGIN_UM <= w * pixel < ext_w + 2 * FRAME_MARGIN_UM + 2 * pixel
    assert ext_h + 2 * FRAME_MARGIN_UM <= h * pixel < ext_h + 2 * FRAME_MARGIN_UM + 2 * pixel
    assert w * h < 0.4 * 1280 * 1024  # far fewer pixels than the paper's full field
    # A given size still wins, and without a pixel the preset keeps the paper's field.
    assert face_grid(tablet, np.eye(3), size=(64, 48), pixel_size_um=None, preset="quick")[0] == (
        64,
        48,
    )
    assert frame_size_for((1000.0, 1000.0), 500.0, margin_um=0.0) == (16, 16)  # at least 16


@pytest.mark.parametrize(
    "size_mm",
    [(5, 10, 4), (10, 200, 5), (10, 10, 12), (10, 10, 2), ("a", 1, 1), (10, 10), (np.nan, 9, 5)],
)
def test_impossible_sizes_are_refused_with_a_message(size_mm):
    with pytest.raises(ValueError, match="tablet size"):
        check_size_mm(size_mm)


def test_a_small_tablet_scan_is_a_valid_bundle_at_the_pixel_asked_for(tmp_path):
    result = simulate_scan(
        tmp_path / "s", seed=2, face="top", tablet_mm=(10.0, 9.0, 5.0), pixel_size_um=250.0
    )
    bundle = result.bundles["top"]
    assert validate_bundle(bundle) == []
    with open_bundle(bundle) as b:
        cam = b.manifest.camera
        assert cam.pixel_size_um == 250.0
        expected = frame_size_for(
            view_extent_um(make_tablet(2, size_mm=(10, 9, 5)), FACE_POSES["top"]), 250.0
        )
        assert (cam.width, cam.height) == expected
        assert b.manifest.scan.id.endswith("-t10x9x5mm")
    mask = np.load(result.gt_dirs["top"] / "mask.npy")
    assert mask.shape == (expected[1], expected[0]) and 0.2 < mask.mean() < 0.9


def test_a_tablet_size_alone_means_the_paper_pixel(tmp_path, monkeypatch):
    import worker.simulate.scan as scan

    seen = {}

    def record(tablet, face, face_dir, **kw):  # the grid is all this test needs
        seen.update(kw, half=tablet.pillow.half_size_um)
        raise RuntimeError("stop")

    monkeypatch.setattr(scan, "_simulate_face", record)
    with pytest.raises(RuntimeError, match="stop"):
        simulate_scan(tmp_path / "p", tablet_mm=(12.0, 10.0, 6.0))
    assert seen["pixel_size_um"] == PAPER_PIXEL_UM and seen["size"] is None
    assert seen["scan_suffix"] == "-t12x10x6mm" and 2 * seen["half"][0] == 12_000.0


def test_cli_tablet_size_and_pixel_and_refuses_bad_values(tmp_path, capsys):
    for bad in (["--tablet-mm", "10x10"], ["--tablet-mm", "3x3x2"], ["--pixel-um", "0"]):
        with pytest.raises(SystemExit) as exc:
            main(["--out", str(tmp_path / "bad"), *bad])
        assert exc.value.code == 2
        assert "--" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "m"), "--mesh", "x.ply", "--tablet-mm", "10x10x5"])
    assert "own size" in capsys.readouterr().err
    assert main(["--out", str(tmp_path / "ok"), "--tablet-mm", "9x8x4", "--pixel-um", "300"]) == 0
    with open_bundle(tmp_path / "ok" / "bundle") as b:
        assert b.manifest.camera.pixel_size_um == 300.0
    doc = json.loads((tmp_path / "ok" / "gt" / "physics.json").read_text())
    assert doc["physics"]["shape"] == "standard"
