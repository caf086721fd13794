"""open_bundle / validate_bundle on valid bundles: typed frames, radiance, reference matching."""

from __future__ import annotations

import numpy as np
import pytest

from worker.bundle import BundleError, Frame, open_bundle, validate_bundle, write_bundle


@pytest.mark.parametrize("as_zip", [False, True])
def test_round_trip_gives_the_stored_values(written_bundle, valid_bundle, as_zip) -> None:
    path = written_bundle(as_zip=as_zip)
    manifest, images = valid_bundle()
    assert validate_bundle(path) == []
    with open_bundle(path) as bundle:
        assert bundle.manifest.camera.width == 16 and bundle.manifest.camera.height == 12
        assert bundle.manifest.reference.reflectance == 0.95
        assert len(bundle.frames) == len(manifest["frames"])
        for frame in bundle.frames:
            assert frame.file == manifest["frames"][frame.index]["file"]
            raw = bundle.raw(frame)
            assert raw.dtype == np.uint16
            np.testing.assert_array_equal(raw, images[frame.file])


def test_radiance_follows_the_spec(written_bundle, valid_bundle) -> None:
    manifest, images = valid_bundle()
    manifest["camera"]["response_gamma"] = 2.2
    manifest["frames"][1]["exposure"] = 4.0
    path = written_bundle(manifest=manifest, images=images)
    with open_bundle(path) as bundle:
        frame = bundle.frames[1]
        got = bundle.radiance(frame)
    full = 2.0**12 - 1
    v, dark = images[frame.file].astype(np.float64), images["dark.png"].astype(np.float64)
    want = ((v / full) ** 2.2 - (dark / full) ** 2.2) / 4.0
    assert got.dtype == np.float32 and got.shape == (12, 16)
    # float32 rounding of values ≤ 1: |error| ≤ a few ulp(1) = 6e-8 each.
    np.testing.assert_allclose(got, want, rtol=0, atol=5e-7)


def test_radiance_of_float_tiff_is_linear_and_darks_match_encoding(written_bundle, valid_bundle):
    manifest, images = valid_bundle()
    rng = np.random.default_rng(3)
    manifest["frames"][1]["file"] = "object/p0.tif"
    images["object/p0.tif"] = rng.random((12, 16), dtype=np.float32)
    del images["object/p0.png"]
    manifest["frames"].append({"file": "darkf.tiff", "kind": "dark", "exposure": 2.0})
    images["darkf.tiff"] = np.full((12, 16), 0.01, np.float32)
    path = written_bundle(manifest=manifest, images=images)
    with open_bundle(path) as bundle:
        float_frame, int_frame = bundle.frames[1], bundle.frames[2]
        assert bundle.image_info(float_frame).format == "tiff"
        assert bundle.dark_of(float_frame).file == "darkf.tiff"  # the only float dark
        assert bundle.dark_of(int_frame).file == "dark.png"  # the only integer dark
        np.testing.assert_array_equal(
            bundle.radiance(float_frame), images["object/p0.tif"] - np.float32(0.01)
        )


def test_dark_selection_by_exposure(written_bundle, valid_bundle) -> None:
    manifest, images = valid_bundle()
    frames = manifest["frames"]
    for name, exposure in (("d2", 2.0), ("d8", 8.0), ("d05", 0.5)):
        frames.append({"file": f"{name}.png", "kind": "dark", "exposure": exposure})
        images[f"{name}.png"] = np.full((12, 16), 3, np.uint16)
    exposures = {1: 2.0, 2: 4.0, 3: 1.0, 4: 3.0, 5: 0.25}
    for index, exposure in exposures.items():
        frames[index]["exposure"] = exposure
    path = written_bundle(manifest=manifest, images=images)
    with open_bundle(path) as bundle:
        picked = {i: bundle.dark_of(i).file for i in exposures}
        assert bundle.dark_of(0) is None
    assert picked == {
        1: "d2.png",  # same exposure
        2: "d2.png",  # 4 is a ratio 2 from both 2 and 8: the shorter wins
        3: "dark.png",  # exposure 1.0 (default) matches
        4: "d2.png",  # ratio 1.5 to 2 beats ratio 3 to 1 and 2.67 to 8
        5: "d05.png",  # nearest in ratio: 0.5
    }


def test_no_dark_means_zero(written_bundle, valid_bundle) -> None:
    manifest, images = valid_bundle()
    manifest["frames"] = manifest["frames"][1:]
    del images["dark.png"]
    path = written_bundle(manifest=manifest, images=images)
    with open_bundle(path) as bundle:
        frame = bundle.frames[0]
        assert bundle.dark_of(frame) is None
        np.testing.assert_allclose(
            bundle.radiance(frame), images[frame.file] / np.float32(4095), rtol=1e-6
        )


