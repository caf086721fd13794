"""manifest.json: strict JSON and every field rule of SCAN_BUNDLE.md."""

from __future__ import annotations

import json

import pytest

from worker.bundle import Problem
from worker.bundle.manifest import build_manifest, check_manifest, parse_manifest_json


def _wheres(problems: list[Problem]) -> list[str]:
    return [p.where for p in problems]


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        (b'{"a": NaN}', "NaN"),
        (b'{"a": Infinity}', "Infinity"),
        (b'{"a": -Infinity}', "-Infinity"),
        (b'{"a": 1e999}', "infinity"),
        (b'{"a": 1, "a": 2}', "duplicate key 'a'"),
        (b'{"a": {"b": 1, "b": 1}}', "duplicate key 'b'"),
        (b"\xef\xbb\xbf{}", "byte-order mark"),
        (b'{"a": "\xff"}', "UTF-8"),
        (b"{'a': 1}", "not valid JSON"),
        (b'{"a": 1,}', "not valid JSON"),
        (b"", "not valid JSON"),
        (b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
        (b'{"a": ' + b"9" * 5000 + b"}", "not strict JSON"),
        (b'{"a": "x\\ud800"}', "lone surrogate"),
        (b'{"\\udfff": 1}', "lone surrogate"),
    ],
)
def test_parse_refuses_non_strict_json(text: bytes, fragment: str) -> None:
    value, problems = parse_manifest_json(text)
    assert value is None
    assert len(problems) == 1 and problems[0].where == "manifest.json"
    assert fragment in problems[0].message


def test_escaped_surrogate_pairs_are_fine() -> None:
    assert parse_manifest_json(b'{"a": "\\ud83d\\ude00"}') == ({"a": "\U0001f600"}, [])


def test_parse_caps_size_before_parsing() -> None:
    text = json.dumps({"pad": "x" * 100}).encode()
    value, problems = parse_manifest_json(text, max_bytes=50)
    assert value is None and "more than the cap of 50" in problems[0].message
    assert parse_manifest_json(text, max_bytes=len(text))[1] == []


@pytest.mark.parametrize("value", [[], "x", 3, None, True])
def test_manifest_must_be_an_object(value) -> None:
    problems = check_manifest(value)
    assert _wheres(problems) == ["manifest.json"]
    assert "must hold a JSON object" in problems[0].message


def test_valid_manifest_has_no_problems_and_defaults_apply(valid_bundle) -> None:
    manifest, _ = valid_bundle()
    del manifest["reference"]
    manifest["frames"][1]["polar_deg"] = 20
    assert check_manifest(manifest) == []
    m = build_manifest(manifest)
    assert m.reference.reflectance == 1.0
    assert m.camera.response_gamma == 1.0
    assert m.camera.psf_sigma_px is None  # absent: unknown, never a default blur
    assert m.scan.face == "obverse" and m.scan.tablet == {"designation": "P123456"}
    dark, first, second = m.frames[:3]
    assert (dark.kind, dark.azimuth_deg, dark.polar_deg, dark.exposure) == ("dark", None, None, 1.0)
    assert first.polar_deg == 20.0  # its own
    assert second.polar_deg == 40.0  # source.polar_deg
    assert [f.index for f in m.frames] == list(range(len(manifest["frames"])))
    assert all(f.target in ("object", "reference") for f in m.frames)


@pytest.mark.parametrize("sigma", [0, 0.5, 1.5])
def test_camera_psf_sigma_is_read_when_given(valid_bundle, sigma) -> None:
    manifest, _ = valid_bundle()
    manifest["camera"]["psf_sigma_px"] = sigma
    assert check_manifest(manifest) == []
    assert build_manifest(manifest).camera.psf_sigma_px == float(sigma)


def test_missing_top_level_fields_are_all_reported() -> None:
    problems = check_manifest({})
    assert set(_wheres(problems)) == {
        "format", "version", "scan", "scan.face", "camera", "source", "frames",
    }  # fmt: skip


