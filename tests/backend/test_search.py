"""Search: text prefixes, filters, facets (other filters in force), sort, paging, formats."""

from __future__ import annotations

import csv
import io
import json

import pytest

from backend.db import make_engine, make_sessionmaker, session_scope
from backend.search import FacetSnapshot, SearchQuery, page_key, search_tablets
from backend.tables import Tablet, User

RECORDS = [
    # designation, museum_no, period, genre, language, public, has_3d, publication, notes
    ("VAT 15259", "VAT 15259", "Uruk IV", "mathematical", None, True, True, "ATU 5, pl. 057", None),
    ("VAT 15171", "VAT 15171", "Uruk IV", "mathematical", None, True, False, "ATU 5", None),
    ("BM 80150", "BM 80150", "Old Babylonian", "literary", "Sumerian", True, False, "CT 42", None),
    ("BM 85194", "BM 85194", "Old Babylonian", "mathematical", "Akkadian", True, True, None,
     "squares and circles"),
    ("YBC 7289", "YBC 7289", "Old Babylonian", "mathematical", "Akkadian", True, False,
     "MCT 42", "square root of two"),
    ("K 3375", "K 3375", "Neo-Assyrian", "literary", "Akkadian", True, False, "CT 13", None),
    ("Secret A", "X 1", "Old Babylonian", "literary", "Sumerian", False, False, None, "square"),
]  # fmt: skip


@pytest.fixture
def catalogue(world):
    ids = {}
    with world.session() as session:
        for i, (des, mus, per, gen, lang, public, has_3d, pub, notes) in enumerate(RECORDS):
            tablet = Tablet(
                designation=des,
                p_number=f"P1000{i:02d}",
                museum_no=mus,
                period=per,
                genre=gen,
                language=lang,
                is_public=public,
                has_3d=has_3d,
                primary_publication=pub,
                notes=notes,
                institution_id=world.institution_a,
                extra={},
            )
            session.add(tablet)
            session.flush()
            ids[des] = tablet.id
    return ids


def _designations(response) -> list[str]:
    assert response.status_code == 200, response.text
    return [item["designation"] for item in response.json()["items"]]


def test_text_prefixes_across_fields(client, catalogue):
    assert _designations(client.get("/api/v1/tablets", params={"q": "vat 152"})) == ["VAT 15259"]
    # publication, notes, P-number
    assert set(_designations(client.get("/api/v1/tablets", params={"q": "ct"}))) == {
        "BM 80150",
        "K 3375",
    }
    assert _designations(client.get("/api/v1/tablets", params={"q": "root two"})) == ["YBC 7289"]
    assert _designations(client.get("/api/v1/tablets", params={"q": "P100005"})) == ["K 3375"]
    assert _designations(client.get("/api/v1/tablets", params={"q": "nothing-like-this"})) == []


def test_private_records_only_for_their_institution(client, world, catalogue):
    anonymous = _designations(client.get("/api/v1/tablets", params={"q": "square"}))
    own = _designations(
        client.get("/api/v1/tablets", params={"q": "square"}, headers=world.headers("staff_own"))
    )
    other = _designations(
        client.get("/api/v1/tablets", params={"q": "square"}, headers=world.headers("staff_other"))
    )
    assert sorted(anonymous) == ["BM 85194", "YBC 7289"]
    assert sorted(own) == ["BM 85194", "Secret A", "YBC 7289"]
    assert sorted(other) == sorted(anonymous)


def test_filters_and_facets(client, catalogue):
    response = client.get(
        "/api/v1/tablets",
        params=[("period", "Old Babylonian"), ("period", "Uruk IV"), ("genre", "mathematical")],
    )
    body = response.json()
    assert sorted(_designations(response)) == ["BM 85194", "VAT 15171", "VAT 15259", "YBC 7289"]
    assert body["total"] == 4
    facets = {
        name: {f["value"]: f["count"] for f in values} for name, values in body["facets"].items()
    }
    # a facet counts with every filter but its own: periods of the mathematical tablets...
    assert facets["period"] == {"Old Babylonian": 2, "Uruk IV": 2}
    # ...and genres of the tablets of the two chosen periods (public ones: 5)
    assert facets["genre"] == {"mathematical": 4, "literary": 1}
    assert facets["has_3d"] == {True: 2, False: 2}
    assert facets["language"] == {"Akkadian": 2, None: 2}
    response = client.get("/api/v1/tablets", params={"has_3d": "true", "language": "Akkadian"})
    assert _designations(response) == ["BM 85194"]


def test_sort_and_paging(client, catalogue):
    pages = [
        client.get("/api/v1/tablets", params={"sort": "-designation", "page": p, "page_size": 4})
        for p in (1, 2)
    ]
    names = _designations(pages[0]) + _designations(pages[1])
    # the world's own public record ("Public A") is in the library too
    public = sorted([*(r[0] for r in RECORDS if r[5]), "Public A"], reverse=True)
    assert names == public
    assert pages[1].json()["total"] == len(public) and pages[1].json()["page"] == 2
    first = _designations(client.get("/api/v1/tablets", params={"q": "vat", "sort": "relevance"}))
    assert sorted(first) == ["VAT 15171", "VAT 15259"]


