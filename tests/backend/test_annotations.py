"""Annotations of signs (W3C Web Annotations), transliterations and model licences, over the
API as clients use it; the IIIF manifest carries the annotations and still validates."""

from __future__ import annotations

import json
from datetime import datetime
from urllib.parse import urlsplit

import numpy as np
import pytest
import test_jobs as job_helpers
from iiif_prezi3 import Manifest as Prezi3Manifest
from test_iiif import finish

from backend import jobs
from backend.catalogue import import_catalogue
from backend.storage import LocalStorage
from backend.tables import Tablet

API = "/api/v1"
ANNO = "http://www.w3.org/ns/anno.jsonld"
ATF = "@obverse\n1. a-na {d}utu\n2. qi2-bi2-ma\n@reverse\n1. um-ma lugal-ma"
CC_BY = "https://creativecommons.org/licenses/by/4.0/"
# A triangle on the obverse of a model with 50 µm pixels and a 256 × 192 image grid.
TRIANGLE_MM = [[1.0, 2.0, -0.1], [3.0, 2.0, -0.1], [2.0, 4.0, -0.2]]


@pytest.fixture
def store(app) -> LocalStorage:
    app.state.storage = LocalStorage(app.state.settings.resolved_storage_dir)
    return app.state.storage


@pytest.fixture
def obverse(client, world, store, tmp_path) -> int:
    """Public tablet A with ATF and an obverse model (version 1); returns the model id."""
    with world.session() as session:
        session.get(Tablet, world.public_a).atf = ATF
    return finish(world, store, tmp_path, job_helpers.new_job(world, tablet_id=world.public_a))


def post(client, world, model_id: int, role: str = "reader", **body):
    payload = {"reference": "o 1 3", "polygon_mm": TRIANGLE_MM, **body}
    return client.post(
        f"{API}/models/{model_id}/annotations", json=payload, headers=world.headers(role)
    )


def test_transliteration_from_the_record_and_the_catalogue_import(client, world, tmp_path):
    url = f"{API}/tablets/{world.public_a}"
    assert client.get(f"{url}/transliteration").status_code == 404
    patched = client.patch(url, json={"atf": ATF + "\r\n\r\n"}, headers=world.headers("staff_own"))
    assert patched.status_code == 200 and patched.json()["atf"] == ATF
    parsed = client.get(f"{url}/transliteration").json()
    assert [s["surface"] for s in parsed["surfaces"]] == ["o", "r"]
    first = parsed["surfaces"][0]["lines"][0]
    assert first["number"] == "1" and first["text"] == "a-na {d}utu"
    assert [(s["text"], s["reference"]) for s in first["signs"]] == [
        ("a", "o 1 1"),
        ("na", "o 1 2"),
        ("{d}", "o 1 3"),
        ("utu", "o 1 4"),
    ]
    assert parsed["problems"] == []

    source = tmp_path / "catalogue.jsonl"
    record = {"id_text": "P000777", "designation": "Imported", "atf": "@reverse\n1. a-na\n2. ma"}
    source.write_text(json.dumps(record) + "\n")
    with world.session() as session:
        summary = import_catalogue(session, source, is_public=True)
    assert summary.inserted == 1
    imported = client.get(f"{API}/tablets/P000777/transliteration").json()
    assert [ln["number"] for ln in imported["surfaces"][0]["lines"]] == ["1", "2"]
    with world.session() as session:
        assert import_catalogue(session, source).unchanged == 1  # lines compared as text