def test_reference_of(written_bundle, valid_bundle) -> None:
    manifest, images = valid_bundle()
    by_file = {f["file"]: f for f in manifest["frames"]}
    # Angles modulo 360 and within 1e-6: still the same lighting.
    by_file["reference/p90.png"]["azimuth_deg"] = 90 - 720 + 5e-7
    by_file["reference/f90.png"]["phase_deg"] = 450
    by_file["reference/red.png"]["polar_deg"] = 40.0000004
    path = written_bundle(manifest=manifest, images=images)
    with open_bundle(path) as bundle:
        pairs = {
            f.file: (bundle.reference_of(f).file if bundle.reference_of(f) else None)
            for f in bundle.frames
        }
    for name in ("p0.png", "p90.png", "red.png", "f0.png", "f90.png", "f180.png", "f270.png"):
        assert pairs[f"object/{name}"] == f"reference/{name}"
        assert pairs[f"reference/{name}"] is None
    assert pairs["dark.png"] is None


def test_radiance_many_equals_radiance(written_bundle) -> None:
    with open_bundle(written_bundle(as_zip=True)) as bundle:
        frames = bundle.frames_where(target="object")
        stack = bundle.radiance_many(frames, max_workers=2)
        assert stack.shape == (len(frames), 12, 16) and stack.dtype == np.float32
        for i, frame in enumerate(frames):
            np.testing.assert_array_equal(stack[i], bundle.radiance(frame))
        assert frames[0].kind == "dark"  # darks are object frames by default
        np.testing.assert_array_equal(bundle.radiance_many([3], max_workers=1)[0], stack[3])
        out = np.empty((12, 16), np.float32)
        assert bundle.radiance(frames[3], out=out) is out
        np.testing.assert_array_equal(out, stack[3])


def test_frame_argument_must_belong_to_the_bundle(written_bundle) -> None:
    with open_bundle(written_bundle()) as bundle:
        with pytest.raises(ValueError, match="frame"):
            bundle.radiance(Frame(index=1, file="other.png", kind="dark"))
        with pytest.raises(ValueError, match="frame"):
            bundle.raw(999)


def test_values_are_checked_while_decoding(tmp_path, valid_bundle) -> None:
    manifest, images = valid_bundle()
    manifest["camera"]["bit_depth"] = 16
    images["object/p0.png"][3, 4] = 5000
    path = write_bundle(tmp_path / "b", manifest, images)
    text = (path / "manifest.json").read_text().replace('"bit_depth": 16', '"bit_depth": 12')
    (path / "manifest.json").write_text(text)
    # Headers are fine, so the bundle opens; values are checked as each image is decoded.
    with open_bundle(path) as bundle, pytest.raises(BundleError) as info:
        bundle.radiance(1)
    assert [p.where for p in info.value.problems] == ["object/p0.png"]
    assert "1 values above 2^12 − 1 = 4095 (maximum 5000)" in str(info.value)
    with pytest.raises(BundleError, match="object/p0.png"):
        open_bundle(path, decode_all=True)
    assert [p.where for p in validate_bundle(path)] == ["object/p0.png"]


def test_a_vanished_bundle_raises_bundle_error(written_bundle) -> None:
    import shutil

    path = written_bundle()
    with open_bundle(path) as bundle:
        shutil.rmtree(path)
        with pytest.raises(
            BundleError, match="dark.png: cannot be read: the bundle folder is gone"
        ):
            bundle.raw(0)


def test_dark_frames_are_decoded_once(written_bundle, valid_bundle) -> None:
    _, images = valid_bundle()
    with open_bundle(written_bundle(as_zip=True)) as bundle:
        reads: list[str] = []
        read = bundle._container.read
        bundle._container.read = lambda path, **kw: reads.append(path) or read(path, **kw)
        bundle.radiance_many(bundle.frames[1:], max_workers=2)
        for frame in bundle.frames[1:4]:
            bundle.radiance(frame)
        assert reads.count("dark.png") == 1
        assert len(reads) == len(bundle.frames) - 1 + 3 + 1
        # A dark frame's own radiance is lin(v) / exposure: nothing is subtracted from it.
        np.testing.assert_allclose(
            bundle.radiance(0), images["dark.png"] / np.float32(4095), rtol=1e-6
        )
