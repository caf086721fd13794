"""Catalogue search: full text, filters, facets, sort and paging on SQLite and PostgreSQL.

The one module that knows how each database does full-text search:

- SQLite: the FTS5 table ``tablets_fts`` (external content, kept in sync by triggers made in
  the initial migration); relevance is FTS5's bm25 ``rank`` (lower is better).
- PostgreSQL: the generated ``tablets.search_vector`` tsvector ('simple' configuration, GIN
  index); relevance is ``ts_rank`` (higher is better).

Query text is cut into word tokens (``\\w+``); every token must match as a word prefix
(``vat 152`` finds "VAT 15259"). Searched columns: designation, P-number, museum number,
excavation number, primary publication and notes.

Facets count values among the records that match the query text and every *other* filter
(the usual multi-select facets: choosing "Old Babylonian" still lists the other periods
with the counts they would give). Values within one filter are alternatives (OR); different
filters must all hold (AND).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import sqlalchemy as sa
from sqlalchemy import ColumnElement, Select, func, select
from sqlalchemy.orm import Session

from backend.crud import visible_clause
from backend.tables import Tablet, User

FILTER_FIELDS: tuple[str, ...] = ("period", "provenience", "genre", "collection", "language")
FACET_FIELDS: tuple[str, ...] = (*FILTER_FIELDS, "has_3d")
SORT_FIELDS: dict[str, sa.orm.InstrumentedAttribute] = {
    "designation": Tablet.designation,
    "p_number": Tablet.p_number,
    "museum_no": Tablet.museum_no,
    "period": Tablet.period,
    "provenience": Tablet.provenience,
    "genre": Tablet.genre,
    "collection": Tablet.collection,
    "created_at": Tablet.created_at,
    "updated_at": Tablet.updated_at,
    "id": Tablet.id,
}
SORT_CHOICES: tuple[str, ...] = (
    "relevance",
    *SORT_FIELDS,
    *(f"-{name}" for name in SORT_FIELDS),
)
MAX_QUERY_TOKENS = 16
_TOKEN = re.compile(r"\w+", re.UNICODE)


@dataclass(frozen=True)
class SearchQuery:
    """One search request. ``filters`` maps a FILTER_FIELDS name to accepted values."""

    q: str | None = None
    filters: dict[str, tuple[str, ...]] = field(default_factory=dict)
    has_3d: bool | None = None
    sort: str | None = None
    page: int = 1
    page_size: int = 25

    def __post_init__(self) -> None:
        unknown = set(self.filters) - set(FILTER_FIELDS)
        if unknown:
            raise ValueError(f"filters: unknown field(s) {sorted(unknown)}")
        if self.sort is not None and self.sort not in SORT_CHOICES:
            raise ValueError(f"sort: {self.sort!r} is not one of {', '.join(SORT_CHOICES)}")
        if self.page < 1:
            raise ValueError("page: must be at least 1")
        if self.page_size < 1:
            raise ValueError("page_size: must be at least 1")


@dataclass(frozen=True)
class SearchResult:
    items: list[Tablet]
    total: int
    facets: dict[str, list[tuple[str | bool | None, int]]]


def query_tokens(q: str | None) -> list[str]:
    """Lower-case word tokens of the query text (at most MAX_QUERY_TOKENS)."""
    if not q:
        return []
    return [t.lower() for t in _TOKEN.findall(q)][:MAX_QUERY_TOKENS]


class _TextMatch:
    """The dialect-specific pieces of a text search: a join target and a relevance order."""

    def __init__(self, dialect: str, tokens: list[str]):
        self.dialect = dialect
        if dialect == "sqlite":
            # Tokens are \w+ only, so quoting them cannot break the FTS5 syntax.
            match = " ".join(f'"{t}"*' for t in tokens)
            fts = sa.table("tablets_fts", sa.column("rowid"), sa.column("rank"))
            self.subquery = (
                select(fts.c.rowid.label("tablet_id"), fts.c.rank.label("score"))
                .where(sa.literal_column("tablets_fts").op("MATCH")(sa.literal(match)))
                .subquery("text_match")
            )
            self.order = self.subquery.c.score.asc()
        elif dialect == "postgresql":
            tsquery = " & ".join(f"{t}:*" for t in tokens)
            vector = sa.literal_column("tablets.search_vector")
            query = func.to_tsquery(sa.literal_column("'simple'::regconfig"), sa.literal(tsquery))
            self.condition = vector.op("@@")(query)
            self.order = func.ts_rank(vector, query).desc()
            self.subquery = None
        else:
            raise ValueError(f"dialect: full-text search not available for {dialect!r}")

    def apply(self, stmt: Select) -> Select:
        if self.subquery is not None:
            return stmt.join(self.subquery, self.subquery.c.tablet_id == Tablet.id)
        return stmt.where(self.condition)


def _conditions(query: SearchQuery, user: User | None) -> dict[str, ColumnElement[bool]]:
    """Named conditions: one per filter in force, plus visibility (key '')."""
    conditions: dict[str, ColumnElement[bool]] = {"": visible_clause(user)}
    for name, values in query.filters.items():
        if values:
            conditions[name] = getattr(Tablet, name).in_(values)
    if query.has_3d is not None:
        conditions["has_3d"] = Tablet.has_3d.is_(query.has_3d)
    return conditions


def _filtered(
    stmt: Select, conditions: dict[str, ColumnElement[bool]], text: _TextMatch | None, *, skip=""
) -> Select:
    if text is not None:
        stmt = text.apply(stmt)
    for name, condition in conditions.items():
        if name != skip or name == "":
            stmt = stmt.where(condition)
    return stmt


def _order(query: SearchQuery, text: _TextMatch | None) -> list:
    sort = query.sort or ("relevance" if text is not None else "designation")
    if sort == "relevance":
        if text is None:
            return [Tablet.designation.asc(), Tablet.id.asc()]
        return [text.order, Tablet.id.asc()]
    column = SORT_FIELDS[sort.lstrip("-")]
    direction = column.desc() if sort.startswith("-") else column.asc()
    # NULLs last either way, then id for a stable order across pages.
    return [column.is_(None), direction, Tablet.id.asc()]


def search_tablets(
    session: Session,
    query: SearchQuery,
    *,
    user: User | None,
    facet_limit: int = 50,
    with_facets: bool = True,
    paged: bool = True,
) -> SearchResult:
    """Records matching ``query`` that ``user`` may see: one page (or all), total, facets."""
    dialect = session.get_bind().dialect.name
    tokens = query_tokens(query.q)
    text = _TextMatch(dialect, tokens) if tokens else None
    conditions = _conditions(query, user)

    stmt = _filtered(select(Tablet), conditions, text).order_by(*_order(query, text))
    if paged:
        stmt = stmt.limit(query.page_size).offset((query.page - 1) * query.page_size)
    items = list(session.scalars(stmt).unique())

    total = session.scalar(
        _filtered(select(func.count(Tablet.id)).select_from(Tablet), conditions, text)
    )
    facets: dict[str, list[tuple[str | bool | None, int]]] = {}
    if with_facets:
        for name in FACET_FIELDS:
            column = getattr(Tablet, name)
            count = func.count(Tablet.id)
            stmt = _filtered(select(column, count).select_from(Tablet), conditions, text, skip=name)
            stmt = stmt.group_by(column).order_by(count.desc(), column).limit(facet_limit)
            facets[name] = [(value, n) for value, n in session.execute(stmt)]
    return SearchResult(items=items, total=int(total or 0), facets=facets)