def test_csv_and_jsonl_export_every_match(client, catalogue):
    response = client.get("/api/v1/tablets", params={"genre": "literary", "format": "csv"})
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(response.text)))
    assert sorted(r["designation"] for r in rows) == ["BM 80150", "K 3375"]
    # absolute, from the configured public URL: a spreadsheet has no base to resolve against
    base = client.app.state.settings.resolved_public_url
    assert rows[0]["url"].startswith(f"{base}/api/v1/tablets/")

    response = client.get(
        "/api/v1/tablets", params={"genre": "literary"}, headers={"Accept": "application/x-ndjson"}
    )
    assert response.headers["content-type"].startswith("application/x-ndjson")
    lines = [json.loads(line) for line in response.text.splitlines()]
    assert sorted(line["designation"] for line in lines) == ["BM 80150", "K 3375"]
    assert response.headers["x-total-count"] == "2"


@pytest.mark.parametrize(
    ("params", "where"),
    [
        ({"page_size": 100000}, "query.page_size"),
        ({"sort": "colour"}, "query.sort"),
        ({"page": 0}, "query.page"),
        ({"has_3d": "maybe"}, "query.has_3d"),
        ({"format": "xml"}, "query.format"),
    ],
)
def test_bad_parameters_name_the_culprit(client, params, where):
    response = client.get("/api/v1/tablets", params=params)
    assert response.status_code == 422
    assert response.json()["where"] == where


def test_snapshot_agrees_with_the_database_and_follows_changes(client, world, catalogue):
    queries = [
        SearchQuery(),
        SearchQuery(q="square"),
        SearchQuery(filters={"period": ("Old Babylonian",)}, has_3d=False),
        SearchQuery(q="bm", filters={"genre": ("literary", "mathematical")}),
    ]
    snapshot = FacetSnapshot()
    with world.session() as session:
        for role in ("anonymous", "reader", "staff_own", "staff_other", "admin"):
            user = None if role == "anonymous" else session.get(User, world.users[role])
            for query in queries:
                cached = search_tablets(session, query, user=user, snapshot=snapshot)
                direct = search_tablets(session, query, user=user)
                assert (cached.total, cached.facets) == (direct.total, direct.facets), (role, query)
    # the API's snapshot follows an edit made through the API
    before = client.get("/api/v1/tablets").json()["facets"]["period"]
    assert {"value": "Uruk III", "count": 1} not in before
    response = client.patch(
        f"/api/v1/tablets/{catalogue['K 3375']}",
        json={"period": "Uruk III"},
        headers=world.headers("staff_own"),
    )
    assert response.status_code == 200
    after = client.get("/api/v1/tablets").json()["facets"]["period"]
    assert {"value": "Uruk III", "count": 1} in after


def test_snapshot_sees_other_processes_writes_after_the_check_interval(
    client, app, world, catalogue, monkeypatch
):
    def periods():
        facets = client.get("/api/v1/tablets").json()["facets"]["period"]
        return {f["value"]: f["count"] for f in facets}

    assert periods()["Neo-Assyrian"] == 1
    # another process: an engine and sessions the app's snapshot knows nothing of
    engine = make_engine(app.state.settings.resolved_database_url)
    with session_scope(make_sessionmaker(engine)) as session:
        session.get(Tablet, catalogue["BM 80150"]).period = "Neo-Assyrian"
    engine.dispose()
    monkeypatch.setattr(FacetSnapshot, "CHECK_INTERVAL_S", 0.0)
    assert periods()["Neo-Assyrian"] == 2


def test_cached_pages_never_cross_visibility_scopes(client, world, catalogue):
    params = {"q": "square"}

    def seen(role):
        response = client.get("/api/v1/tablets", params=params, headers=world.headers(role))
        return sorted(_designations(response)), response.json()["total"]

    public = (["BM 85194", "YBC 7289"], 2)
    with_secret = (["BM 85194", "Secret A", "YBC 7289"], 3)
    # privileged scopes fill the cache first: the others must still get their own pages
    assert seen("staff_own") == with_secret
    assert seen("admin") == with_secret
    for role in ("anonymous", "reader", "staff_other"):
        assert seen(role) == public, role
    # and the other way round: a public page cached first is not what staff see
    params = {"q": "square", "page_size": 10}
    assert seen("anonymous") == public
    assert seen("staff_own") == with_secret
    assert seen("staff_other") == public


