"""Scans of a tablet: listing, reading, with their latest job and model versions."""

from __future__ import annotations

import pytest
import test_jobs as job_helpers  # sibling helpers (tests/backend is on pythonpath)

from backend import jobs
from backend.storage import LocalStorage

API = "/api/v1"


@pytest.fixture
def db_url(sqlite_url) -> str:
    return sqlite_url


def test_scan_lists_latest_job_and_models(client, world, app, tmp_path):
    store = LocalStorage(app.state.settings.resolved_storage_dir)
    app.state.storage = store
    job_id = job_helpers.new_job(world, tablet_id=world.private_a, face="reverse", uid="rig-9")
    with world.session() as session:
        jobs.mark_running(session, job_id=job_id)
        jobs.mark_failed(session, job_id=job_id, error="dark frame missing")
        jobs.retry(session, job_id=job_id)
        jobs.mark_running(session, job_id=job_id)
        model = jobs.mark_succeeded(
            session, job_id=job_id, model_dir=job_helpers.model_dir(tmp_path), storage=store
        )
    headers = world.headers("staff_own")
    (scan,) = client.get(f"{API}/tablets/{world.private_a}/scans", headers=headers).json()
    assert scan["face"] == "reverse" and scan["scan_uid"] == "rig-9"
    assert scan["latest_job"]["state"] == "succeeded" and scan["latest_job"]["attempts"] == 2
    assert [m["id"] for m in scan["models"]] == [model.id]
    assert scan["models"][0]["assets"]["model.glb"].endswith(f"/models/{model.id}/assets/model.glb")
    assert client.get(f"{API}/scans/{scan['id']}", headers=headers).json() == scan
    # The same through the P-number URL.
    assert client.get(f"{API}/tablets/P000002/scans", headers=headers).json() == [scan]


def test_scan_visibility(client, world):
    job_id = job_helpers.new_job(world, tablet_id=world.private_b)
    with world.session() as session:
        from backend.tables import Job

        scan_id = session.get(Job, job_id).scan_id
    for role, status in [("anonymous", 404), ("staff_other", 200), ("staff_own", 404)]:
        # staff_other is staff of B here: the owner of private_b.
        response = client.get(f"{API}/scans/{scan_id}", headers=world.headers(role))
        assert response.status_code == status, role
    assert client.get(f"{API}/scans/999999", headers=world.headers("admin")).status_code == 404
    public = client.get(f"{API}/tablets/{world.public_a}/scans")
    assert public.status_code == 200 and public.json() == []
