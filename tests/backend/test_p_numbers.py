"""P-numbers are unique per institution (docs/api.md "P-numbers"), on both databases.

The world (conftest.py): A holds P000001 (public) and P000002 (private), B holds P000003
(private). No caller learns that a private record exists, and no institution can block
another from registering its own record of a tablet.
"""

from __future__ import annotations

import pytest
from sqlalchemy import text

from backend import crud
from backend.db import alembic_config, make_engine, migrate

API = "/api/v1"


def create(client, world, role, p_number, **fields):
    body = {"designation": f"{role} {p_number}", "p_number": p_number, **fields}
    return client.post(f"{API}/tablets", json=body, headers=world.headers(role))


def get(client, world, role, ref):
    return client.get(f"{API}/tablets/{ref}", headers=world.headers(role))


def test_a_private_p_number_of_another_institution_neither_blocks_nor_leaks(client, world):
    response = create(client, world, "staff_other", "P000002")  # A holds it privately
    assert response.status_code == 201, response.text
    b_record = response.json()["id"]
    assert b_record != world.private_a
    # Each institution's staff reach their own record by the P-number; others see nothing.
    assert get(client, world, "staff_other", "P000002").json()["id"] == b_record
    assert get(client, world, "staff_own", "P000002").json()["id"] == world.private_a
    assert get(client, world, "anonymous", "P000002").status_code == 404
    assert get(client, world, "reader", "P000002").status_code == 404


def test_claiming_first_does_not_block_the_owner(client, world):
    assert create(client, world, "staff_other", "P123456").status_code == 201
    assert create(client, world, "staff_own", "P123456").status_code == 201


def test_a_duplicate_within_one_institution_is_409(client, world):
    response = create(client, world, "staff_other", "P000003")  # B's own record
    assert response.status_code == 409 and response.json()["where"] == "p_number"
    assert "P000003" in response.json()["detail"]


def test_which_record_a_p_number_names(client, world):
    # Public A's P000001 is what everybody sees until B has its own.
    assert get(client, world, "staff_other", "P000001").json()["id"] == world.public_a
    own = create(client, world, "staff_other", "P000001", is_public=True).json()["id"]
    assert get(client, world, "staff_other", "P000001").json()["id"] == own
    assert get(client, world, "anonymous", "P000001").json()["id"] == world.public_a  # oldest
    # A record of no institution (the shared catalogue) comes before other public ones.
    shared = create(client, world, "admin", "P000001", is_public=True).json()["id"]
    assert get(client, world, "anonymous", "P000001").json()["id"] == shared
    assert get(client, world, "staff_own", "P000001").json()["id"] == world.public_a
    assert create(client, world, "admin", "P000001").status_code == 409  # no institution: once


def test_changing_a_p_number_checks_the_records_institution_only(client, world):
    mine = create(client, world, "staff_other", "P200000").json()["id"]
    patch = client.patch(
        f"{API}/tablets/{mine}", json={"p_number": "P000002"}, headers=world.headers("staff_other")
    )
    assert patch.status_code == 200  # A's private P000002 does not matter
    patch = client.patch(
        f"{API}/tablets/{mine}", json={"p_number": "P000003"}, headers=world.headers("staff_other")
    )
    assert patch.status_code == 409
    # An admin moving a record into an institution that has the P-number: 409.
    move = client.patch(
        f"{API}/tablets/{mine}",
        json={"institution_id": world.institution_a},
        headers=world.headers("admin"),
    )
    assert move.status_code == 409 and move.json()["where"] == "p_number"


@pytest.mark.parametrize("institution", ["a", None])
def test_the_database_refuses_a_duplicate_the_check_missed(world, monkeypatch, institution):
    """Two concurrent registrations both pass the check; the unique index decides."""
    world.new_tablet(institution=institution, p_number="P300000")
    monkeypatch.setattr(crud, "p_number_taken", lambda *a, **k: False)
    with pytest.raises(ValueError, match="already has a record P300000"):
        world.new_tablet(institution=institution, p_number="P300000")
    world.new_tablet(institution="b", p_number="P300000")  # another institution: fine


def test_migration_keeps_rows_and_search(db_url):
    """0002 -> head with data: tablets, their scans and the full-text index survive."""
    from alembic import command

    command.downgrade(alembic_config(db_url), "0002")
    engine = make_engine(db_url)
    with engine.begin() as conn:
        conn.execute(
            text("INSERT INTO institutions (id, name, created_at) VALUES (1, 'M', :t)"),
            {"t": "2026-01-01"},
        )
        conn.execute(
            text(
                "INSERT INTO tablets (id, designation, p_number, institution_id, is_public, "
                "has_3d, extra, created_at, updated_at) VALUES (1, 'Kept ziggurat', 'P000009', "
                "1, true, false, '{}', :t, :t)"
            ),
            {"t": "2026-01-01"},
        )
        conn.execute(
            text(
                "INSERT INTO scans (id, tablet_id, face, bundle_key, bundle_sha256, size_bytes, "
                "manifest, created_at) VALUES (1, 1, 'obverse', 'k', :sha, 1, '{}', :t)"
            ),
            {"sha": "0" * 64, "t": "2026-01-01"},
        )
    engine.dispose()
    migrate(db_url)
    engine = make_engine(db_url)
    with engine.begin() as conn:
        assert conn.execute(text("SELECT count(*) FROM scans")).scalar() == 1
        conn.execute(
            text(
                "INSERT INTO tablets (id, designation, p_number, institution_id, is_public, "
                "has_3d, extra, created_at, updated_at) VALUES (2, 'New ziggurat', 'P000009', "
                "NULL, true, false, '{}', :t, :t)"
            ),
            {"t": "2026-01-01"},
        )
        if conn.dialect.name == "sqlite":  # the rebuilt table's triggers feed the index again
            hits = conn.execute(
                text("SELECT rowid FROM tablets_fts WHERE tablets_fts MATCH 'ziggurat'")
            ).scalars()
            assert sorted(hits) == [1, 2]
    engine.dispose()


@pytest.mark.parametrize("digits", ["４５１８０６", "٤٥١٨٠٦"])  # fullwidth, Arabic-Indic
def test_only_ascii_digits_make_a_p_number_or_an_id(client, world, digits):
    # Python's and pydantic's \d take any Unicode digit: "P４５１８０６" was stored as a
    # P-number, and /tablets/１ answered as tablet 1, a second URL for one record.
    assert (
        create(client, world, "admin", f"P{digits}", institution_id=world.institution_a).status_code
        == 422
    )
    assert get(client, world, "admin", f"P{digits}").status_code == 422
    assert get(client, world, "admin", digits[0]).status_code == 422
    assert get(client, world, "admin", str(world.public_a)).status_code == 200


@pytest.mark.parametrize("ref", ["p000001", "P000001", "p000002"])
def test_a_p_number_in_the_path_is_case_insensitive(client, world, ref):
    # Scholars type "p451806": it names the same record as "P451806" (stored upper case).
    expected = {"000001": world.public_a, "000002": world.private_a}[ref[1:]]
    response = get(client, world, "staff_own", ref)
    assert response.status_code == 200, response.text
    assert response.json()["id"] == expected
    assert response.json()["p_number"] == ref.upper()
    manifest = client.get(f"{API}/tablets/{ref}/scans", headers=world.headers("staff_own"))
    assert manifest.status_code == 200, manifest.text
    # ...and stays hidden from whoever may not read it, in either case.
    if ref[1:] == "000002":
        assert get(client, world, "anonymous", ref).status_code == 404
