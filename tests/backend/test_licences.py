"""Licences and attribution: set per tablet or as an institution default, carried by the
manifest and the exports."""

from __future__ import annotations

import csv
import io
import json

import pytest
import test_jobs as job_helpers
from test_iiif import finish

from backend.storage import LocalStorage

API = "/api/v1"
CC_BY = "https://creativecommons.org/licenses/by/4.0/"
CC0 = "https://creativecommons.org/publicdomain/zero/1.0/"


@pytest.fixture
def db_url(sqlite_url) -> str:
    return sqlite_url


@pytest.fixture
def store(app) -> LocalStorage:
    app.state.storage = LocalStorage(app.state.settings.resolved_storage_dir)
    return app.state.storage


def test_a_licence_must_be_a_rights_uri(client, world):
    url = f"{API}/tablets/{world.public_a}"
    refused = client.patch(
        url, json={"licence": "All rights reserved"}, headers=world.headers("admin")
    )
    assert refused.status_code == 422
    body = refused.json()
    assert body["where"] == "body.licence" and "Creative Commons" in body["detail"]
    ok = client.patch(url, json={"licence": CC0}, headers=world.headers("staff_own"))
    assert ok.status_code == 200 and ok.json()["licence"] == CC0
    assert ok.json()["effective_licence"] == CC0


def test_the_institution_default_applies_until_a_record_sets_its_own(client, world):
    inst = f"{API}/institutions/{world.institution_a}"
    body = {"licence": CC_BY, "attribution": "Courtesy of the Trustees of Museum A"}
    assert client.patch(inst, json=body, headers=world.headers("staff_other")).status_code == 403
    assert client.patch(inst, json=body, headers=world.headers("reader")).status_code == 403
    changed = client.patch(inst, json=body, headers=world.headers("staff_own"))
    assert changed.status_code == 200 and changed.json()["licence"] == CC_BY
    assert (
        client.patch(inst, json={"licence": "mine"}, headers=world.headers("admin")).status_code
        == 422
    )

    record = client.get(f"{API}/tablets/{world.public_a}").json()
    assert record["licence"] is None and record["effective_licence"] == CC_BY
    assert record["effective_attribution"] == "Courtesy of the Trustees of Museum A"
    assert record["cdli_url"] == "https://cdli.mpiwg-berlin.mpg.de/artifacts/1"
    own = client.patch(
        f"{API}/tablets/{world.public_a}", json={"licence": CC0}, headers=world.headers("admin")
    ).json()
    assert own["effective_licence"] == CC0


def test_manifest_and_exports_carry_the_licence(client, world, store, tmp_path):
    client.patch(
        f"{API}/institutions/{world.institution_a}",
        json={"licence": CC_BY, "attribution": "Courtesy of Museum A"},
        headers=world.headers("admin"),
    )
    finish(world, store, tmp_path, job_helpers.new_job(world, tablet_id=world.public_a))
    manifest = client.get(f"{API}/tablets/{world.public_a}/iiif/manifest.json").json()
    assert manifest["rights"] == CC_BY
    assert manifest["requiredStatement"]["value"] == {"en": ["Courtesy of Museum A"]}

    base = client.app.state.settings.resolved_public_url
    response = client.get(f"{API}/tablets", params={"q": "Public A", "format": "csv"})
    (row,) = [
        r for r in csv.DictReader(io.StringIO(response.text)) if r["designation"] == "Public A"
    ]
    assert row["url"] == f"{base}{API}/tablets/{world.public_a}"
    assert row["iiif_manifest"] == f"{base}{API}/tablets/{world.public_a}/iiif/manifest.json"
    assert row["cdli_url"] == "https://cdli.mpiwg-berlin.mpg.de/artifacts/1"
    assert (
        row["effective_licence"] == CC_BY and row["effective_attribution"] == "Courtesy of Museum A"
    )

    response = client.get(f"{API}/tablets", params={"q": "Public A", "format": "jsonl"})
    lines = [json.loads(line) for line in response.text.splitlines()]
    (line,) = [x for x in lines if x["designation"] == "Public A"]
    assert line["url"].startswith(base) and line["effective_licence"] == CC_BY
