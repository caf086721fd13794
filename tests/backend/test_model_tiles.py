"""A model's tiles (worker/tiles) through the asset route: recorded once (tiles/index.json
and tiles/files.json), every tile served with ETag, 304, Range; IIIF info.json with its id
from the public URL; hostile names never reach another file; private tiles stay private."""

from __future__ import annotations

import hashlib
import json
import shutil

import pytest
import test_jobs as job_helpers  # sibling helpers (tests/backend is on pythonpath)

from backend import jobs
from backend.storage import LocalStorage
from worker.simulate.large_face import write_large_face
from worker.tiles import build_tiles

API = "/api/v1"


@pytest.fixture
def db_url(sqlite_url) -> str:
    return sqlite_url


@pytest.fixture(scope="module")
def tiled_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiled") / "face"
    write_large_face(out, width_px=700, height_px=560, seed=1)
    build_tiles(out)
    return out


@pytest.fixture
def store(app) -> LocalStorage:
    app.state.storage = LocalStorage(app.state.settings.resolved_storage_dir)
    return app.state.storage


def _model(world, store, tmp_path, tiled_dir, *, tablet_id: int) -> int:
    directory = tmp_path / "model"
    shutil.copytree(tiled_dir, directory)
    job_id = job_helpers.new_job(world, tablet_id=tablet_id)
    with world.session() as session:
        jobs.mark_running(session, job_id=job_id)
        return jobs.mark_succeeded(session, job_id=job_id, model_dir=directory, storage=store).id


