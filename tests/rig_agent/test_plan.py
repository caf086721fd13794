"""Plans: the standard acquisition, files, and the shots they expand into."""

from __future__ import annotations

import json

import pytest

from rig_agent.patterns import ProjectorGeometry
from rig_agent.plan import Plan, PlanError, Shot, expand, load_plan, quick_plan

GEOMETRY = ProjectorGeometry(width=1280, height=800, pixel_size_um=60.0)


def test_standard_plan_is_the_papers_acquisition():
    shots = expand(Plan(), GEOMETRY, target="object")
    kinds = [s.kind for s in shots if s.role == "bundle"]
    assert kinds.count("dark") == 1
    assert kinds.count("photometric") == 8
    assert kinds.count("color") == 4 * 3
    assert kinds.count("fringe") == 4 * 10 * 4
    # Periods double from a quarter period across the projector to 128 across it.
    at_90 = sorted({s.period_um for s in shots if s.kind == "fringe" and s.azimuth_deg == 90})
    assert at_90[-1] == pytest.approx(1280 * 60 / 0.25, abs=1e-3)
    assert at_90[0] == pytest.approx(1280 * 60 / 128, abs=1e-3)
    assert all(
        b / a == pytest.approx(2.0, rel=1e-6) for a, b in zip(at_90, at_90[1:], strict=False)
    )


def test_every_fringe_set_has_the_four_phase_steps():
    sets: dict[tuple, list[float]] = {}
    for s in expand(Plan(), GEOMETRY, target="reference"):
        if s.kind == "fringe":
            sets.setdefault((s.azimuth_deg, s.period_um), []).append(s.phase_deg)
    assert all(sorted(v) == [0, 90, 180, 270] for v in sets.values())


def test_shots_are_grouped_by_azimuth_with_a_check_frame_last():
    shots = expand(quick_plan(), GEOMETRY, target="object")
    azimuths = [s.azimuth_deg for s in shots if s.kind != "dark" and s.role == "bundle"]
    assert azimuths == sorted(azimuths)
    assert shots[-1].role == "check" and shots[-1].azimuth_deg == 0.0
    assert len({s.key for s in shots}) == len({s.file for s in shots}) == len(shots)
    assert all(s.file.startswith("object/") and s.file.endswith(".png") for s in shots)


def test_reference_plan_has_the_same_lights_and_no_check_frame():
    obj = [s for s in expand(quick_plan(), GEOMETRY, target="object") if s.role == "bundle"]
    ref = expand(quick_plan(), GEOMETRY, target="reference")
    assert [s.light_key() for s in obj] == [s.light_key() for s in ref]


def test_shot_round_trips_and_makes_a_manifest_frame():
    shot = next(s for s in expand(quick_plan(), GEOMETRY, target="object") if s.kind == "fringe")
    assert Shot.from_dict(json.loads(json.dumps(shot.to_dict()))) == shot
    frame = shot.manifest_frame()
    assert set(frame) == {
        "file",
        "kind",
        "target",
        "azimuth_deg",
        "period_um",
        "phase_deg",
        "exposure",
    }


def test_load_plan_from_toml_and_json(tmp_path):
    toml = tmp_path / "p.toml"
    toml.write_text(
        'name = "mine"\nphotometric_azimuths_deg = [0, 120, 240]\n[exposure]\nfringe = 2.0\n'
    )
    plan = load_plan(toml)
    assert plan.name == "mine" and plan.photometric_azimuths_deg == (0, 120, 240)
    assert plan.exposure == {"photometric": 1.0, "color": 1.0, "fringe": 2.0}
    darks = [s for s in expand(plan, GEOMETRY, target="object") if s.kind == "dark"]
    assert sorted(s.exposure for s in darks) == [1.0, 2.0]  # one dark per exposure used
    js = tmp_path / "p.json"
    js.write_text(json.dumps(quick_plan().to_dict()))
    assert load_plan(js) == quick_plan()


@pytest.mark.parametrize(
    ("data", "culprit"),
    [
        ({"colour_channels": ["red"]}, "colour_channels"),
        ({"fringe_phases_deg": [0, 120, 240]}, "fringe_phases_deg"),
        ({"fringe_periods_across": [0, 1]}, "fringe_periods_across"),
        ({"photometric_azimuths_deg": [0, 0]}, "photometric_azimuths_deg"),
        ({"color_channels": ["cyan"]}, "color_channels"),
        ({"exposure": {"fringe": -1}}, "exposure.fringe"),
        ({"averaging": 0}, "averaging"),
    ],
)
def test_bad_plans_name_the_field_and_file(tmp_path, data, culprit):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(PlanError, match=culprit) as info:
        load_plan(path)
    assert "bad.json" in str(info.value)


def test_unreadable_plan_files(tmp_path):
    with pytest.raises(PlanError, match="cannot read"):
        load_plan(tmp_path / "missing.toml")
    (tmp_path / "broken.json").write_text("{")
    with pytest.raises(PlanError, match="not valid"):
        load_plan(tmp_path / "broken.json")
