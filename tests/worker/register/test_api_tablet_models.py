"""GET /api/v1/models?tablet_id=N: the tablet-level models (registration output) of a tablet,
whose fatcross plates are then served by /models/{id}/assets/fatcross/NAME.png."""

from __future__ import annotations

from fastapi.testclient import TestClient

from backend import jobs
from backend.main import create_app
from backend.settings import Settings
from backend.storage import storage_from_settings
from backend.tables import JobKind, JobState, Model, Tablet


def test_tablet_models_are_listed_and_their_plates_served(tmp_path):
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
        storage = storage_from_settings(settings)
        plate = tmp_path / "plate"
        (plate / "fatcross").mkdir(parents=True)
        (plate / "fatcross" / "P1.png").write_bytes(b"\x89PNG fake")
        with app.state.sessionmaker() as session:
            tablet = Tablet(designation="P1", is_public=True)
            session.add(tablet)
            session.flush()
            job = jobs.create(session, tablet_id=tablet.id, kind=JobKind.register)
            job.state = JobState.succeeded
            prefix = f"models/{tablet.id}/tablet/v1"
            stats = storage.put_tree(prefix, plate)
            assets = {
                s.key[len(prefix) + 1 :]: {"size_bytes": s.size_bytes, "sha256": s.etag}
                for s in stats
            }
            session.add(
                Model(
                    scan_id=None,
                    tablet_id=tablet.id,
                    job_id=job.id,
                    version=1,
                    storage_prefix=prefix,
                    assets=assets,
                )
            )
            session.commit()
            tablet_id = tablet.id
        with TestClient(app) as client:
            r = client.get(f"/api/v1/models?tablet_id={tablet_id}")
            assert r.status_code == 200, r.text
            (model,) = r.json()
            assert model["scan_id"] is None
            url = model["assets"]["fatcross/P1.png"]
            got = client.get(url)
            assert got.status_code == 200 and got.content == b"\x89PNG fake"
            assert got.headers["content-type"] == "image/png"
            assert client.get("/api/v1/models?tablet_id=999").status_code == 404
    finally:
        app.state.engine.dispose()
