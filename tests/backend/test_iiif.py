"""IIIF manifests: Presentation 3 (validated by iiif-prezi3), the 3-D draft, every id dereferences."""

from __future__ import annotations

import json
import os
from urllib.parse import urlsplit

import pytest
import test_jobs as job_helpers  # sibling helpers (tests/backend is on pythonpath)
from iiif_prezi3 import Manifest as Prezi3Manifest

from backend import jobs
from backend.iiif import (
    CONTEXT,
    CONTEXT_3D,
    FaceModel,
    Provenance,
    build_3d_manifest,
    build_manifest,
    cdli_url,
    find_by_id,
    is_rights_uri,
    metadata_entries,
)
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


def finish(world, store, tmp_path, job_id: int, *, with_images: bool = True) -> int:
    directory = job_helpers.model_dir(tmp_path, name=f"m{os.urandom(4).hex()}")
    (directory / "height.npy").write_bytes(b"\x93NUMPY height")
    if with_images:
        (directory / "albedo.png").write_bytes(b"\x89PNG\r\n\x1a\n albedo")
        (directory / "normals.png").write_bytes(b"\x89PNG\r\n\x1a\n normals")
        report = {"pixel_size_um": 50, "image_size": {"width": 256, "height": 192}}
        (directory / "report.json").write_text(json.dumps(report))
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
        tablet.licence = "https://creativecommons.org/licenses/by/4.0/"
    ids = {}
    for face in ("obverse", "obverse", "reverse"):
        ids[face] = finish(
            world, store, tmp_path, job_helpers.new_job(world, tablet_id=world.public_a, face=face)
        )
    with world.session() as session:
        whole_job = jobs.create(session, tablet_id=world.public_a, kind="register").id
    ids["tablet"] = finish(world, store, tmp_path, whole_job, with_images=False)
    return ids


def get_json(client, url: str, **kwargs):
    response = client.get(urlsplit(url).path, **kwargs)
    assert response.status_code == 200, (url, response.text)
    return response.json()


def _walk(node):
    if isinstance(node, dict):
        yield node
        for value in node.values():
            yield from _walk(value)
    elif isinstance(node, list):
        for value in node:
            yield from _walk(value)


def test_manifest_is_valid_presentation_3(client, world, tablet_with_models):
    response = client.get(f"{API}/tablets/{world.public_a}/iiif/manifest.json")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("application/ld+json")
    manifest = response.json()
    Prezi3Manifest(**manifest)  # raises on any deviation from the Presentation 3 schema
    assert manifest["@context"] == CONTEXT and manifest["type"] == "Manifest"
    assert manifest["id"].endswith(f"{API}/tablets/{world.public_a}/iiif/manifest.json")
    assert manifest["label"] == {"none": ["Public A"]}
    assert "Sippar" in manifest["summary"]["en"][0]
    assert manifest["rights"] == "https://creativecommons.org/licenses/by/4.0/"
    assert manifest["requiredStatement"]["value"] == {"en": ["Courtesy of Museum A"]}
    labels = {m["label"]["en"][0]: m["value"]["none"][0] for m in manifest["metadata"]}
    assert labels["Period"].startswith("Old Babylonian") and labels["Provenience"] == "Sippar"
    assert labels["CDLI number"] == "P000001" and labels["Dimensions"] == "height 61.5 mm"
    see_also = {s["format"]: s["id"] for s in manifest["seeAlso"]}
    assert see_also["application/json"].endswith(f"{API}/tablets/{world.public_a}")
    assert see_also["text/html"] == "https://cdli.mpiwg-berlin.mpg.de/artifacts/1"
    assert see_also["application/ld+json"].endswith("/iiif/3d/manifest.json")
    assert all(node.get("type") != "Scene" for node in _walk(manifest))

    canvases = manifest["items"]
    assert [c["type"] for c in canvases] == ["Canvas", "Canvas"]  # the whole model: 3-D only
    assert [c["label"]["en"][0] for c in canvases] == [
        "obverse, model version 2",
        "reverse, model version 1",
    ]
    newest = tablet_with_models["obverse"]
    obverse = canvases[0]
    assert (obverse["width"], obverse["height"]) == (256, 192)
    assert obverse["service"][0]["physicalScale"] == 0.05
    assert obverse["service"][0]["physicalUnits"] == "mm"
    (page,) = obverse["items"]
    albedo, normal = page["items"]
    for annotation, map_type, name in ((albedo, "albedo", "albedo"), (normal, "normal", "normals")):
        assert annotation["motivation"] == "painting" and annotation["target"] == obverse["id"]
        body = annotation["body"]
        assert body["type"] == "Image" and body["format"] == "image/png"
        assert body["id"].endswith(f"/models/{newest}/assets/{name}.png")
        assert (body["width"], body["height"]) == (256, 192)
        (service,) = body["service"]
        assert service["profile"] == "http://iiif.io/api/annex/services/lightingmap"
        assert service["mapType"] == map_type
    formats = {r["format"]: r["type"] for r in obverse["rendering"]}
    assert formats["application/ply"] == "Model"
    assert formats["application/octet-stream"] == "Dataset"  # the height map
    thumbnail = manifest["thumbnail"][0]
    assert thumbnail["id"].endswith(f"/models/{newest}/assets/thumbnail.png")  # the obverse