def test_an_annotation_is_a_web_annotation(client, world, obverse):
    response = post(client, world, obverse, reading="d", comment="divine determinative")
    assert response.status_code == 201, response.text
    assert response.headers["content-type"] == f'application/ld+json; profile="{ANNO}"'
    a = response.json()
    assert a["@context"] == ANNO and a["type"] == "Annotation"
    assert a["id"].endswith(f"{API}/annotations/{a['annotationId']}")
    assert a["motivation"] == "commenting"
    assert [(b["type"], b["purpose"], b["value"]) for b in a["body"]] == [
        ("TextualBody", "identifying", "o 1 3"),
        ("TextualBody", "describing", "d"),
        ("TextualBody", "commenting", "divine determinative"),
    ]
    for stamp in (a["created"], a["modified"]):
        assert datetime.fromisoformat(stamp).utcoffset().total_seconds() == 0
    assert a["creator"]["type"] == "Person" and "@" not in a["creator"]["name"]
    model_target, image_target = a["target"]
    assert model_target["source"]["id"].endswith(f"/models/{obverse}/assets/model.glb")
    (wkt,) = model_target["selector"]
    assert wkt["type"] == "WktSelector"
    assert wkt["value"].startswith("POLYGON Z ((1.0000 2.0000 -0.1000, 3.0000")
    assert wkt["value"].endswith("1.0000 2.0000 -0.1000))")  # the ring is closed
    # Pixels from millimetres: c = 1000·x/s, r = 1000·y/s with s = 50 µm.
    assert image_target["source"]["id"].endswith(f"/models/{obverse}/assets/albedo.png")
    svg, box = image_target["selector"]
    assert svg["type"] == "SvgSelector" and 'points="20,40 60,40 40,80"' in svg["value"]
    assert box == {
        "type": "FragmentSelector",
        "conformsTo": "http://www.w3.org/TR/media-frags/",
        "value": "xywh=pixel:20,40,40,40",
    }
    assert (a["modelId"], a["modelVersion"], a["face"]) == (obverse, 1, "obverse")
    assert a["reference"] == {"text": "o 1 3", "surface": "o", "line": "1", "sign": 3}
    assert client.get(urlsplit(a["id"]).path).json() == a


@pytest.mark.parametrize(
    ("body", "where", "words"),
    [
        ({"reference": "x 1 1"}, "body.reference", "surface 'x' is not one of o, r"),
        ({"reference": "o one 1"}, "body.reference", "line 'one' is not a line number"),
        ({"reference": "o 1 0"}, "body.reference", "sign '0' is not a sign number"),
        ({"reference": "o 7 1"}, "body.reference", "the obverse has no line '7'"),
        ({"reference": "o 1 9"}, "body.reference", "line 1 of the obverse has 4 sign(s)"),
        ({"reference": "te 1 1"}, "body.reference", "has no top"),
        ({"polygon_mm": [[0, 0, 0], [1, 1, 1]]}, "body.polygon_mm", "at least 3"),
        ({"polygon_mm": [[0, 0, 0], [1, 1], [2, 2, 2]]}, "body.polygon_mm.1", "at least 3"),
        ({"polygon_mm": [[0, 0, 0], [1, 0, 0], [99, 0, 0]]}, "body.polygon_mm", "point 2"),
        ({"polygon_px": [[0, 0], [1, 1], [2, 2], [3, 3]]}, "body.polygon_px", "4 points"),
        ({"image_face": "reverse"}, "body.image_face", "this model is of the obverse"),
        ({"polygon_mm": [[0, 0, "NaN"], [1, 0, 0], [2, 0, 0]]}, "body.polygon_mm.0.2", "finite"),
        ({"colour": "red"}, "body.colour", "not permitted"),
    ],
)
def test_bad_annotations_are_422_naming_what_is_wrong(client, world, obverse, body, where, words):
    response = post(client, world, obverse, **body)
    assert response.status_code == 422, response.text
    error = response.json()
    assert error["where"] == where and words in error["detail"], error
    listing = client.get(f"{API}/models/{obverse}/annotations").json()
    assert listing["total"] == 0  # nothing half-written


