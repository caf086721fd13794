"""Catalogue search: full text, filters, facets, sort and paging on SQLite and PostgreSQL.

The one module that knows how each database does full-text search:

- SQLite: the FTS5 table ``tablets_fts`` (external content, kept in sync by triggers made in
  the initial migration); relevance is FTS5's bm25 ``rank`` (lower is better).
- PostgreSQL: the generated ``tablets.search_vector`` tsvector ('simple' configuration over
  ``f_unaccent`` of the columns, GIN index); relevance is ``ts_rank`` (higher is better).

Query text is cut into word tokens (``\\w+``); every token must match as a word prefix
(``vat 152`` finds "VAT 15259"), regardless of case and diacritics on both databases
("puzris" finds "Puzriš"). Searched columns (migration 0004_search): designation, P-number,
museum number, excavation number, primary publication, notes, period, genre, subgenre,
provenience, language and collection, so "Ur III" finds the Ur III tablets. By relevance,
records where every word matches whole come first (the Ur III tablets before the Uruk III
ones "ur" also finds), then by the database's rank.

Facet values are grouped regardless of letter case (catalogues write "Mathematical" and
"mathematical"): a facet lists each value once, under its most frequent spelling, with the
count of all spellings, and filtering on a value accepts every spelling of it. The records
keep the spelling their catalogue gave.

Facets count values among the records that match the query text and every *other* filter
(the usual multi-select facets: choosing "Old Babylonian" still lists the other periods
with the counts they would give). Values within one filter are alternatives (OR); different
filters must all hold (AND).
"""

from __future__ import annotations

import re
import threading
import time
from collections import Counter, OrderedDict
from dataclasses import dataclass, field

import sqlalchemy as sa
from sqlalchemy import ColumnElement, Select, event, func, select
from sqlalchemy.orm import Session

from backend.crud import visible_clause
from backend.tables import Role, Tablet, User

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
    """The dialect-specific pieces of a text search: a filter and a relevance order."""

    def __init__(self, dialect: str, tokens: list[str]):
        self.dialect = dialect
        if dialect == "sqlite":
            # Tokens are \w+ only, so quoting them cannot break the FTS5 syntax.
            match = " ".join(f'"{t}"*' for t in tokens)
            fts = sa.table("tablets_fts", sa.column("rowid"), sa.column("rank"))
            matches = sa.literal_column("tablets_fts").op("MATCH")(sa.literal(match))
            # IN (subquery) is evaluated once per statement; a join on the FTS table would
            # run the MATCH again for every candidate row.
            self.condition = Tablet.id.in_(select(fts.c.rowid).where(matches))
            self.ranked = (
                select(fts.c.rowid.label("tablet_id"), fts.c.rank.label("score"))
                .where(matches)
                .subquery("text_match")
            )
            # Records where every word is whole come first ("Ur III" before "Uruk III"),
            # then bm25: prefixes are for typing, not for outranking what was typed.
            whole = sa.literal_column("tablets_fts").op("MATCH")(
                sa.literal(" ".join(f'"{t}"' for t in tokens))
            )
            whole_first = sa.case((Tablet.id.in_(select(fts.c.rowid).where(whole)), 0), else_=1)
            self.order = [whole_first.asc(), self.ranked.c.score.asc()]
        elif dialect == "postgresql":
            tsquery = " & ".join(f"{t}:*" for t in tokens)
            vector = sa.literal_column("tablets.search_vector")
            query = func.to_tsquery(
                sa.literal_column("'simple'::regconfig"), func.f_unaccent(sa.literal(tsquery))
            )
            self.condition = vector.op("@@")(query)
            whole = func.to_tsquery(
                sa.literal_column("'simple'::regconfig"),
                func.f_unaccent(sa.literal(" & ".join(tokens))),
            )
            whole_first = sa.case((vector.op("@@")(whole), 0), else_=1)
            self.order = [whole_first.asc(), func.ts_rank(vector, query).desc()]
            self.ranked = None
        else:
            raise ValueError(f"dialect: full-text search not available for {dialect!r}")

    def apply(self, stmt: Select, *, ranked: bool = False) -> Select:
        if ranked and self.ranked is not None:
            return stmt.join(self.ranked, self.ranked.c.tablet_id == Tablet.id)
        return stmt.where(self.condition)


def _fold(value):
    """The key a facet value is grouped and filtered by: its case-folded text."""
    return value.casefold() if isinstance(value, str) else value


