"""Simulated data says so: scans and models whose scan.tablet free metadata (or registration
report) marks them simulated carry ``simulated: true`` in the API; real ones false."""

from __future__ import annotations

from fastapi.testclient import TestClient

from backend import jobs
from backend.main import create_app
from backend.settings import Settings
from backend.tables import JobKind, JobState, Model, Scan, Tablet
from worker.bundle import is_simulated


def test_is_simulated_reads_the_free_metadata():
    assert is_simulated({"simulated": "true"}) and is_simulated({"simulated": "True"})
    assert is_simulated({"simulator": "worker.simulate"})
    assert not is_simulated({"simulated": "false"}) and not is_simulated({})
    assert not is_simulated(None) and not is_simulated({"designation": "P1"})


def test_scans_and_models_report_whether_they_are_simulated(tmp_path):
    settings = Settings(
        _env_file=None,
        environment="test",
        data_dir=tmp_path / "var",
        database_url=f"sqlite:///{tmp_path / 'db.sqlite'}",
        secret_key="x" * 48,
        storage_dir=tmp_path / "storage",
        frontend_dist=tmp_path / "no-frontend",
    )
    from backend.db import migrate

    migrate(settings.resolved_database_url)
    app = create_app(settings)
    try:
        with app.state.sessionmaker() as session:
            tablet = Tablet(designation="P1", is_public=True)
            session.add(tablet)
            session.flush()
            scans = {}
            for uid, meta in (("sim", {"simulated": "true"}), ("real", {"designation": "P1"})):
                scan = Scan(
                    tablet_id=tablet.id,
                    face="obverse",
                    scan_uid=uid,
                    bundle_key=f"bundles/{uid}.zip",
                    bundle_sha256="0" * 64,
                    size_bytes=1,
                    manifest={"scan": {"id": uid, "face": "obverse", "tablet": meta}},
                )
                session.add(scan)
                session.flush()
                job = jobs.create(session, scan=scan)
                job.state = JobState.succeeded
                session.add(
                    Model(
                        scan_id=scan.id,
                        tablet_id=tablet.id,
                        job_id=job.id,
                        version=1,
                        storage_prefix=f"models/{uid}",
                        assets={},
                        report={"scan": {"id": uid, "tablet": meta}},
                    )
                )
                scans[uid] = scan.id
            job = jobs.create(session, tablet_id=tablet.id, kind=JobKind.register)
            job.state = JobState.succeeded
            session.add(
                Model(
                    scan_id=None,
                    tablet_id=tablet.id,
                    job_id=job.id,
                    version=1,
                    storage_prefix="models/tablet",
                    assets={},
                    report={"simulated": True},
                )
            )
            session.commit()
            tablet_id = tablet.id
        with TestClient(app) as client:
            r = client.get(f"/api/v1/tablets/{tablet_id}/scans")
            assert r.status_code == 200, r.text
            by_uid = {s["scan_uid"]: s for s in r.json()}
            assert by_uid["sim"]["simulated"] is True
            assert by_uid["real"]["simulated"] is False
            assert by_uid["sim"]["models"][0]["simulated"] is True
            assert by_uid["real"]["models"][0]["simulated"] is False
            (whole,) = client.get(f"/api/v1/models?tablet_id={tablet_id}").json()
            assert whole["scan_id"] is None and whole["simulated"] is True
    finally:
        app.state.engine.dispose()