def test_tiles_are_recorded_once_and_every_file_is_served(
    client, world, store, tmp_path, tiled_dir
):
    model_id = _model(world, store, tmp_path, tiled_dir, tablet_id=world.public_a)
    assets = client.get(f"{API}/models/{model_id}").json()["assets"]
    assert {n for n in assets if n.startswith("tiles/")} == {"tiles/index.json", "tiles/files.json"}
    files = json.loads((tiled_dir / "tiles" / "files.json").read_text())
    assert len(files) > 20
    for name, info in list(files.items())[:: max(1, len(files) // 15)]:
        if name.endswith("info.json"):
            continue  # rewritten at serve time (below)
        response = client.get(f"{API}/models/{model_id}/assets/tiles/{name}")
        assert response.status_code == 200, name
        assert response.content == (tiled_dir / "tiles" / name).read_bytes()
        assert response.headers["etag"] == f'"{info["sha256"]}"'


def test_a_tile_has_etag_304_head_and_range(client, world, store, tmp_path, tiled_dir):
    model_id = _model(world, store, tmp_path, tiled_dir, tablet_id=world.public_a)
    url = f"{API}/models/{model_id}/assets/tiles/3d/0/0_0.glb"
    data = (tiled_dir / "tiles" / "3d" / "0" / "0_0.glb").read_bytes()
    response = client.get(url)
    assert response.status_code == 200 and response.content == data
    assert response.headers["content-type"] == "model/gltf-binary"
    assert "immutable" in response.headers["cache-control"]
    assert "max-age=31536000" in response.headers["cache-control"]
    etag = response.headers["etag"]
    assert etag == f'"{hashlib.sha256(data).hexdigest()}"'
    assert client.get(url, headers={"If-None-Match": etag}).status_code == 304
    head = client.head(url)
    assert head.status_code == 200 and head.content == b""
    assert head.headers["content-length"] == str(len(data))
    part = client.get(url, headers={"Range": "bytes=12-99"})
    assert part.status_code == 206 and part.content == data[12:100]
    assert part.headers["content-range"] == f"bytes 12-99/{len(data)}"
    assert client.get(url, headers={"Range": f"bytes={len(data)}-"}).status_code == 416


def test_height_rows_by_range(client, world, store, tmp_path, tiled_dir):
    import numpy as np

    model_id = _model(world, store, tmp_path, tiled_dir, tablet_id=world.public_a)
    index = client.get(f"{API}/models/{model_id}/assets/tiles/index.json").json()
    h, w = index["height_raw"]["shape"]
    row = 300
    start = row * w * 4
    response = client.get(
        f"{API}/models/{model_id}/assets/tiles/{index['height_raw']['path']}",
        headers={"Range": f"bytes={start}-{start + 4 * w - 1}"},
    )
    assert response.status_code == 206
    values = np.frombuffer(response.content, "<f4")
    np.testing.assert_array_equal(values, np.load(tiled_dir / "height.npy")[row])


def test_iiif_info_json_id_comes_from_the_public_url(client, world, store, tmp_path, tiled_dir):
    model_id = _model(world, store, tmp_path, tiled_dir, tablet_id=world.public_a)
    url = f"{API}/models/{model_id}/assets/tiles/iiif/albedo/info.json"
    response = client.get(url, headers={"Host": "evil.example"})
    assert response.status_code == 200
    info = response.json()
    public = client.app.state.settings.resolved_public_url
    layer = f"{public}{API}/models/{model_id}/assets/tiles/iiif/albedo"
    assert info["id"] == layer and "evil" not in response.text
    assert info["type"] == "ImageService3" and info["profile"] == "level0"
    assert response.headers["content-length"] == str(len(response.content))
    etag = response.headers["etag"]
    assert etag == f'"{hashlib.sha256(response.content).hexdigest()}"'
    assert client.get(url, headers={"If-None-Match": etag}).status_code == 304
    assert client.head(url).headers["content-length"] == str(len(response.content))
    # A IIIF client's tile request, made from the id: {id}/{region}/{size}/0/default.jpg
    size = info["tiles"][0]["width"]
    tile = f"{info['id']}/0,0,{size},{size}/{size},{size}/0/default.jpg".removeprefix(public)
    got = client.get(tile)
    assert got.status_code == 200 and got.headers["content-type"] == "image/jpeg"
    assert got.content[:2] == b"\xff\xd8"


@pytest.mark.parametrize(
    "name",
    [
        # (plain "../" is resolved by the HTTP client itself: encoded, it reaches the route)
        "tiles/%2e%2e/report.json",
        "tiles/3d/..%2F..%2Freport.json",
        "tiles/index.json/%2e%2e/%2e%2e/report.json",
        "tiles//3d/tileset.json",
        "tiles/%2Fetc%2Fpasswd",
        "tiles/3d/0/0_0.glb%00",
        "tiles/.files.json",
        "tiles/files.json/x",
        "faces/x/tiles/3d/tileset.json",
        "tiles/",
        "tiles",
    ],
)
def test_hostile_tile_names_are_not_found(client, world, store, tmp_path, tiled_dir, name):
    model_id = _model(world, store, tmp_path, tiled_dir, tablet_id=world.public_a)
    response = client.get(f"{API}/models/{model_id}/assets/{name}")
    assert response.status_code in (404, 422), name
    assert response.json()["detail"]


def test_private_model_tiles_are_not_readable_anonymously(
    client, world, store, tmp_path, tiled_dir
):
    model_id = _model(world, store, tmp_path, tiled_dir, tablet_id=world.private_a)
    for name in ("tiles/3d/tileset.json", "tiles/3d/0/0_0.glb", "tiles/iiif/albedo/info.json"):
        url = f"{API}/models/{model_id}/assets/{name}"
        assert client.get(url).status_code == 404
        assert client.head(url).status_code == 404
        assert client.get(url, headers=world.headers("staff_other")).status_code == 404
        owner = client.get(url, headers=world.headers("staff_own"))
        assert owner.status_code == 200
        assert owner.headers["cache-control"].startswith("private")


def test_manifest_gives_each_layer_its_image_service(client, world, store, tmp_path, tiled_dir):
    """Issue 18: albedo, normal map and height of a face carry a IIIF Image API 3 level-0
    service on the tiles; the manifest still validates with iiif-prezi3."""
    from urllib.parse import urlsplit

    from iiif_prezi3 import Manifest as Prezi3Manifest

    job_id = job_helpers.new_job(world, tablet_id=world.public_a, face="obverse")
    directory = tmp_path / "model"
    shutil.copytree(tiled_dir, directory)
    with world.session() as session:
        jobs.mark_running(session, job_id=job_id)
        model_id = jobs.mark_succeeded(
            session, job_id=job_id, model_dir=directory, storage=store
        ).id
    manifest = client.get(f"{API}/tablets/{world.public_a}/iiif/manifest.json").json()
    Prezi3Manifest(**manifest)  # raises on any deviation from the Presentation 3 schema
    (canvas,) = manifest["items"]
    assert (canvas["width"], canvas["height"]) == (700, 560)
    public = client.app.state.settings.resolved_public_url
    base = f"{public}{API}/models/{model_id}/assets/tiles/iiif"
    bodies = [a["body"] for a in canvas["items"][0]["items"]]
    (height_annotation,) = canvas["annotations"][0]["items"]
    assert height_annotation["motivation"] == "supplementing"
    bodies.append(height_annotation["body"])
    for body, layer in zip(bodies, ("albedo", "normals", "height"), strict=True):
        (service,) = [s for s in body["service"] if s["type"] == "ImageService3"]
        assert service == {"id": f"{base}/{layer}", "type": "ImageService3", "profile": "level0"}
        # The service's base URI redirects (303) to its info.json, whose id is the service id.
        redirect = client.get(urlsplit(service["id"]).path, follow_redirects=False)
        assert redirect.status_code == 303
        info = client.get(urlsplit(redirect.headers["location"]).path).json()
        assert info["id"] == service["id"]
    # The height image itself: the largest whole-image rendition of the pyramid.
    height = client.get(urlsplit(bodies[2]["id"]).path)
    assert height.status_code == 200 and height.headers["content-type"] == "image/png"
    assert (bodies[2]["width"], bodies[2]["height"]) == (350, 280)


def test_a_whole_tablets_face_tiles_are_served(client, world, store, tmp_path, tiled_dir):
    """A whole-tablet model: tiles/faces/<label>/... found in the one tiles/files.json."""
    import numpy as np

    from worker.tiles.tablet import build_tablet_tiles

    directory = tmp_path / "tablet"
    directory.mkdir()
    build_tablet_tiles(directory, {"faces/obverse": (tiled_dir, np.eye(4))})
    (directory / "model.glb").write_bytes((tiled_dir / "model.glb").read_bytes())
    with world.session() as session:
        job_id = jobs.create(session, tablet_id=world.public_a, kind="register").id
        jobs.mark_running(session, job_id=job_id)
        model_id = jobs.mark_succeeded(
            session, job_id=job_id, model_dir=directory, storage=store
        ).id
    base = f"{API}/models/{model_id}/assets/tiles"
    root = client.get(f"{base}/3d/tileset.json").json()
    (child,) = root["root"]["children"]
    # The external tileset's URI, resolved against the root tileset's URL as a browser does.
    face_set = client.get(f"{base}/{child['content']['uri'].removeprefix('../')}")
    assert face_set.status_code == 200
    glb = client.get(f"{base}/faces/obverse/3d/{face_set.json()['root']['content']['uri']}")
    assert glb.status_code == 200 and glb.content[:4] == b"glTF"
    info = client.get(f"{base}/faces/obverse/iiif/normals/info.json").json()
    assert info["id"].endswith(f"/models/{model_id}/assets/tiles/faces/obverse/iiif/normals")
