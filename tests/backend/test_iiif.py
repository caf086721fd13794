"""IIIF Presentation 3.0 manifests: required structure, and every id dereferences in the app."""

from __future__ import annotations

import os
from urllib.parse import urlsplit

import pytest
import test_jobs as job_helpers  # sibling helpers (tests/backend is on pythonpath)

from backend import jobs
from backend.iiif import CONTEXT, FaceModel, build_manifest, find_by_id, metadata_entries
from backend.storage import LocalStorage
from backend.tables import Tablet

API = "/api/v1"


@pytest.fixture
def db_url(sqlite_url) -> str:
    return sqlite_url


@pytest.fixture
def store(app) -> LocalStorage:
    app.state.storage = LocalStorage(app.state.settings.resolved_storage_dir)
    return app.state.storage


def finish(world, store, tmp_path, job_id: int) -> int:
    directory = job_helpers.model_dir(tmp_path, name=f"m{os.urandom(4).hex()}")
    (directory / "height.npy").write_bytes(b"\x93NUMPY height")
    with world.session() as session:
        jobs.mark_running(session, job_id=job_id)
        return jobs.mark_succeeded(session, job_id=job_id, model_dir=directory, storage=store).id


@pytest.fixture
def tablet_with_models(world, store, tmp_path):
    """Public tablet A: obverse (two versions), reverse, and a whole-tablet model."""
    with world.session() as session:
        tablet = session.get(Tablet, world.public_a)
        tablet.period = "Old Babylonian (ca. 1900-1600 BC)"
        tablet.provenience = "Sippar"
        tablet.owner = "Museum A"
        tablet.height_mm = 61.5
        tablet.extra = {"rights": "http://creativecommons.org/licenses/by/4.0/"}
    ids = {}
    for face in ("obverse", "obverse", "reverse"):
        ids[face] = finish(
            world, store, tmp_path, job_helpers.new_job(world, tablet_id=world.public_a, face=face)
        )
    with world.session() as session:
        whole_job = jobs.create(session, tablet_id=world.public_a, kind="register").id
    ids["tablet"] = finish(world, store, tmp_path, whole_job)
    return ids


def get_json(client, url: str, **kwargs):
    response = client.get(urlsplit(url).path, **kwargs)
    assert response.status_code == 200, (url, response.text)
    return response.json()


def test_manifest_structure(client, world, tablet_with_models):
    response = client.get(f"{API}/tablets/{world.public_a}/iiif/manifest.json")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("application/ld+json")
    manifest = response.json()
    assert manifest["@context"] == CONTEXT
    assert manifest["type"] == "Manifest"
    assert manifest["id"].endswith(f"{API}/tablets/{world.public_a}/iiif/manifest.json")
    assert manifest["label"] == {"none": ["Public A"]}
    assert manifest["rights"] == "http://creativecommons.org/licenses/by/4.0/"
    assert manifest["requiredStatement"]["value"] == {"en": ["Courtesy of Museum A"]}
    labels = {m["label"]["en"][0]: m["value"]["none"][0] for m in manifest["metadata"]}
    assert labels["Period"].startswith("Old Babylonian") and labels["Provenience"] == "Sippar"
    assert labels["CDLI number"] == "P000001" and labels["Dimensions"] == "height 61.5 mm"

    scenes = manifest["items"]
    assert [s["label"]["en"][0] for s in scenes] == ["whole tablet", "obverse", "reverse"]
    for scene in scenes:
        assert scene["type"] == "Scene"
        (page,) = scene["items"]
        assert page["type"] == "AnnotationPage"
        (annotation,) = page["items"]
        assert annotation["type"] == "Annotation" and annotation["motivation"] == "painting"
        assert annotation["target"] == scene["id"]
        body = annotation["body"]
        assert body["type"] == "Model" and body["format"] == "model/gltf-binary"
        formats = {r["format"]: r["type"] for r in scene["rendering"]}
        assert formats["application/ply"] == "Model"
        assert formats["application/octet-stream"] == "Dataset"  # the height map
        assert scene["thumbnail"][0]["format"] == "image/png"
    obverse = scenes[1]["items"][0]["items"][0]["body"]
    newest = tablet_with_models["obverse"]
    assert obverse["id"].endswith(f"/models/{newest}/assets/model.glb")  # newest version shown
    assert "version 2" in obverse["label"]["en"][0]
    assert manifest["thumbnail"][0]["type"] == "Image"


