"""Import of catalogue records (CDLI/ORACC style) from CSV or JSON-lines.

Idempotent on the P-number (CDLI ``P123456``; ORACC composite ``Q...`` and ``X...`` numbers
are keys of the same kind): a record already in the library is updated in place, an unchanged
one is left alone, a new one is inserted. Tolerant of what museums actually write: blanks,
"?" for unknown, dimensions as "45", "4.5 cm" or junk (left blank and reported). Rows that
cannot be keyed (no P-number) are skipped with the reason.

Fast: one query loads the existing records, new rows go in as bulk INSERTs and changed rows
as bulk UPDATEs by primary key (the FTS triggers/generated tsvector keep search in sync).
"""

from __future__ import annotations

import csv
import json
import re
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sqlalchemy import insert, select, update
from sqlalchemy.orm import Session

from backend.atf import MAX_ATF_CHARS
from backend.tables import Tablet

P_NUMBER = re.compile(r"^[PQX][0-9]{6}$")
TEXT_FIELDS: dict[str, int] = {  # column -> max length (as in tables.py)
    "designation": 300,
    "museum_no": 300,
    "collection": 300,
    "owner": 300,
    "excavation_no": 300,
    "period": 200,
    "provenience": 200,
    "genre": 200,
    "subgenre": 300,
    "language": 200,
    "material": 200,
    "object_type": 200,
    "primary_publication": 5000,
    "notes": 20000,
}
LENGTH_FIELDS = {"height": "height_mm", "width": "width_mm", "thickness": "thickness_mm"}
KEY_FIELDS = ("id_text", "key", "_key", "p_number")
ATF_FIELD = "atf"  # the transliteration: kept line by line, unlike the one-line text fields
BLANK_VALUES = {"", "?", "??", "-", "--", "n/a", "na", "none", "null", "unknown", "unk"}
MAX_LENGTH_MM = 2000.0  # the largest inscribed objects (steles) are ~2.3 m; tablets far less
_LENGTH = re.compile(r"^(\d+(?:[.,]\d+)?)\s*(mm|cm|m)?\.?$", re.IGNORECASE)
_UNIT_MM = {None: 1.0, "mm": 1.0, "cm": 10.0, "m": 1000.0}
BATCH_ROWS = 1000


@dataclass
class ImportSummary:
    """What an import did; ``reasons`` keeps the first ``max_reasons`` explanations."""

    source: str
    read: int = 0
    inserted: int = 0
    updated: int = 0
    unchanged: int = 0
    skipped: int = 0
    fields_blanked: int = 0
    skip_counts: Counter = field(default_factory=Counter)
    reasons: list[str] = field(default_factory=list)
    max_reasons: int = 20

    def note(self, where: str, message: str) -> None:
        if len(self.reasons) < self.max_reasons:
            self.reasons.append(f"{where}: {message}")

    def text(self) -> str:
        lines = [
            f"{self.source}: read {self.read} records: {self.inserted} inserted, "
            f"{self.updated} updated, {self.unchanged} unchanged, {self.skipped} skipped",
        ]
        if self.skip_counts:
            lines.append(
                "skipped: " + ", ".join(f"{n} {why}" for why, n in self.skip_counts.most_common())
            )
        if self.fields_blanked:
            lines.append(f"odd values left blank: {self.fields_blanked}")
        if self.reasons:
            lines.append(f"first {len(self.reasons)} reasons:")
            lines.extend(f"  {reason}" for reason in self.reasons)
        return "\n".join(lines)


def parse_length_mm(value: Any) -> tuple[float | None, str | None]:
    """A length in mm from "45", "4.5 cm", "45 mm", 45; (None, why) for junk, (None, None) blank."""
    if value is None:
        return None, None
    if isinstance(value, bool):
        return None, f"{value!r} is not a length"
    if isinstance(value, int | float):
        number, unit = float(value), None
    else:
        text = str(value).strip()
        if text.lower() in BLANK_VALUES:
            return None, None
        match = _LENGTH.match(text)
        if match is None:
            return None, f"{text!r} is not a length"
        number, unit = float(match.group(1).replace(",", ".")), match.group(2)
        unit = unit.lower() if unit else None
    length_mm = number * _UNIT_MM[unit]
    if not 0 < length_mm <= MAX_LENGTH_MM:
        return None, f"{value!r} is outside (0, {MAX_LENGTH_MM:g}] mm"
    return length_mm, None