def test_a_write_is_visible_in_the_next_search(client, world, catalogue):
    params = {"genre": "literary"}
    assert sorted(_designations(client.get("/api/v1/tablets", params=params))) == [
        "BM 80150",
        "K 3375",
    ]
    headers = world.headers("staff_own")
    response = client.patch(
        f"/api/v1/tablets/{catalogue['K 3375']}", json={"designation": "K 3375a"}, headers=headers
    )
    assert response.status_code == 200
    assert sorted(_designations(client.get("/api/v1/tablets", params=params))) == [
        "BM 80150",
        "K 3375a",
    ]
    response = client.post(
        "/api/v1/tablets",
        json={"designation": "New 1", "genre": "literary", "is_public": True},
        headers=headers,
    )
    assert response.status_code == 201, response.text
    page = client.get("/api/v1/tablets", params=params).json()
    assert sorted(item["designation"] for item in page["items"]) == ["BM 80150", "K 3375a", "New 1"]
    assert page["total"] == 3
    response = client.delete(f"/api/v1/tablets/{catalogue['BM 80150']}", headers=headers)
    assert response.status_code == 204
    assert sorted(_designations(client.get("/api/v1/tablets", params=params))) == [
        "K 3375a",
        "New 1",
    ]


def test_equivalent_requests_share_one_cached_page(client, app, catalogue):
    snapshot = app.state.facet_snapshot
    first = client.get(
        "/api/v1/tablets",
        params=[("q", "VAT"), ("period", "Uruk IV"), ("period", "Old Babylonian")],
    )
    # other case, other value order, a repeated value: the same results, the same page
    second = client.get(
        "/api/v1/tablets",
        params=[("q", "vat"), ("period", "Old Babylonian"), ("period", "Uruk IV"), ("period", "Uruk IV")],
    )  # fmt: skip
    assert first.content == second.content
    assert len(snapshot._pages) == 1
    assert page_key(SearchQuery(q="a b")) != page_key(SearchQuery(q="a"))
    assert page_key(SearchQuery(page=1)) != page_key(SearchQuery(page=2))
    assert page_key(SearchQuery(sort="id")) != page_key(SearchQuery(sort="-id"))


def test_a_page_rendered_across_a_write_is_not_cached(world, catalogue):
    snapshot = FacetSnapshot()
    renders = []

    def render_with_a_write_meanwhile():
        renders.append(1)
        snapshot.invalidate()  # as a commit of this process would
        snapshot.refresh(session)  # and another request reloads the snapshot at once
        return b"stale"

    def render():
        renders.append(1)
        return b"fresh"

    with world.session() as session:
        key = page_key(SearchQuery())
        assert snapshot.cached_page(session, None, key, render_with_a_write_meanwhile) == b"stale"
        assert snapshot.cached_page(session, None, key, render) == b"fresh"
        assert snapshot.cached_page(session, None, key, render) == b"fresh"
    assert len(renders) == 2


def test_page_cache_is_bounded(world, catalogue, monkeypatch):
    monkeypatch.setattr(FacetSnapshot, "PAGE_CACHE_SIZE", 3)
    monkeypatch.setattr(FacetSnapshot, "PAGE_CACHE_BYTES", 10)
    snapshot = FacetSnapshot()
    with world.session() as session:
        for page in range(1, 6):
            snapshot.cached_page(session, None, page_key(SearchQuery(page=page)), lambda: b"1234")
        # 4 bytes each: two fit in 10 bytes, the most recent ones
        assert len(snapshot._pages) == 2 and snapshot._pages_bytes == 8
        assert [k[-1][4] for k in snapshot._pages] == [4, 5]


def test_csv_export_escapes_formulas_but_not_numbers_or_jsonl(client, world):
    """OWASP's CSV-injection rule: text cells that a spreadsheet would run get a leading
    ``'``; numeric columns (a negative size) stay numbers; JSON lines keep the stored text."""
    evil = '=HYPERLINK("http://evil.example","click")'
    text_cells = {
        "designation": evil,
        "museum_no": "+1+1",
        "collection": "-2+3",
        "owner": "@SUM(A1)",
        "notes": "\t=1",
        "primary_publication": "\r=1",
        "period": "Old Babylonian",  # an ordinary value stays as it is
    }
    tablet_id = world.new_tablet(is_public=True, height_mm=-1.5, width_mm=42.0, **text_cells)
    response = client.get("/api/v1/tablets", params={"format": "csv"})
    assert response.status_code == 200
    rows = {int(r["id"]): r for r in csv.DictReader(io.StringIO(response.text, newline=""))}
    row = rows[tablet_id]
    for name, value in text_cells.items():
        expected = value if name == "period" else "'" + value
        assert row[name] == expected, name
    assert row["height_mm"] == "-1.5" and row["width_mm"] == "42.0"

    response = client.get("/api/v1/tablets", params={"format": "jsonl"})
    lines = {line["id"]: line for line in map(json.loads, response.text.splitlines())}
    assert lines[tablet_id]["designation"] == evil
    assert lines[tablet_id]["height_mm"] == -1.5
