"""write_bundle: validates first, writes atomically and deterministically."""

from __future__ import annotations

import hashlib
import zipfile
from pathlib import Path

import numpy as np
import pytest

from worker.bundle import BundleError, open_bundle, validate_bundle, write_bundle
from worker.bundle import writer as writer_module


def _digest(path: Path) -> dict[str, str]:
    if path.is_file():
        return {"": hashlib.sha256(path.read_bytes()).hexdigest()}
    return {
        str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(path.rglob("*"))
        if p.is_file()
    }


@pytest.mark.parametrize("as_zip", [False, True])
def test_output_is_deterministic(tmp_path, valid_bundle, as_zip) -> None:
    manifest, images = valid_bundle()
    a = write_bundle(tmp_path / "a", manifest, images, as_zip=as_zip)
    b = write_bundle(tmp_path / "b", manifest, dict(reversed(images.items())), as_zip=as_zip)
    assert _digest(a) == _digest(b)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"]  # no temp left behind


def test_zip_layout(tmp_path, valid_bundle) -> None:
    manifest, images = valid_bundle()
    path = write_bundle(tmp_path / "b.zip", manifest, images, as_zip=True)
    with zipfile.ZipFile(path) as archive:
        infos = archive.infolist()
    assert infos[0].filename == "manifest.json"
    assert sorted(i.filename for i in infos[1:]) == [i.filename for i in infos[1:]]
    assert {i.filename for i in infos[1:]} == set(images)
    assert all(i.compress_type == zipfile.ZIP_STORED for i in infos[1:])


def test_invalid_input_lists_every_problem_and_writes_nothing(tmp_path, valid_bundle) -> None:
    manifest, images = valid_bundle()
    del manifest["frames"][3]["channel"]
    with pytest.raises(BundleError) as info:
        write_bundle(tmp_path / "b", manifest, images)
    assert [str(p) for p in info.value.problems] == ['frames[3].channel: required for kind "color"']

    manifest, images = valid_bundle()
    images["object/p0.png"] = images["object/p0.png"][:, :8]
    images["object/p90.png"] = images["object/p90.png"].astype(np.float32)
    images["object/red.png"] = images["object/red.png"].astype(np.int32)
    images["stray.png"] = images["dark.png"]
    images["reference/f0.png"][0, 0] = 4096
    del images["dark.png"]
    with pytest.raises(BundleError) as info:
        write_bundle(tmp_path / "b", manifest, images)
    wheres = {p.where: p.message for p in info.value.problems}
    assert set(wheres) == {
        "images['object/p0.png']",
        "images['object/p90.png']",
        "images['object/red.png']",
        "images['stray.png']",
        "images['reference/f0.png']",
        "frames[0].file",
    }
    assert "shape (12, 8)" in wheres["images['object/p0.png']"]
    assert "must be TIFF" in wheres["images['object/p90.png']"]
    assert "dtype int32" in wheres["images['object/red.png']"]
    assert "no frame names" in wheres["images['stray.png']"]
    assert "above 2^12 − 1" in wheres["images['reference/f0.png']"]
    assert "no image given" in wheres["frames[0].file"]
    assert list(tmp_path.iterdir()) == []


def test_cross_frame_rules_are_checked(tmp_path, valid_bundle) -> None:
    manifest, images = valid_bundle()
    manifest["frames"][7]["phase_deg"] = 45
    with pytest.raises(BundleError, match="missing phases: 270"):
        write_bundle(tmp_path / "b", manifest, images)


def test_numpy_values_in_the_manifest_are_written_as_json(tmp_path, valid_bundle) -> None:
    manifest, images = valid_bundle()
    manifest["camera"]["width"] = np.int64(16)
    manifest["source"]["polar_deg"] = np.float32(40)
    manifest["scan"]["pose"] = np.eye(3)
    path = write_bundle(tmp_path / "b", manifest, images)
    assert validate_bundle(path) == []
    with open_bundle(path) as bundle:
        assert bundle.manifest.scan.pose == ((1, 0, 0), (0, 1, 0), (0, 0, 1))
    assert isinstance(manifest["camera"]["width"], np.int64)  # input not modified


def test_nan_or_lone_surrogate_in_an_extra_field_is_refused(tmp_path, valid_bundle) -> None:
    manifest, images = valid_bundle()
    manifest["scan"]["note"] = float("nan")
    with pytest.raises(BundleError, match="strict JSON"):
        write_bundle(tmp_path / "b", manifest, images)
    manifest["scan"]["note"] = "\ud800"
    with pytest.raises(BundleError, match="strict JSON"):
        write_bundle(tmp_path / "b", manifest, images)
    manifest["scan"]["note"] = {1: "a", "1": "b"}  # both keys become "1" in JSON
    with pytest.raises(BundleError, match="duplicate key '1'"):
        write_bundle(tmp_path / "b", manifest, images)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("as_zip", [False, True])
def test_existing_output(tmp_path, valid_bundle, as_zip) -> None:
    manifest, images = valid_bundle()
    out = write_bundle(tmp_path / "b", manifest, images, as_zip=as_zip)
    with pytest.raises(FileExistsError):
        write_bundle(out, manifest, images, as_zip=as_zip)
    manifest["scan"]["face"] = "reverse"
    write_bundle(out, manifest, images, as_zip=as_zip, overwrite=True)
    with open_bundle(out) as bundle:
        assert bundle.manifest.scan.face == "reverse"
    assert [p.name for p in tmp_path.iterdir()] == ["b"]


def test_a_failure_while_writing_leaves_nothing(tmp_path, valid_bundle, monkeypatch) -> None:
    manifest, images = valid_bundle()
    calls = []

    def failing_write(path, data):
        calls.append(path)
        if len(calls) == 5:
            raise OSError("disk full")
        path.write_bytes(data)

    monkeypatch.setattr(writer_module, "_write_file", failing_write)
    with pytest.raises(OSError, match="disk full"):
        write_bundle(tmp_path / "b", manifest, images)
    assert list(tmp_path.iterdir()) == []


def test_tiff_and_png_by_name_and_dtype(tmp_path, valid_bundle) -> None:
    manifest, images = valid_bundle()
    manifest["frames"][1]["file"] = "object/p0.tif"
    images["object/p0.tif"] = images.pop("object/p0.png")
    manifest["frames"][2]["file"] = "object/p90.tiff"
    images["object/p90.tiff"] = images.pop("object/p90.png").astype(np.float32) / 4095
    manifest["frames"][0]["file"] = "dark8.png"
    images["dark8.png"] = images.pop("dark.png").astype(np.uint8)
    path = write_bundle(tmp_path / "b", manifest, images)
    assert (path / "object/p0.tif").read_bytes()[:4] == b"II*\x00"
    with open_bundle(path) as bundle:
        assert [bundle.image_info(i).format for i in range(3)] == ["png", "tiff", "tiff"]
        assert bundle.raw(0).dtype == np.uint8
        assert bundle.raw(1).dtype == np.uint16
        assert bundle.raw(2).dtype == np.float32
        np.testing.assert_array_equal(bundle.raw(2), images["object/p90.tiff"])
