"""free-text search also over period, genre, subgenre, provenience, language and collection,
regardless of diacritics on PostgreSQL too

Revision ID: 0004_search
Revises: 0003_p_number
Create Date: 2026-11-27 16:30:00

Scholars type "Ur III" or "Puzris-Dagan" into the search box: the catalogue's period and
provenience must match, with or without diacritics. SQLite's FTS5 tokenizer already folds
diacritics (unicode61 remove_diacritics 2); PostgreSQL's 'simple' configuration does not, so
the tsvector is built from ``f_unaccent`` (the contrib ``unaccent`` dictionary behind an
IMMUTABLE wrapper, which a generated column requires; ``unaccent()`` itself is only STABLE
because its dictionary could be changed: here it is named explicitly).
"""

from collections.abc import Sequence

from alembic import op

revision: str = "0004_search"
down_revision: str | None = "0003_p_number"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

OLD_COLUMNS = (
    "designation",
    "p_number",
    "museum_no",
    "excavation_no",
    "primary_publication",
    "notes",
)
NEW_COLUMNS = (
    *OLD_COLUMNS,
    "period",
    "genre",
    "subgenre",
    "provenience",
    "language",
    "collection",
)

F_UNACCENT = """
CREATE OR REPLACE FUNCTION f_unaccent(text) RETURNS text
LANGUAGE sql IMMUTABLE PARALLEL SAFE STRICT
AS $$ SELECT unaccent('unaccent'::regdictionary, $1) $$
"""


def _sqlite_drop() -> None:
    for trigger in ("tablets_fts_ai", "tablets_fts_ad", "tablets_fts_au"):
        op.execute(f"DROP TRIGGER IF EXISTS {trigger}")
    op.execute("DROP TABLE IF EXISTS tablets_fts")


def _sqlite_create(columns: Sequence[str]) -> None:
    cols = ", ".join(columns)
    new = ", ".join(f"new.{c}" for c in columns)
    old = ", ".join(f"old.{c}" for c in columns)
    op.execute(
        f"CREATE VIRTUAL TABLE tablets_fts USING fts5({cols}, content='tablets', "
        "content_rowid='id', tokenize='unicode61 remove_diacritics 2')"
    )
    op.execute(
        "CREATE TRIGGER tablets_fts_ai AFTER INSERT ON tablets BEGIN "
        f"INSERT INTO tablets_fts(rowid, {cols}) VALUES (new.id, {new}); END"
    )
    op.execute(
        "CREATE TRIGGER tablets_fts_ad AFTER DELETE ON tablets BEGIN "
        f"INSERT INTO tablets_fts(tablets_fts, rowid, {cols}) VALUES ('delete', old.id, {old}); END"
    )
    op.execute(
        f"CREATE TRIGGER tablets_fts_au AFTER UPDATE OF {cols} ON tablets BEGIN "
        f"INSERT INTO tablets_fts(tablets_fts, rowid, {cols}) VALUES ('delete', old.id, {old}); "
        f"INSERT INTO tablets_fts(rowid, {cols}) VALUES (new.id, {new}); END"
    )
    op.execute("INSERT INTO tablets_fts(tablets_fts) VALUES ('rebuild')")


def _pg_vector(columns: Sequence[str], *, unaccent: bool) -> None:
    document = " || ' ' || ".join(f"coalesce({c}, '')" for c in columns)
    if unaccent:
        document = f"f_unaccent({document})"
    op.execute("DROP INDEX IF EXISTS ix_tablets_search_vector")
    op.execute("ALTER TABLE tablets DROP COLUMN IF EXISTS search_vector")
    op.execute(
        "ALTER TABLE tablets ADD COLUMN search_vector tsvector "
        f"GENERATED ALWAYS AS (to_tsvector('simple'::regconfig, {document})) STORED"
    )
    op.execute("CREATE INDEX ix_tablets_search_vector ON tablets USING GIN (search_vector)")


def upgrade() -> None:
    dialect = op.get_bind().dialect.name
    if dialect == "sqlite":
        _sqlite_drop()
        _sqlite_create(NEW_COLUMNS)
    elif dialect == "postgresql":
        op.execute("CREATE EXTENSION IF NOT EXISTS unaccent")
        op.execute(F_UNACCENT)
        _pg_vector(NEW_COLUMNS, unaccent=True)


def downgrade() -> None:
    dialect = op.get_bind().dialect.name
    if dialect == "sqlite":
        _sqlite_drop()
        _sqlite_create(OLD_COLUMNS)
    elif dialect == "postgresql":
        _pg_vector(OLD_COLUMNS, unaccent=False)
        op.execute("DROP FUNCTION IF EXISTS f_unaccent(text)")