def _spellings(session: Session, name: str, values: tuple[str, ...]) -> list[str]:
    """Every stored spelling of ``values`` in column ``name`` (same text but for case), so a
    filter stays an index-friendly IN on the column. A facet column holds a few hundred
    distinct values, so reading them is cheap."""
    wanted = {_fold(v) for v in values}
    column = getattr(Tablet, name)
    stored = session.scalars(select(column).where(column.is_not(None)).distinct())
    return sorted({v for v in stored if _fold(v) in wanted} | set(values))


def _conditions(
    session: Session, query: SearchQuery, user: User | None
) -> dict[str, ColumnElement[bool]]:
    """Named conditions: one per filter in force, plus visibility (key '')."""
    conditions: dict[str, ColumnElement[bool]] = {"": visible_clause(user)}
    for name, values in query.filters.items():
        if values:
            conditions[name] = getattr(Tablet, name).in_(_spellings(session, name, values))
    if query.has_3d is not None:
        conditions["has_3d"] = Tablet.has_3d.is_(query.has_3d)
    return conditions


def _filtered(
    stmt: Select,
    conditions: dict[str, ColumnElement[bool]],
    text: _TextMatch | None,
    *,
    ranked: bool = False,
) -> Select:
    if text is not None:
        stmt = text.apply(stmt, ranked=ranked)
    for condition in conditions.values():
        stmt = stmt.where(condition)
    return stmt


def _order(query: SearchQuery, text: _TextMatch | None) -> tuple[list, bool]:
    """ORDER BY terms, and whether they need the ranked text match."""
    sort = query.sort or ("relevance" if text is not None else "designation")
    if sort == "relevance":
        if text is None:
            return [Tablet.designation.asc(), Tablet.id.asc()], False
        return [*text.order, Tablet.id.asc()], True
    column = SORT_FIELDS[sort.lstrip("-")]
    direction = column.desc() if sort.startswith("-") else column.asc()
    # NULLs last either way, then id for a stable order across pages. Without the NULL term
    # on NOT NULL columns, so that an index on the column can give the order.
    nulls_last = [column.is_(None)] if column.nullable else []
    return [*nulls_last, direction, Tablet.id.asc()], False


def _facet_counts(
    rows: list[tuple], query: SearchQuery, facet_limit: int
) -> tuple[int, dict[str, list[tuple[str | bool | None, int]]]]:
    """Total and facet counts from (FACET_FIELDS values) of the visible text matches.

    A facet counts the rows passing every filter except its own; one pass over the rows
    replaces a GROUP BY query per facet (the rows are at most the catalogue, a few columns).
    """
    active = [
        (FACET_FIELDS.index(name), frozenset(_fold(v) for v in values))
        for name, values in query.filters.items()
        if values
    ]
    if query.has_3d is not None:
        active.append((FACET_FIELDS.index("has_3d"), frozenset([query.has_3d])))
    # Counted by spelling, then grouped by case-folded value (a few hundred keys per facet).
    counters = [Counter() for _ in FACET_FIELDS]
    total = 0
    for row in rows:
        failed = [index for index, accepted in active if _fold(row[index]) not in accepted]
        if not failed:
            total += 1
            for index, value in enumerate(row):
                counters[index][value] += 1
        elif len(failed) == 1:
            counters[failed[0]][row[failed[0]]] += 1
    facets = {}
    for name, counter in zip(FACET_FIELDS, counters, strict=True):
        grouped = _group_spellings(counter)
        ordered = sorted(grouped, key=lambda kv: (-kv[1], kv[0] is None, str(kv[0])))
        facets[name] = ordered[:facet_limit]
    return total, facets


def _group_spellings(counter: Counter) -> list[tuple[str | bool | None, int]]:
    """(value, count) with spellings that differ only in case merged under the most frequent
    one (ties: the first in code-point order, so the label is stable)."""
    groups: dict = {}
    for value, count in counter.items():
        groups.setdefault(_fold(value), []).append((value, count))
    merged = []
    for spellings in groups.values():
        label = min(spellings, key=lambda vc: (-vc[1], str(vc[0])))[0]
        merged.append((label, sum(count for _, count in spellings)))
    return merged


