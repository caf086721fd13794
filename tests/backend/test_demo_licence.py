"""``make demo`` sets its institution's default licence and attribution through the API as
staff (worker/demo.py ``set_institution_licence``): without them its manifests had no
``rights`` and the tablet page said "Licence: none stated". Run against the real app."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from worker.demo import DEMO_ATTRIBUTION, DEMO_LICENCE, set_institution_licence


def _api(app, headers) -> TestClient:
    return TestClient(app, base_url="http://testserver/api/v1", headers=headers)


def test_the_demo_sets_its_institutions_licence_as_staff(app, world):
    record = f"/tablets/{world.public_a}"
    with _api(app, world.headers("staff_own")) as http:
        assert http.get(record).json()["effective_licence"] is None  # the QA finding
        answer = set_institution_licence(
            http, name="Museum A", licence=DEMO_LICENCE, attribution=DEMO_ATTRIBUTION
        )
        assert (answer["licence"], answer["attribution"]) == (DEMO_LICENCE, DEMO_ATTRIBUTION)
    with _api(app, {}) as anonymous:
        shown = anonymous.get(record).json()
    assert shown["effective_licence"] == DEMO_LICENCE
    assert shown["effective_attribution"] == DEMO_ATTRIBUTION


def test_a_missing_institution_or_a_refusal_is_an_error(app, world):
    with _api(app, world.headers("staff_own")) as http, pytest.raises(RuntimeError):
        set_institution_licence(http, name="Nowhere", licence=DEMO_LICENCE, attribution="x")
    # Staff of another institution may not set it: the demo would say so, not go on.
    # (The test client's HTTPStatusError is its own httpx copy's: matched by its message.)
    with _api(app, world.headers("staff_other")) as http, pytest.raises(Exception, match="403"):
        set_institution_licence(http, name="Museum A", licence=DEMO_LICENCE, attribution="x")
