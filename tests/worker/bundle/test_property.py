"""Property tests: mutated manifests and random bytes never crash the validator."""

from __future__ import annotations

import json
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from worker.bundle import Problem, validate_bundle, write_bundle
from worker.bundle.manifest import build_manifest, check_manifest, parse_manifest_json
from worker.bundle.matching import check_frames

scalars = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(10**30), max_value=10**30)
    | st.just(10**4000)  # overflows float(); hypothesis cannot print 10**5000
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.sampled_from(
        ["", "dark", "fringe", "color", "red", "object", "reference", "../x", "a.png", "\ud800.png"]
    )
    | st.text(max_size=6)
)
json_like = st.recursive(
    scalars,
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)


def _paths(value: Any, prefix: tuple = ()) -> list[tuple]:
    """Every location (a tuple of keys/indices) inside a nested dict/list."""
    out = [prefix] if prefix else []
    if isinstance(value, dict):
        for key, item in value.items():
            out += _paths(item, (*prefix, key))
    elif isinstance(value, list):
        for i, item in enumerate(value):
            out += _paths(item, (*prefix, i))
    return out


def _mutate(value: dict, data: st.DataObject) -> dict:
    for _ in range(data.draw(st.integers(1, 4), label="mutations")):
        paths = _paths(value)
        if not paths:
            break
        path = data.draw(st.sampled_from(paths), label="path")
        parent = value
        for key in path[:-1]:
            parent = parent[key]
        op = data.draw(st.sampled_from(["drop", "replace", "retype"]), label="op")
        if op == "drop":
            del parent[path[-1]]
        elif op == "replace":
            parent[path[-1]] = data.draw(json_like, label="new value")
        else:
            old = parent[path[-1]]
            parent[path[-1]] = [old] if not isinstance(old, list) else {"x": old}
    return value


def _check(value: Any) -> list[Problem]:
    """What the reader does with a parsed manifest; must return Problems, never raise."""
    problems = check_manifest(value)
    assert all(isinstance(p, Problem) and p.where and p.message for p in problems)
    if not problems:
        problems = check_frames(build_manifest(value).frames)
    return problems


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_mutated_manifests_give_only_problems(valid_bundle, data) -> None:
    manifest, _ = valid_bundle()
    _check(_mutate(manifest, data))


@settings(max_examples=50, deadline=None)
@given(value=json_like)
def test_random_json_gives_only_problems(value) -> None:
    problems = _check(value)
    assert problems  # nothing random is a valid manifest


@settings(max_examples=50, deadline=None)
@given(data=st.binary(max_size=200) | st.text(max_size=100).map(str.encode))
def test_random_bytes_parse_or_give_one_problem(data: bytes) -> None:
    value, problems = parse_manifest_json(data)
    if problems:
        assert value is None and len(problems) == 1
    else:
        # Parsed: the JSON value itself, which may be null (check_manifest refuses it).
        assert value == json.loads(data.decode("utf-8"))


def test_json_null_parses_to_none_and_is_refused_by_the_field_checks() -> None:
    assert parse_manifest_json(b"null") == (None, [])
    assert "must hold a JSON object" in check_manifest(None)[0].message


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory, valid_bundle):
    manifest, images = valid_bundle()
    return write_bundle(tmp_path_factory.mktemp("prop") / "b", manifest, images)


@settings(
    max_examples=30,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(data=st.data())
def test_mutated_bundles_on_disk_give_only_problems(bundle_dir, valid_bundle, data) -> None:
    manifest, _ = valid_bundle()
    mutated = _mutate(manifest, data)
    (bundle_dir / "manifest.json").write_text(json.dumps(mutated))
    problems = validate_bundle(bundle_dir)
    assert all(isinstance(p, Problem) for p in problems)
    try:
        json.dumps(mutated, allow_nan=False)
    except ValueError:  # the file holds NaN or Infinity: strict JSON refuses the whole file
        assert [p.where for p in problems] == ["manifest.json"]