class FacetSnapshot:
    """Per-process copy of the facet columns of every tablet, for fast facet counts.

    Holds ``(id, is_public, institution_id, *FACET_FIELDS)`` per tablet (a few hundred bytes
    each: fine up to ~10^5 records) and reloads it when the catalogue's signature
    ``(count, max id, max updated_at)`` changes; every write of a tablet moves at least one
    of the three (``updated_at`` is set on every update, bulk ones included). The signature
    is checked at most every ``CHECK_INTERVAL_S``; writes through this process's sessions
    invalidate at once (:func:`invalidate_on_tablet_writes`). Totals and
    facets computed from a snapshot are memoised with it (``MEMO_SIZE`` most recent
    queries): exact, since the memo is dropped with the snapshot. Thread-safe.

    Whole rendered search pages are cached the same way (:meth:`cached_page`): keyed by the
    snapshot's version, the viewer's visibility scope and the normalised request, at most
    ``PAGE_CACHE_BYTES`` / ``PAGE_CACHE_SIZE`` (least recently used dropped), and dropped with
    the snapshot. A page is rendered only from tablet columns plus the institution's name;
    institutions are never renamed (the API only creates them), so the tablet signature
    covers everything a page shows.
    """

    MEMO_SIZE = 512
    PAGE_CACHE_SIZE = 1024
    PAGE_CACHE_BYTES = 32 * 1024 * 1024
    CHECK_INTERVAL_S = 1.0  # how stale counts may be after another process's write

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._signature: tuple | None = None
        self._rows: list[tuple] = []
        self._memo: OrderedDict = OrderedDict()
        self._pages: OrderedDict = OrderedDict()
        self._pages_bytes = 0
        # Bumped by every invalidation: a page computed while a write of this process
        # committed is not stored (its version no longer matches).
        self._generation = 0
        self._checked_at = float("-inf")

    def invalidate(self) -> None:
        """Forget the snapshot: the next search reloads it (called after tablet writes)."""
        with self._lock:
            self._checked_at = float("-inf")
            self._signature = None
            self._generation += 1
            self._clear_pages()

    def _clear_pages(self) -> None:
        self._pages.clear()
        self._pages_bytes = 0

    def refresh(self, session: Session) -> None:
        now = time.monotonic()
        with self._lock:
            if self._signature is not None:
                if now - self._checked_at < self.CHECK_INTERVAL_S:
                    return
                # One request checks; the others meanwhile use the snapshot they may use
                # anyway (CHECK_INTERVAL_S stale) instead of all running the same query.
                self._checked_at = now
        signature = tuple(
            session.execute(
                select(func.count(Tablet.id), func.max(Tablet.id), func.max(Tablet.updated_at))
            ).one()
        )
        with self._lock:
            self._checked_at = now
            if signature != self._signature:
                columns = [Tablet.id, Tablet.is_public, Tablet.institution_id]
                columns += [getattr(Tablet, name) for name in FACET_FIELDS]
                self._rows = [tuple(row) for row in session.execute(select(*columns))]
                self._signature = signature
                self._memo.clear()
                self._clear_pages()

    def rows(self, session: Session) -> tuple[tuple | None, list[tuple]]:
        """(signature, rows) of the current snapshot; the signature tags memo keys."""
        self.refresh(session)
        with self._lock:
            return self._signature, self._rows

    def memo_get(self, key):
        with self._lock:
            value = self._memo.get(key)
            if value is not None:
                self._memo.move_to_end(key)
            return value

    def memo_put(self, key, value) -> None:
        with self._lock:
            self._memo[key] = value
            while len(self._memo) > self.MEMO_SIZE:
                self._memo.popitem(last=False)

    def peek_page(self, user: User | None, key: tuple) -> bytes | None:
        """The cached page of :meth:`cached_page`, when the snapshot needs no check now.

        No database access: an async route can call it without leaving the event loop.
        """
        now = time.monotonic()
        with self._lock:
            if self._signature is None or now - self._checked_at >= self.CHECK_INTERVAL_S:
                return None
            full_key = ((self._generation, self._signature), _visibility_key(user), key)
            body = self._pages.get(full_key)
            if body is not None:
                self._pages.move_to_end(full_key)
            return body

    def cached_page(self, session: Session, user: User | None, key: tuple, render) -> bytes:
        """The bytes ``render()`` gives for request ``key`` as seen by ``user``, cached.

        ``key`` must determine the page completely for a given viewer scope and catalogue
        (normalised query, facet limit, URL prefix: see :func:`page_key`); the viewer's
        visibility scope and the snapshot version are added here, so a page is never served
        to a scope other than the one it was rendered for, nor after a catalogue change.
        """
        self.refresh(session)
        with self._lock:
            version = (self._generation, self._signature)
            full_key = (version, _visibility_key(user), key)
            body = self._pages.get(full_key)
            if body is not None:
                self._pages.move_to_end(full_key)
                return body
        body = render()
        with self._lock:
            if (self._generation, self._signature) == version and full_key not in self._pages:
                self._pages[full_key] = body
                self._pages_bytes += len(body)
                while self._pages and (
                    len(self._pages) > self.PAGE_CACHE_SIZE
                    or self._pages_bytes > self.PAGE_CACHE_BYTES
                ):
                    _, dropped = self._pages.popitem(last=False)
                    self._pages_bytes -= len(dropped)
        return body