def test_versions_listing_search_edit_and_delete(client, world, store, tmp_path, obverse):
    first = post(client, world, obverse, reading="{d}", comment="clear wedge").json()
    newer = finish(world, store, tmp_path, job_helpers.new_job(world, tablet_id=world.public_a))
    second = post(client, world, newer, "staff_other", reference="r 1 4", reading="lugal").json()
    assert second["modelVersion"] == 2 and second["motivation"] == "tagging"

    page = client.get(f"{API}/tablets/{world.public_a}/annotations").json()
    assert page["type"] == "AnnotationPage" and page["@context"] == ANNO
    assert [(a["reference"]["text"], a["modelVersion"]) for a in page["items"]] == [
        ("o 1 3", 1),
        ("r 1 4", 2),
    ]
    by_model = client.get(f"{API}/models/{newer}/annotations").json()
    assert [a["annotationId"] for a in by_model["items"]] == [second["annotationId"]]
    for q, found in [("LUGAL", ["r 1 4"]), ("wedge", ["o 1 3"]), ("r 1", ["r 1 4"]), ("%", [])]:
        hits = client.get(f"{API}/tablets/{world.public_a}/annotations", params={"q": q}).json()
        assert [a["reference"]["text"] for a in hits["items"]] == found, q

    url = f"{API}/annotations/{first['annotationId']}"
    refused = client.patch(url, json={"comment": "no"}, headers=world.headers("staff_other"))
    assert refused.status_code == 403 and refused.json()["where"] == "annotation_id"
    changed = client.patch(
        url, json={"reference": "o 2 1", "comment": None}, headers=world.headers("reader")
    )
    assert changed.status_code == 200, changed.text
    body = changed.json()
    assert body["reference"]["text"] == "o 2 1" and body["comment"] is None
    assert [b["purpose"] for b in body["body"]] == ["identifying", "describing"]
    assert body["modified"] >= body["created"]
    bad = client.patch(url, json={"reference": "o 2 9"}, headers=world.headers("staff_own"))
    assert bad.status_code == 422 and bad.json()["where"] == "body.reference"
    assert (
        client.patch(url, json={"reference": None}, headers=world.headers("admin")).json()["where"]
        == "body.reference"
    )
    assert client.delete(url, headers=world.headers("staff_own")).status_code == 204
    assert client.get(url).status_code == 404


def test_whole_tablet_annotations_name_their_face(client, world, store, tmp_path):
    with world.session() as session:
        job_id = jobs.create(session, tablet_id=world.public_a, kind="register").id
    whole = finish(world, store, tmp_path, job_id, with_images=False)
    missing = post(client, world, whole, polygon_px=[[1, 1], [2, 1], [2, 2]])
    assert missing.status_code == 422 and missing.json()["where"] == "body.image_face"
    ok = post(client, world, whole, polygon_px=[[1, 1], [2, 1], [2, 2]], image_face="reverse")
    assert ok.status_code == 201, ok.text
    assert ok.json()["face"] == "tablet" and ok.json()["imageFace"] == "reverse"
    only_mm = post(client, world, whole).json()
    assert len(only_mm["target"]) == 1  # no image grid named: the model region only


def test_the_manifest_carries_the_annotations_and_validates(client, world, obverse):
    post(client, world, obverse, reading="{d}", comment="clear")
    post(client, world, obverse, reference="o 2 1")
    manifest = client.get(f"{API}/tablets/{world.public_a}/iiif/manifest.json").json()
    Prezi3Manifest(**manifest)
    (canvas,) = manifest["items"]
    (page,) = canvas["annotations"]
    assert page["type"] == "AnnotationPage"
    assert [a["motivation"] for a in page["items"]] == ["commenting", "tagging"]
    target = page["items"][0]["target"]
    assert target["source"] == {"id": canvas["id"], "type": "Canvas"}
    assert target["selector"]["type"] == "SvgSelector"
    assert 'points="20,40 60,40 40,80"' in target["selector"]["value"]
    for node in (page, *page["items"]):
        served = client.get(urlsplit(node["id"]).path)
        assert served.status_code == 200 and served.json()["id"] == node["id"]


def test_staff_set_a_model_licence_seen_in_record_and_manifests(client, world, obverse):
    url = f"{API}/models/{obverse}"
    assert client.get(url).json()["effective_licence"] is None
    bad = client.patch(url, json={"licence": "all rights reserved"}, headers=world.headers("admin"))
    assert bad.status_code == 422 and bad.json()["where"] == "body.licence"
    assert "Creative Commons" in bad.json()["detail"]
    refused = client.patch(url, json={"licence": CC_BY}, headers=world.headers("staff_other"))
    assert refused.status_code == 403
    body = {"licence": CC_BY, "attribution": "Scanned by the Hilprecht project"}
    changed = client.patch(url, json=body, headers=world.headers("staff_own"))
    assert changed.status_code == 200, changed.text
    record = client.get(url).json()
    assert record["licence"] == CC_BY and record["effective_licence"] == CC_BY
    assert record["effective_attribution"] == "Scanned by the Hilprecht project"
    scans = client.get(f"{API}/tablets/{world.public_a}/scans").json()
    (listed,) = [m for s in scans for m in s["models"] if m["id"] == obverse]
    assert listed["effective_licence"] == CC_BY

    manifest = client.get(f"{API}/tablets/{world.public_a}/iiif/manifest.json").json()
    Prezi3Manifest(**manifest)
    canvas = manifest["items"][0]
    assert canvas["rights"] == CC_BY
    assert canvas["requiredStatement"]["value"] == {"en": ["Scanned by the Hilprecht project"]}
    assert "rights" not in manifest  # the tablet itself states no licence
    scene = client.get(f"{API}/tablets/{world.public_a}/iiif/3d/manifest.json").json()["items"][0]
    assert scene["rights"] == CC_BY

    cleared = client.patch(url, json={"licence": None}, headers=world.headers("admin")).json()
    assert cleared["licence"] is None and cleared["attribution"] is not None