def _text(value: Any) -> str | None:
    if value is None:
        return None
    if isinstance(value, list):
        value = "; ".join(str(v) for v in value if v not in (None, ""))
    text = " ".join(str(value).split())
    return None if text.lower() in BLANK_VALUES else text


def _atf(value: Any) -> tuple[str | None, str | None]:
    """The ATF text with its lines kept (one newline style, trailing blanks dropped)."""
    if value is None or isinstance(value, bool) or not isinstance(value, str | list):
        return (
            None,
            None if value is None else f"atf {type(value).__name__} is not text; left blank",
        )
    text = "\n".join(value) if isinstance(value, list) else value
    lines = [line.rstrip() for line in text.replace("\r\n", "\n").replace("\r", "\n").split("\n")]
    text = "\n".join(lines).strip("\n")
    if not text.strip():
        return None, None
    if len(text) > MAX_ATF_CHARS:
        return None, f"atf longer than {MAX_ATF_CHARS} characters; left blank"
    return text, None


def _p_number(raw: dict[str, Any]) -> str | None:
    for key in KEY_FIELDS:
        value = raw.get(key)
        if isinstance(value, str) and value.strip():
            return value.strip().upper()
    return None


def normalize_record(raw: dict[str, Any]) -> tuple[dict[str, Any] | None, list[str], str | None]:
    """Catalogue record -> (tablet fields, problems with single fields, reason to skip)."""
    p_number = _p_number(raw)
    if p_number is None:
        return None, [], "no P-number"
    if not P_NUMBER.match(p_number):
        return None, [], f"P-number {p_number[:40]!r} is not like P123456"
    problems: list[str] = []
    fields: dict[str, Any] = {"p_number": p_number}
    for name, max_chars in TEXT_FIELDS.items():
        value = _text(raw.get(name))
        if value is not None and len(value) > max_chars:
            problems.append(f"{name} longer than {max_chars} characters; cut")
            value = value[:max_chars]
        fields[name] = value
    if fields["language"] is None and raw.get("langs"):
        fields["language"] = _text(raw.get("langs"))
    fields["designation"] = fields["designation"] or fields["museum_no"] or p_number
    fields[ATF_FIELD], problem = _atf(raw.get(ATF_FIELD))
    if problem:
        problems.append(problem)
    for source, column in LENGTH_FIELDS.items():
        length_mm, problem = parse_length_mm(raw.get(source, raw.get(column)))
        if problem:
            problems.append(f"{source} {problem}; left blank")
        fields[column] = length_mm
    used = set(TEXT_FIELDS) | set(LENGTH_FIELDS) | set(LENGTH_FIELDS.values()) | set(KEY_FIELDS)
    used.add(ATF_FIELD)
    fields["extra"] = {
        k.lstrip("_"): v for k, v in raw.items() if k not in used and v not in (None, "", [], {})
    }
    return fields, problems, None


def read_records(path: Path) -> Iterator[tuple[str, dict[str, Any] | None, str | None]]:
    """(where, record, error) per record of a .csv or .jsonl file; where is "line N"."""
    suffix = path.suffix.lower()
    if suffix == ".csv":
        with path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            if not reader.fieldnames:
                raise ValueError(f"{path}: empty CSV file (no header)")
            for row in reader:
                yield f"line {reader.line_num}", row, None
    elif suffix in (".jsonl", ".ndjson", ".json"):
        with path.open(encoding="utf-8-sig") as fh:
            for number, line in enumerate(fh, 1):
                if not line.strip():
                    continue
                try:
                    record = json.loads(line)
                except json.JSONDecodeError as exc:
                    yield f"line {number}", None, f"not JSON ({exc.msg})"
                    continue
                if not isinstance(record, dict):
                    yield f"line {number}", None, "not a JSON object"
                    continue
                yield f"line {number}", record, None
    else:
        raise ValueError(f"{path}: unknown format {suffix!r}; use .csv or .jsonl")