def test_3d_manifest_is_the_presentation_4_draft(client, world, tablet_with_models):
    manifest = get_json(client, f"{API}/tablets/{world.public_a}/iiif/3d/manifest.json")
    assert manifest["@context"] == CONTEXT_3D
    assert manifest["rights"] == "https://creativecommons.org/licenses/by/4.0/"
    scenes = manifest["items"]
    assert [s["label"]["en"][0] for s in scenes] == ["whole tablet", "obverse", "reverse"]
    for scene in scenes:
        assert scene["type"] == "Scene"
        (page,) = scene["items"]
        (annotation,) = page["items"]
        assert annotation["target"]["id"] == scene["id"]
        body = annotation["body"]
        assert body["type"] == "Model" and body["format"] == "model/gltf-binary"
    obverse = scenes[1]["items"][0]["items"][0]["body"]
    assert obverse["id"].endswith(f"/models/{tablet_with_models['obverse']}/assets/model.glb")
    assert "version 2" in obverse["label"]["en"][0]


@pytest.mark.parametrize("which", ["manifest.json", "3d/manifest.json"])
def test_every_id_dereferences(client, world, tablet_with_models, which):
    manifest = get_json(client, f"{API}/tablets/{world.public_a}/iiif/{which}")
    nodes = [n for n in _walk(manifest) if "id" in n and "type" in n]
    assert len(nodes) > 20
    for node in nodes:
        if not node["id"].startswith(client.app.state.settings.resolved_public_url):
            assert node["id"].startswith("https://cdli.mpiwg-berlin.mpg.de/"), node["id"]
            continue
        response = client.get(urlsplit(node["id"]).path)
        assert response.status_code == 200, node["id"]
        if node["type"] in ("Canvas", "Scene", "AnnotationPage", "Annotation", "Service"):
            assert response.json()["id"] == node["id"] and response.json()["type"] == node["type"]
        elif "format" in node and node["format"] != "text/html":
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


@pytest.mark.parametrize("simulated", [True, False])
def test_simulated_scans_say_so_in_both_manifests(simulated):
    # The demo attaches simulated scans to a real record (P451806): a IIIF viewer elsewhere
    # showed them as that tablet's scans, with nothing saying they were simulated.
    urls = {"albedo.png": "http://x/a.png", "model.glb": "http://x/m.glb"}
    face = FaceModel(
        face="obverse",
        model_id=1,
        version=2,
        asset_urls=urls,
        width_px=4,
        height_px=3,
        simulated=simulated,
    )
    fields = {"designation": "T", "period": "Ur III"}
    manifest = build_manifest(manifest_id="http://x/m.json", fields=fields, face_models=[face])
    scenes = build_3d_manifest(manifest_id="http://x/3d.json", fields=fields, face_models=[face])
    Prezi3Manifest(**manifest)
    canvas, scene = manifest["items"][0], scenes["items"][0]
    texts = [
        manifest["summary"]["en"][0],
        scenes["summary"]["en"][0],
        canvas["label"]["en"][0],
        scene["label"]["en"][0],
        scene["items"][0]["items"][0]["body"]["label"]["en"][0],
    ]
    assert [("simulated" in t.lower()) for t in texts] == [simulated] * len(texts), texts