def test_a_word_that_is_also_a_surface_finds_readings_and_references(client, world, obverse):
    post(client, world, obverse, reference="o 2 2", reading="be")
    post(client, world, obverse, reference="o 1 1", reading="a")
    url = f"{API}/models/{obverse}/annotations"
    found = client.get(url, params={"q": "be"}).json()["items"]
    assert [a["reading"] for a in found] == ["be"]  # no bottom edge sign, but the reading
    assert client.get(url, params={"q": "o"}).json()["total"] == 2  # every obverse sign
    assert client.get(url, params={"q": "o 1"}).json()["total"] == 1
    long = client.get(url, params={"q": "x" * 201})
    assert long.status_code == 422 and long.json()["where"] == "query.q"


def _model_with_glb(world, store, tmp_path, glb: bytes) -> int:
    """An obverse model of public A whose model.glb is ``glb`` (the rest as ``finish``)."""
    directory = job_helpers.model_dir(tmp_path, name="with-glb")
    (directory / "model.glb").write_bytes(glb)
    (directory / "albedo.png").write_bytes(b"\x89PNG\r\n\x1a\n albedo")
    report = {"pixel_size_um": 50, "image_size": {"width": 256, "height": 192}}
    (directory / "report.json").write_text(json.dumps(report))
    job_id = job_helpers.new_job(world, tablet_id=world.public_a)
    with world.session() as session:
        jobs.mark_running(session, job_id=job_id)
        return jobs.mark_succeeded(session, job_id=job_id, model_dir=directory, storage=store).id


def test_the_3d_manifest_puts_each_region_in_its_scene(client, world, store, tmp_path, obverse):
    import trimesh

    from worker.recon.gltf_frame import gltf_root_matrix, wrap_scene_in_gltf_frame

    vertices = np.array([[0.0, 0.0, 0.0], [12.0, 0.0, 0.0], [0.0, 9.0, -1.0]])
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.Trimesh(vertices=vertices, faces=[[0, 1, 2]]))
    glb = wrap_scene_in_gltf_frame(scene.export(file_type="glb"))
    post(client, world, obverse)  # its model.glb is not a GLB: no scene region, no error
    model_id = _model_with_glb(world, store, tmp_path, glb)
    created = post(client, world, model_id, comment="checked").json()

    manifest = client.get(f"{API}/tablets/{world.public_a}/iiif/3d/manifest.json").json()
    (scene_json,) = [s for s in manifest["items"] if s["label"]["en"] == ["obverse"]]
    (page,) = scene_json["annotations"]
    (annotation,) = page["items"]
    assert annotation["motivation"] == ["commenting"]
    assert [b["purpose"] for b in annotation["body"]] == ["identifying", "commenting"]
    target = annotation["target"]
    assert target["source"] == {"id": scene_json["id"], "type": "Scene"}
    (selector,) = target["selector"]
    assert selector["type"] == "WktSelector"
    ring = selector["value"].removeprefix("POLYGON Z ((").removesuffix("))").split(", ")
    got = np.array([[float(v) for v in p.split()] for p in ring])
    # Scan frame mm → glTF metres, +Y up, the box centred (worker/recon/gltf_frame.py).
    matrix = gltf_root_matrix(vertices.min(axis=0), vertices.max(axis=0))
    points = np.array(TRIANGLE_MM + TRIANGLE_MM[:1])
    expected = points @ matrix[:3, :3].T + matrix[:3, 3]
    assert np.allclose(got, expected, atol=1e-6), (got, expected)
    served = client.get(urlsplit(annotation["id"]).path)
    assert served.status_code == 200 and served.json()["id"] == annotation["id"]
    assert annotation["id"].endswith(f"/annotations/{created['annotationId']}")