_COMPARED = [*TEXT_FIELDS, ATF_FIELD, "height_mm", "width_mm", "thickness_mm", "extra"]


def import_catalogue(
    session: Session,
    path: Path,
    *,
    institution_id: int | None = None,
    is_public: bool | None = None,
    max_reasons: int = 20,
) -> ImportSummary:
    """Insert or update the records of ``path``; flushes, never commits (the caller does).

    ``institution_id`` and ``is_public`` are applied to every record of the file when given;
    when ``is_public`` is None new records are private and existing ones keep their setting.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"file: {path} does not exist")
    summary = ImportSummary(source=str(path), max_reasons=max_reasons)
    wanted: dict[str, tuple[str, dict[str, Any]]] = {}
    for where, raw, error in read_records(path):
        summary.read += 1
        if error is not None:
            summary.skipped += 1
            summary.skip_counts[error.split(" (")[0]] += 1
            summary.note(where, f"skipped: {error}")
            continue
        fields, problems, skip = normalize_record(raw)
        label = f"{where} ({fields['p_number']})" if fields else where
        if skip is not None:
            summary.skipped += 1
            summary.skip_counts[skip if skip == "no P-number" else "bad P-number"] += 1
            summary.note(label, f"skipped: {skip}")
            continue
        if fields["p_number"] in wanted:
            summary.skipped += 1
            summary.skip_counts["duplicate P-number"] += 1
            summary.note(label, f"skipped: duplicate of {wanted[fields['p_number']][0]}")
            continue
        summary.fields_blanked += len(problems)
        for problem in problems:
            summary.note(label, problem)
        wanted[fields["p_number"]] = (where, fields)

    columns = [getattr(Tablet, c) for c in _COMPARED]
    # A P-number is unique per institution (crud.p_number_taken): the file's records are
    # matched with that institution's records only (or those of no institution).
    scope = (
        Tablet.institution_id.is_(None)
        if institution_id is None
        else Tablet.institution_id == institution_id
    )
    existing = {
        row.p_number: row
        for row in session.execute(
            select(
                Tablet.id, Tablet.p_number, Tablet.is_public, Tablet.institution_id, *columns
            ).where(Tablet.p_number.is_not(None), scope)
        )
    }
    now = datetime.now(UTC)
    new_rows, changed_rows = [], []
    for p_number, (_where, fields) in wanted.items():
        old = existing.get(p_number)
        if old is None:
            row = dict(fields, created_at=now, updated_at=now, has_3d=False)
            row["is_public"] = bool(is_public)
            row["institution_id"] = institution_id
            new_rows.append(row)
            continue
        change = {c: fields[c] for c in _COMPARED if getattr(old, c) != fields[c]}
        if is_public is not None and old.is_public != is_public:
            change["is_public"] = is_public
        if change:
            changed_rows.append(dict(change, id=old.id, updated_at=now))
        else:
            summary.unchanged += 1
    # Core INSERT (executemany): the ORM's bulk path is ~3x slower on PostgreSQL.
    for start in range(0, len(new_rows), BATCH_ROWS):
        session.execute(insert(Tablet.__table__), new_rows[start : start + BATCH_ROWS])
    # Bulk UPDATE by primary key wants the same keys in every row: group by key set.
    by_keys: dict[tuple[str, ...], list[dict[str, Any]]] = {}
    for row in changed_rows:
        by_keys.setdefault(tuple(sorted(row)), []).append(row)
    for rows in by_keys.values():
        session.execute(update(Tablet), rows)
    summary.inserted, summary.updated = len(new_rows), len(changed_rows)
    session.flush()
    return summary
