"""Ids are never reused, so a stable URL never names another record later (0009).

SQLite gave a deleted newest tablet's id (7526) to the next record; PostgreSQL's sequences
never did. Both databases through the API, and the SQLite migration with rows in it.
"""

from __future__ import annotations

import sqlite3

from alembic import command
from sqlalchemy import text

from backend.db import alembic_config, make_engine, migrate

API = "/api/v1"
T = "2026-01-01"


def test_a_deleted_records_id_is_not_given_to_the_next_one(client, world):
    headers = world.headers("staff_own")
    newest = client.post(f"{API}/tablets", json={"designation": "Newest"}, headers=headers)
    gone = newest.json()["id"]
    assert client.delete(f"{API}/tablets/{gone}", headers=headers).status_code == 204
    after = client.post(f"{API}/tablets", json={"designation": "After"}, headers=headers)
    assert after.json()["id"] > gone
    assert client.get(f"{API}/tablets/{gone}", headers=headers).status_code == 404


def test_every_table_with_ids_in_urls_never_reuses_them(world):
    # Rows of every kind: the newest of each deleted, then a new one of each.
    tablet = world.new_tablet()
    model = world.new_model(tablet)
    with world.session() as session:
        ids = {
            table: session.execute(text(f"SELECT max(id) FROM {table}")).scalar()
            for table in ("tablets", "scans", "jobs", "models")
        }
        session.execute(text("DELETE FROM models WHERE id = :id"), {"id": model})
        session.execute(text("DELETE FROM tablets WHERE id = :id"), {"id": tablet})
    tablet = world.new_tablet()
    world.new_model(tablet)
    with world.session() as session:
        for table, old in ids.items():
            assert session.execute(text(f"SELECT max(id) FROM {table}")).scalar() > old, table


def _schema(path) -> dict:
    with sqlite3.connect(path) as conn:
        rows = conn.execute(
            "SELECT type, name FROM sqlite_master WHERE name NOT LIKE 'sqlite_%'"
        ).fetchall()
    return sorted(rows)


def test_the_sqlite_migration_keeps_rows_indexes_triggers_and_search(tmp_path):
    path = tmp_path / "old.db"
    url = f"sqlite:///{path}"
    migrate(url, "0008_annotations")
    before = _schema(path)
    engine = make_engine(url)
    with engine.begin() as conn:
        conn.execute(
            text("INSERT INTO institutions (id, name, created_at) VALUES (1, 'M', :t)"), {"t": T}
        )
        for i, word in ((1, "ziggurat"), (7526, "ziggurat newest")):
            conn.execute(
                text(
                    "INSERT INTO tablets (id, designation, institution_id, is_public, has_3d, "
                    "extra, created_at, updated_at) VALUES (:i, :d, 1, 1, 0, '{}', :t, :t)"
                ),
                {"i": i, "d": f"Kept {word}", "t": T},
            )
        conn.execute(
            text(
                "INSERT INTO scans (id, tablet_id, face, bundle_key, bundle_sha256, size_bytes, "
                "manifest, created_at) VALUES (3, 7526, 'obverse', 'k', :sha, 1, '{}', :t)"
            ),
            {"sha": "0" * 64, "t": T},
        )
    engine.dispose()

    migrate(url)
    assert _schema(path) == before  # every index and trigger made again
    engine = make_engine(url)  # foreign keys on, as the service runs
    with engine.begin() as conn:
        assert conn.execute(text("PRAGMA foreign_key_check")).all() == []
        assert conn.execute(text("SELECT tablet_id FROM scans")).scalar() == 7526
        # The newest deleted (its scan goes with it, ON DELETE CASCADE), then a new record.
        conn.execute(text("DELETE FROM tablets WHERE id = 7526"))
        assert conn.execute(text("SELECT count(*) FROM scans")).scalar() == 0
        conn.execute(
            text(
                "INSERT INTO tablets (designation, is_public, has_3d, extra, created_at, "
                "updated_at) VALUES ('New ziggurat', 1, 0, '{}', :t, :t)"
            ),
            {"t": T},
        )
        new_id = conn.execute(text("SELECT max(id) FROM tablets")).scalar()
        assert new_id == 7527
        hits = conn.execute(
            text("SELECT rowid FROM tablets_fts WHERE tablets_fts MATCH 'ziggurat'")
        ).scalars()
        assert sorted(hits) == [1, new_id]  # the full-text triggers still feed the index
    engine.dispose()

    command.downgrade(alembic_config(url), "0008_annotations")
    assert _schema(path) == before
    with sqlite3.connect(path) as conn:
        assert conn.execute("SELECT count(*) FROM tablets").fetchone() == (2,)