def test_example_message_from_the_issue(valid_bundle) -> None:
    manifest, _ = valid_bundle()
    frames = manifest["frames"]
    while len(frames) < 18:
        frames.append({"file": f"x{len(frames)}.png", "kind": "photometric", "azimuth_deg": 0})
    frames[17] = {"file": "f.png", "kind": "fringe", "azimuth_deg": 0, "phase_deg": 0}
    assert [str(p) for p in check_manifest(manifest)] == [
        'frames[17].period_um: required for kind "fringe"'
    ]


@pytest.mark.parametrize(
    ("section", "field", "value", "fragment"),
    [
        ("camera", "width", 0, "outside [1, inf)"),
        ("camera", "width", 12.5, "must be an integer"),
        ("camera", "width", True, "must be an integer, not true"),
        ("camera", "width", "16", "must be an integer"),
        ("camera", "height", None, "must be an integer, not null"),
        ("camera", "pixel_size_um", 0, "outside (0, inf)"),
        ("camera", "pixel_size_um", -1.5, "outside (0, inf)"),
        ("camera", "pixel_size_um", False, "must be a number, not false"),
        ("camera", "bit_depth", 7, "outside [8, 16]"),
        ("camera", "bit_depth", 17, "outside [8, 16]"),
        ("camera", "bit_depth", 12.5, "must be an integer"),
        ("camera", "response_gamma", 0, "outside (0, inf)"),
        ("camera", "psf_sigma_px", -0.1, "outside [0, inf)"),
        ("camera", "psf_sigma_px", "0.5", "must be a number"),
        ("source", "polar_deg", 0, "outside (0, 90)"),
        ("source", "polar_deg", 90, "outside (0, 90)"),
        ("source", "polar_deg", [], "must be a number, not a list"),
        ("reference", "reflectance", 0, "outside (0, 1]"),
        ("reference", "reflectance", 1.0000001, "outside (0, 1]"),
        ("scan", "face", "front", "is not one of"),
        ("scan", "face", 1, "is not one of"),
        ("scan", "id", 5, "must be a string"),
        ("scan", "captured_at", "yesterday", "not an ISO 8601"),
        ("scan", "tablet", [], "must be an object"),
        ("scan", "pose", [[1, 0], [0, 1]], "3x3"),
        ("scan", "pose", [[1, 0, 0], [0, 1, 0], [0, 0, 2]], "not a rotation"),
        ("scan", "pose", [[1, 0, 0], [0, 1, 0], [0, 0, -1]], "determinant"),
        ("scan", "pose", [[1, 0, 0], [0, 1, 0], [0, 0, True]], "numbers"),
    ],
)
def test_field_rules(valid_bundle, section: str, field: str, value, fragment: str) -> None:
    manifest, _ = valid_bundle()
    manifest.setdefault(section, {})[field] = value
    problems = check_manifest(manifest)
    assert _wheres(problems) == [f"{section}.{field}"], problems
    assert fragment in problems[0].message


@pytest.mark.parametrize(
    ("section", "field", "value"),
    [
        ("camera", "width", 16.0),  # integral float: allowed
        ("camera", "bit_depth", 8),
        ("camera", "bit_depth", 16.0),
        ("reference", "reflectance", 1),
        ("scan", "captured_at", "2026-11-21T01:02:03Z"),
        ("scan", "pose", [[0, -1, 0], [1, 0, 0], [0, 0, 1]]),
        ("scan", "pose", [[0.7071, -0.7071, 0], [0.7071, 0.7071, 0], [0, 0, 1]]),
    ],
)
def test_field_values_allowed(valid_bundle, section: str, field: str, value) -> None:
    manifest, _ = valid_bundle()
    manifest[section][field] = value
    assert check_manifest(manifest) == []


