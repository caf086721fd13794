"""The tablet registration job through worker.tasks.register_tablet (in-process)."""

from __future__ import annotations

import json

import pytest

from backend import jobs
from backend.db import migrate
from backend.settings import Settings
from backend.storage import storage_from_settings
from backend.tables import Job, JobKind, JobState, Model, Scan, Tablet
from worker import celery_app as capp
from worker import tasks

from .synthetic import write_gt_model_dirs


@pytest.fixture
def env(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", _env_file=None, job_stale_after_s=30)
    migrate(settings.resolved_database_url)
    previous = capp.settings
    capp.configure(settings)
    yield settings
    capp.configure(previous)


def _tablet_with_models(settings, model_dirs, *, p_number: str | None = None) -> int:
    storage = storage_from_settings(settings)
    with capp.session_factory()() as session:
        tablet = Tablet(designation="P000001" if p_number is None else "CUSAS 1, 1")
        tablet.p_number = p_number
        session.add(tablet)
        session.flush()
        for i, d in enumerate(model_dirs):
            scan = Scan(
                tablet_id=tablet.id,
                face=d.name,
                bundle_key=f"scans/{i}",
                bundle_sha256="0" * 64,
                size_bytes=1,
            )
            session.add(scan)
            session.flush()
            job = jobs.create(session, scan=scan)
            job.state = JobState.succeeded
            prefix = f"models/{tablet.id}/{d.name}/v1"
            storage.put_tree(prefix, d)
            session.add(
                Model(
                    scan_id=scan.id,
                    tablet_id=tablet.id,
                    job_id=job.id,
                    version=1,
                    storage_prefix=prefix,
                )
            )
        job = jobs.create(session, tablet_id=tablet.id, kind=JobKind.register)
        session.commit()
        return job.id


@pytest.mark.slow
def test_register_job_stores_a_tablet_model_with_plates(env, tmp_path):
    dirs, _ = write_gt_model_dirs(tmp_path / "models", size=(64, 52))
    # The first face model has its photographs and gloss (worker/photos.py); the others none.
    photo = "photos/000-photometric-az045.0.jpg"
    (dirs[0] / "photos").mkdir()
    (dirs[0] / photo).write_bytes(b"\xff\xd8 a photograph")
    index = {"version": 1, "photos": [{"file": photo, "light": [0.5, 0, -0.87]}]}
    (dirs[0] / "photos" / "index.json").write_text(json.dumps(index))
    (dirs[0] / "gloss.png").write_bytes(b"\x89PNG gloss")
    (dirs[0] / "gloss.json").write_text('{"strength_scale": 0.4, "exponent": 32}')
    job_id = _tablet_with_models(env, dirs)
    assert tasks.register_tablet.apply(args=[job_id]).get() == "succeeded"
    with capp.session_factory()() as session:
        job = session.get(Job, job_id)
        model = session.get(Model, job.model_id)
        assert model.scan_id is None and model.tablet_id == job.tablet_id
        for name in (
            "model.glb",
            "tablet.glb",
            "merged.ply",
            "transforms.json",
            "fatcross/P000001_fatcross_natural.png",
            "fatcross/P000001_fatcross.pdf",
        ):
            assert name in model.assets, name
        # Every face keeps its full-resolution normals (with blending weights) for the viewer.
        for d in dirs:
            assert f"faces/sim-0-{d.name}/normals.png" in model.assets, sorted(model.assets)
        assert model.report["pairs"]
        # The face's photographs and gloss come with it, under its folder.
        storage = storage_from_settings(env)
        first = f"faces/sim-0-{dirs[0].name}"
        for name in (photo, "photos/index.json", "gloss.png", "gloss.json"):
            assert f"{first}/{name}" in model.assets, name
            stored = storage.read_bytes(f"{model.storage_prefix}/{first}/{name}")
            assert stored == (dirs[0] / name).read_bytes(), name
        assert not any(f"sim-0-{d.name}/photos" in n for d in dirs[1:] for n in model.assets)
        # The whole tablet streams face by face: a root tileset over the faces' tilesets.
        assert {n for n in model.assets if n.startswith("tiles/")} == {
            "tiles/index.json",
            "tiles/files.json",
        }
        storage = storage_from_settings(env)
        files = json.loads(storage.read_bytes(f"{model.storage_prefix}/tiles/files.json"))
        root = json.loads(storage.read_bytes(f"{model.storage_prefix}/tiles/3d/tileset.json"))
        uris = sorted(c["content"]["uri"] for c in root["root"]["children"])
        assert uris == sorted(f"../faces/sim-0-{d.name}/3d/tileset.json" for d in dirs)
        for uri in uris:
            assert uri.removeprefix("../") in files


@pytest.mark.slow
def test_register_job_names_plates_by_p_number_titled_with_the_designation(env, tmp_path):
    dirs, _ = write_gt_model_dirs(tmp_path / "models", size=(48, 40), faces=["obverse", "top"])
    job_id = _tablet_with_models(env, dirs, p_number="P000002")
    assert tasks.register_tablet.apply(args=[job_id]).get() == "succeeded"
    with capp.session_factory()() as session:
        model = session.get(Model, session.get(Job, job_id).model_id)
        assert "fatcross/P000002_fatcross_natural.png" in model.assets
        assert model.report["fatcross"]["designation"] == "P000002 (CUSAS 1, 1)"


def test_register_job_with_one_model_fails_with_a_message(env, tmp_path):
    dirs, _ = write_gt_model_dirs(tmp_path / "models", size=(48, 40), faces=["obverse"])
    job_id = _tablet_with_models(env, dirs)
    assert tasks.register_tablet.apply(args=[job_id]).get() == "failed"
    with capp.session_factory()() as session:
        job = session.get(Job, job_id)
        assert job.state == JobState.failed and "two or more scans" in job.error


def test_plates_carry_the_tablets_own_licence_never_an_invented_one():
    from types import SimpleNamespace as NS

    from worker.register.job import plate_licence_line

    museum = NS(name="British Museum", licence=None, attribution=None)
    by = "https://creativecommons.org/licenses/by/4.0/"
    own = NS(licence=by, attribution=None, owner="British Museum", institution=museum)
    assert plate_licence_line(own) == f"{by} · Courtesy of British Museum"
    museum_default = NS(
        name="Yale", licence="http://rightsstatements.org/vocab/InC/1.0/", attribution="YBC"
    )
    inherited = NS(licence=None, attribution=None, owner=None, institution=museum_default)
    assert plate_licence_line(inherited) == "http://rightsstatements.org/vocab/InC/1.0/ · YBC"
    unstated = NS(licence=None, attribution=None, owner=None, institution=None)
    assert plate_licence_line(unstated) == "not stated by the holder"