def test_build_manifest_rules():
    images = {"albedo.png": "http://x/a.png", "model.glb": "http://x/m.glb"}
    face = FaceModel(face="top", model_id=1, version=3, asset_urls=images, width_px=4, height_px=3)
    manifest = build_manifest(
        manifest_id="http://x/api/v1/tablets/1/iiif/manifest.json",
        fields={"designation": "T", "p_number": "X000001"},
        face_models=[face],
        provenance=Provenance(rights="All rights reserved"),
    )
    Prezi3Manifest(**manifest)
    assert "rights" not in manifest and "requiredStatement" not in manifest  # not a rights URI
    assert "seeAlso" not in manifest  # an X-number has no CDLI artifact page
    assert len(manifest["items"][0]["items"][0]["items"]) == 1  # no normal map, one layer
    assert "service" not in manifest["items"][0]  # no pixel size, no physical scale
    assert find_by_id(manifest, "http://x/api/v1/tablets/1/iiif/canvas/top")["type"] == "Canvas"
    assert find_by_id(manifest, "http://nowhere") is None
    no_grid = FaceModel(face="top", model_id=1, version=3, asset_urls=images)
    with pytest.raises(ValueError, match="albedo"):
        build_manifest(manifest_id="http://x/m.json", fields={}, face_models=[no_grid])
    with pytest.raises(ValueError, match="model.glb"):
        build_3d_manifest(manifest_id="http://x/m.json", fields={}, face_models=[])
    assert metadata_entries({"designation": "", "period": None, "width_mm": 20.0}) == [
        {"label": {"en": ["Dimensions"]}, "value": {"none": ["width 20 mm"]}}
    ]


@pytest.mark.parametrize(
    ("uri", "ok"),
    [
        ("https://creativecommons.org/licenses/by/4.0/", True),
        ("http://creativecommons.org/licenses/by-nc-sa/4.0/", True),
        ("https://creativecommons.org/publicdomain/zero/1.0/", True),
        ("http://creativecommons.org/publicdomain/mark/1.0/", True),
        ("http://rightsstatements.org/vocab/InC/1.0/", True),
        ("https://creativecommons.org/licenses/by/4.0/deed.de", False),
        ("All rights reserved", False),
        ("https://example.org/licenses/by/4.0/", False),
        (None, False),
    ],
)
def test_rights_uris(uri, ok):
    assert is_rights_uri(uri) is ok


def test_cdli_url():
    assert cdli_url("P254191") == "https://cdli.mpiwg-berlin.mpg.de/artifacts/254191"
    assert cdli_url("Q000001") is None and cdli_url(None) is None and cdli_url("P12") is None


def test_a_whole_tablet_model_alone_is_3d_only(client, world, store, tmp_path):
    with world.session() as session:
        job_id = jobs.create(session, tablet_id=world.public_a, kind="register").id
    finish(world, store, tmp_path, job_id, with_images=False)
    base = f"{API}/tablets/{world.public_a}/iiif"
    response = client.get(f"{base}/manifest.json")
    assert response.status_code == 404 and "relightable" in response.json()["detail"]
    assert client.get(f"{base}/3d/manifest.json").status_code == 200


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
    allowed = (base, "https://cdli.mpiwg-berlin.mpg.de/")
    assert ids and all(i.startswith(allowed) for i in ids), ids