def page_key(query: SearchQuery, *extra) -> tuple:
    """A hashable key equal for requests giving the same results (any viewer).

    Text is reduced to its tokens (the only part of ``q`` the search uses); filter values
    are alternatives, so their order and repeats do not matter. ``extra``: whatever else
    shapes the rendered page (facet limit, URL prefix).
    """
    filters = tuple(
        sorted(
            (name, tuple(sorted(set(values)))) for name, values in query.filters.items() if values
        )
    )
    return (
        tuple(query_tokens(query.q)),
        filters,
        query.has_3d,
        query.sort,
        query.page,
        query.page_size,
        *extra,
    )


def _visibility_key(user: User | None) -> tuple:
    if user is not None and user.role == Role.admin:
        return ("admin",)
    if user is not None and user.role == Role.staff and user.institution_id is not None:
        return ("staff", user.institution_id)
    return ("public",)


def _visible_in_python(user: User | None):
    """The rule of crud.visible_clause on (id, is_public, institution_id, ...) tuples."""
    if user is not None and user.role == Role.admin:
        return lambda row: True
    if user is not None and user.role == Role.staff and user.institution_id is not None:
        home = user.institution_id
        return lambda row: row[1] or row[2] == home
    return lambda row: row[1]


def _text_ids(session: Session, text: _TextMatch) -> set[int]:
    return set(session.scalars(text.apply(select(Tablet.id))))


def search_tablets(
    session: Session,
    query: SearchQuery,
    *,
    user: User | None,
    facet_limit: int = 50,
    with_facets: bool = True,
    paged: bool = True,
    snapshot: FacetSnapshot | None = None,
) -> SearchResult:
    """Records matching ``query`` that ``user`` may see: one page (or all), total, facets.

    The page is one statement. The total and the facets come from one pass over the facet
    columns of the visible text matches (see :func:`_facet_counts`): read from the database,
    or from ``snapshot`` (the API keeps one per process) plus the ids the text matches.
    """
    dialect = session.get_bind().dialect.name
    tokens = query_tokens(query.q)
    text = _TextMatch(dialect, tokens) if tokens else None
    conditions = _conditions(session, query, user)

    order, ranked = _order(query, text)
    stmt = _filtered(select(Tablet), conditions, text, ranked=ranked).order_by(*order)
    if paged:
        stmt = stmt.limit(query.page_size).offset((query.page - 1) * query.page_size)
    items = list(session.scalars(stmt).unique())
    if not with_facets:
        total = len(items) if not paged else _count(session, conditions, text)
        return SearchResult(items=items, total=total, facets={})
    if snapshot is not None:
        signature, rows = snapshot.rows(session)
        key = (
            signature,
            _visibility_key(user),
            tuple(tokens),
            tuple(sorted((k, tuple(sorted(v))) for k, v in query.filters.items() if v)),
            query.has_3d,
            facet_limit,
        )
        memo = snapshot.memo_get(key)
        if memo is None:
            visible = _visible_in_python(user)
            ids = _text_ids(session, text) if text is not None else None
            rows = [r[3:] for r in rows if visible(r) and (ids is None or r[0] in ids)]
            memo = _facet_counts(rows, query, facet_limit)
            snapshot.memo_put(key, memo)
        total, facets = memo
        return SearchResult(items=items, total=total, facets=facets)
    else:
        columns = [getattr(Tablet, name) for name in FACET_FIELDS]
        stmt = _filtered(select(*columns), {"": conditions[""]}, text)
        rows = [tuple(row) for row in session.execute(stmt)]
    total, facets = _facet_counts(rows, query, facet_limit)
    return SearchResult(items=items, total=total, facets=facets)


def _count(session: Session, conditions, text) -> int:
    stmt = _filtered(select(func.count(Tablet.id)).select_from(Tablet), conditions, text)
    return int(session.scalar(stmt) or 0)


def invalidate_on_tablet_writes(factory, snapshot: FacetSnapshot) -> None:
    """Make sessions of ``factory`` invalidate ``snapshot`` when they commit tablet changes."""

    @event.listens_for(factory, "after_flush")
    def _note_tablet_changes(session, _flush_context):
        if any(isinstance(obj, Tablet) for obj in (*session.new, *session.dirty, *session.deleted)):
            session.info["tablets_changed"] = True

    @event.listens_for(factory, "do_orm_execute")
    def _note_bulk_writes(state):
        if (state.is_insert or state.is_update or state.is_delete) and any(
            mapper.class_ is Tablet for mapper in state.all_mappers
        ):
            state.session.info["tablets_changed"] = True

    @event.listens_for(factory, "after_commit")
    def _invalidate(session):
        if session.info.pop("tablets_changed", False):
            snapshot.invalidate()