def test_every_id_dereferences(client, world, tablet_with_models):
    manifest = get_json(client, f"{API}/tablets/{world.public_a}/iiif/manifest.json")
    ids = []

    def collect(node):
        if isinstance(node, dict):
            if "id" in node and "type" in node:
                ids.append(node)
            for value in node.values():
                collect(value)
        elif isinstance(node, list):
            for value in node:
                collect(value)

    collect(manifest)
    assert len(ids) > 20
    for node in ids:
        response = client.get(urlsplit(node["id"]).path)
        assert response.status_code == 200, node["id"]
        if node["type"] in ("Scene", "AnnotationPage", "Annotation"):
            assert response.json()["id"] == node["id"] and response.json()["type"] == node["type"]
        elif "format" in node:
            assert response.headers["content-type"].split(";")[0] == node["format"]


def test_p_number_url_and_private_tablets(client, world, store, tmp_path, tablet_with_models):
    by_p = get_json(client, f"{API}/tablets/P000001/iiif/manifest.json")
    assert by_p["id"].endswith(f"/tablets/{world.public_a}/iiif/manifest.json")
    finish(world, store, tmp_path, job_helpers.new_job(world, tablet_id=world.private_a))
    url = f"{API}/tablets/{world.private_a}/iiif/manifest.json"
    assert client.get(url).status_code == 404
    assert client.get(url, headers=world.headers("staff_other")).status_code == 404
    assert client.get(url, headers=world.headers("staff_own")).status_code == 200
    assert "rights" not in client.get(url, headers=world.headers("admin")).json()


def test_no_model_yet_is_404(client, world):
    response = client.get(
        f"{API}/tablets/{world.private_b}/iiif/manifest.json", headers=world.headers("admin")
    )
    assert response.status_code == 404 and response.json()["where"] == "tablet_id"


def test_build_manifest_rules():
    face = FaceModel(face="top", model_id=1, version=3, asset_urls={"model.glb": "http://x/m.glb"})
    manifest = build_manifest(
        manifest_id="http://x/api/v1/tablets/1/iiif/manifest.json",
        fields={"designation": "T", "extra": {"rights": "All rights reserved"}},
        face_models=[face],
    )
    assert "rights" not in manifest and "requiredStatement" not in manifest  # not a rights URI
    assert "rendering" not in manifest["items"][0] and "thumbnail" not in manifest
    assert find_by_id(manifest, "http://x/api/v1/tablets/1/iiif/scene/top")["type"] == "Scene"
    assert find_by_id(manifest, "http://nowhere") is None
    with pytest.raises(ValueError, match="face_models"):
        build_manifest(manifest_id="http://x/m.json", fields={}, face_models=[])
    assert metadata_entries({"designation": "", "period": None, "width_mm": 20.0}) == [
        {"label": {"en": ["Dimensions"]}, "value": {"none": ["width 20 mm"]}}
    ]


def test_ids_come_from_the_public_url_not_the_host_header(
    sqlite_url, tmp_path, password_hash, monkeypatch
):
    """A forged Host header must not end up in ids that harvesters store and follow."""
    from fastapi.testclient import TestClient

    from backend.main import create_app
    from tests.backend.conftest import build_world, make_settings

    settings = make_settings(sqlite_url, tmp_path, public_url="https://library.example.org/dh/")
    app = create_app(settings)
    app.state.storage = LocalStorage(settings.resolved_storage_dir)
    world = build_world(app.state.sessionmaker, password_hash, settings)
    finish(world, app.state.storage, tmp_path, job_helpers.new_job(world, tablet_id=world.public_a))
    with TestClient(app, base_url="http://evil.example") as client:
        url = f"{API}/tablets/{world.public_a}/iiif/manifest.json"
        manifest = client.get(url, headers={"Host": "evil.example"}).json()
    app.state.engine.dispose()
    base = "https://library.example.org/dh"
    assert manifest["id"] == f"{base}{API}/tablets/{world.public_a}/iiif/manifest.json"
    text = str(manifest)
    assert "evil.example" not in text and "testserver" not in text
    ids = [node["id"] for node in _walk(manifest) if isinstance(node.get("id"), str)]
    assert ids and all(i.startswith(base) or i.startswith("http://iiif.io") for i in ids), ids


def _walk(node):
    if isinstance(node, dict):
        yield node
        for value in node.values():
            yield from _walk(value)
    elif isinstance(node, list):
        for value in node:
            yield from _walk(value)
