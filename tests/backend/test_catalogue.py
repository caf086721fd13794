"""Catalogue import: tolerant parsing, idempotence on the P-number, reported skips."""

from __future__ import annotations

import csv
import json
from contextlib import contextmanager

import pytest
from sqlalchemy import func, select

from backend.catalogue import import_catalogue, normalize_record, parse_length_mm
from backend.db import make_engine, make_sessionmaker, session_scope
from backend.tables import Tablet

REAL_CSV = "/work/shared/data/oracc-catalogue/oracc_catalogue_merged.csv"


@pytest.mark.parametrize(
    ("value", "expected_mm"),
    [
        ("45", 45.0),
        ("4.5 cm", 45.0),
        ("4,5cm", 45.0),
        ("45 mm", 45.0),
        (45, 45.0),
        ("0.1 m", 100.0),
    ],
)
def test_lengths_in_any_unit(value, expected_mm):
    assert parse_length_mm(value) == (pytest.approx(expected_mm), None)


@pytest.mark.parametrize("value", [None, "", "?", " n/a ", "-"])
def test_blank_lengths_are_silent(value):
    assert parse_length_mm(value) == (None, None)


@pytest.mark.parametrize("value", ["38 (+) 59", "1l8", "0", "2540", "-3", True])
def test_junk_lengths_are_reported(value):
    length, problem = parse_length_mm(value)
    assert length is None
    assert problem and repr(value) in problem


def test_normalize_falls_back_and_keeps_the_rest():
    fields, problems, skip = normalize_record(
        {"_key": "p001229", "museum_no": " VAT  15259 ", "height": "4.5 cm", "uri": "http://x"}
    )
    assert skip is None and problems == []
    assert fields["p_number"] == "P001229"
    assert fields["designation"] == "VAT 15259"  # from museum_no, whitespace collapsed
    assert fields["height_mm"] == pytest.approx(45.0)
    assert fields["extra"] == {"uri": "http://x"}


def _write_csv(path, rows):
    columns = ["id_text", "designation", "period", "genre", "height", "width", "notes"]
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({c: row.get(c, "") for c in columns})


ROWS = [
    {"id_text": "P000101", "designation": "BM 1", "period": "Ur III", "height": "45"},
    {"id_text": "P000102", "designation": "BM 2", "period": "Ur III", "width": "junk"},
    {"id_text": "", "designation": "no number"},
    {"id_text": "K 1234", "designation": "bad number"},
    {"id_text": "P000101", "designation": "BM 1 again"},
    {"id_text": "Q000103", "designation": "composite", "genre": "literary"},
]


@contextmanager
def _sessionmaker(url):
    engine = make_engine(url)
    try:
        yield make_sessionmaker(engine)
    finally:
        engine.dispose()


def test_import_reports_and_is_idempotent(db_url, tmp_path):
    source = tmp_path / "cat.csv"
    _write_csv(source, ROWS)
    with _sessionmaker(db_url) as factory:
        _import_twice_then_change(factory, source)


def _import_twice_then_change(factory, source):
    with session_scope(factory) as session:
        summary = import_catalogue(session, source, is_public=True)
    assert (summary.read, summary.inserted, summary.updated, summary.skipped) == (6, 3, 0, 3)
    assert summary.skip_counts == {"no P-number": 1, "bad P-number": 1, "duplicate P-number": 1}
    assert summary.fields_blanked == 1
    text = summary.text()
    assert "line 3 (P000102): width 'junk' is not a length; left blank" in text
    assert "line 6 (P000101): skipped: duplicate of line 2" in text

    with session_scope(factory) as session:
        again = import_catalogue(session, source)
    assert (again.inserted, again.updated, again.unchanged) == (0, 0, 3)

    rows_changed = [dict(ROWS[0], period="Old Babylonian"), *ROWS[1:]]
    _write_csv(source, rows_changed)
    with session_scope(factory) as session:
        changed = import_catalogue(session, source)
        tablet = session.scalar(select(Tablet).where(Tablet.p_number == "P000101"))
        assert tablet.period == "Old Babylonian"
        assert tablet.is_public is True  # not given on re-import: left as it was
        assert tablet.height_mm == pytest.approx(45.0)
    assert (changed.inserted, changed.updated, changed.unchanged) == (0, 1, 2)


def test_import_jsonl_with_broken_lines(sqlite_url, tmp_path):
    source = tmp_path / "cat.jsonl"
    source.write_text(
        json.dumps({"id_text": "P000201", "designation": "A", "langs": ["Akkadian"]})
        + "\n{not json\n[1, 2]\n\n"
        + json.dumps({"_key": "X000202", "designation": "B", "thickness": 20})
        + "\n"
    )
    with _sessionmaker(sqlite_url) as factory, session_scope(factory) as session:
        summary = import_catalogue(session, source)
        by_number = {t.p_number: t for t in session.scalars(select(Tablet))}
    assert (summary.read, summary.inserted, summary.skipped) == (4, 2, 2)
    assert summary.skip_counts == {"not JSON": 1, "not a JSON object": 1}
    assert by_number["P000201"].language == "Akkadian"
    assert by_number["X000202"].thickness_mm == pytest.approx(20.0)
    assert by_number["X000202"].is_public is False  # new records are private by default


def test_unknown_format_is_refused(sqlite_url, tmp_path):
    source = tmp_path / "cat.xlsx"
    source.write_bytes(b"PK")
    with (
        _sessionmaker(sqlite_url) as factory,
        session_scope(factory) as session,
        pytest.raises(ValueError, match="xlsx"),
    ):
        import_catalogue(session, source)


@pytest.mark.slow
def test_real_extract_imports_completely(sqlite_url):
    with open(REAL_CSV, newline="") as fh:
        rows = list(csv.DictReader(fh))
    with _sessionmaker(sqlite_url) as factory, session_scope(factory) as session:
        summary = import_catalogue(session, REAL_CSV, is_public=True)
        assert session.scalar(select(func.count(Tablet.id))) == len(rows)
        tablet = session.scalar(select(Tablet).where(Tablet.p_number == "P001229"))
    # every row of the extract has an id_text; none is skipped
    assert (summary.inserted, summary.skipped) == (len(rows), 0)
    assert (tablet.designation, tablet.period, tablet.provenience) == (
        "VAT 15259",
        "Uruk IV",
        "Uruk",
    )