def test_version_and_format(valid_bundle) -> None:
    manifest, _ = valid_bundle()
    manifest["version"] = 1.0
    assert check_manifest(manifest) == []
    for bad in (True, 2, "1"):
        manifest["version"] = bad
        assert _wheres(check_manifest(manifest)) == ["version"]
    manifest["version"] = 1
    manifest["format"] = "cuneiform"
    assert _wheres(check_manifest(manifest)) == ["format"]


@pytest.mark.parametrize(
    ("kind", "drop", "where", "message"),
    [
        ("photometric", "azimuth_deg", "azimuth_deg", 'required for kind "photometric"'),
        ("color", "azimuth_deg", "azimuth_deg", 'required for kind "color"'),
        ("color", "channel", "channel", 'required for kind "color"'),
        ("fringe", "azimuth_deg", "azimuth_deg", 'required for kind "fringe"'),
        ("fringe", "phase_deg", "phase_deg", 'required for kind "fringe"'),
        ("fringe", "file", "file", "required"),
        ("fringe", "kind", "kind", "required"),
    ],
)
def test_per_kind_required_fields(valid_bundle, kind, drop, where, message) -> None:
    manifest, _ = valid_bundle()
    index = next(i for i, f in enumerate(manifest["frames"]) if f["kind"] == kind)
    del manifest["frames"][index][drop]
    problems = check_manifest(manifest)
    assert [str(p) for p in problems] == [f"frames[{index}].{where}: {message}"]


def test_dark_needs_no_azimuth_and_unknown_kind_is_reported(valid_bundle) -> None:
    manifest, _ = valid_bundle()
    assert "azimuth_deg" not in manifest["frames"][0]
    manifest["frames"][1]["kind"] = "infrared"
    manifest["frames"][2]["target"] = "sky"
    manifest["frames"][3]["channel"] = "yellow"
    manifest["frames"][4]["exposure"] = 0
    manifest["frames"][5]["polar_deg"] = 95
    manifest["frames"][6]["period_um"] = -3
    manifest["frames"].append("not a frame")
    n = len(manifest["frames"]) - 1
    assert _wheres(check_manifest(manifest)) == [
        "frames[1].kind",
        "frames[2].target",
        "frames[3].channel",
        "frames[4].exposure",
        "frames[5].polar_deg",
        "frames[6].period_um",
        f"frames[{n}]",
    ]


@pytest.mark.parametrize(
    ("path", "fragment"),
    [
        ("../x.png", "'..'"),
        ("a/../../x.png", "'..'"),
        ("/etc/passwd", "start with '/'"),
        ("a\\b.png", "backslash"),
        ("C:x.png", "drive letter"),
        ("c:/x.png", "drive letter"),
        ("a\x00.png", "NUL"),
        ("a\ud800.png", "lone surrogate"),
        ("a" * 5000 + ".png", "is 5004 characters long"),
        ("", "empty"),
        ("a/", "does not name a file"),
        (".", "does not name a file"),
        (3, "must be a string"),
    ],
)
def test_unsafe_paths_are_refused(valid_bundle, path, fragment) -> None:
    manifest, _ = valid_bundle()
    manifest["frames"][2]["file"] = path
    problems = check_manifest(manifest)
    assert _wheres(problems) == ["frames[2].file"]
    assert fragment in problems[0].message


def test_paths_are_normalised(valid_bundle) -> None:
    manifest, _ = valid_bundle()
    manifest["frames"][1]["file"] = "./object//p0.png"
    assert check_manifest(manifest) == []
    assert build_manifest(manifest).frames[1].file == "object/p0.png"


def test_huge_integers_are_not_numbers(valid_bundle) -> None:
    manifest, _ = valid_bundle()
    manifest["camera"]["pixel_size_um"] = 10**400
    manifest["frames"][1]["azimuth_deg"] = -(10**400)
    manifest["frames"][2]["kind"] = 10**5000  # even repr() of this one raises ValueError
    problems = check_manifest(manifest)
    assert _wheres(problems) == ["camera.pixel_size_um", "frames[1].azimuth_deg", "frames[2].kind"]
    assert "a very large integer is not one of" in problems[2].message
