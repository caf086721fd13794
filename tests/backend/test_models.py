"""Model versions and asset delivery: ETag, 304, Range (206/416), types, private access."""

from __future__ import annotations

import os

import pytest
import test_jobs as job_helpers  # sibling helpers (tests/backend is on pythonpath)
from moto.server import ThreadedMotoServer

from backend import jobs
from backend.api.models import parse_range
from backend.storage import LocalStorage, S3Storage

API = "/api/v1"


@pytest.fixture
def db_url(sqlite_url) -> str:
    return sqlite_url


def make_model(world, store, tmp_path, *, tablet_id: int, glb: bytes) -> int:
    directory = job_helpers.model_dir(tmp_path, name=f"m{os.urandom(4).hex()}")
    (directory / "model.glb").write_bytes(glb)
    job_id = job_helpers.new_job(world, tablet_id=tablet_id)
    with world.session() as session:
        jobs.mark_running(session, job_id=job_id)
        return jobs.mark_succeeded(session, job_id=job_id, model_dir=directory, storage=store).id


@pytest.fixture
def store(app) -> LocalStorage:
    app.state.storage = LocalStorage(app.state.settings.resolved_storage_dir)
    return app.state.storage


GLB = bytes(range(256)) * 40  # 10240 bytes


def test_model_record_lists_stable_asset_urls(client, world, store, tmp_path):
    model_id = make_model(world, store, tmp_path, tablet_id=world.public_a, glb=GLB)
    body = client.get(f"{API}/models/{model_id}").json()
    assert body["version"] == 1 and body["tablet_id"] == world.public_a
    assert body["assets"]["model.glb"] == f"{API}/models/{model_id}/assets/model.glb"
    assert body["assets"]["quality/residual.npy"].endswith("/assets/quality/residual.npy")
    for url in body["assets"].values():  # every listed URL dereferences
        assert client.get(url).status_code == 200


def test_full_download_with_caching_headers(client, world, store, tmp_path):
    model_id = make_model(world, store, tmp_path, tablet_id=world.public_a, glb=GLB)
    url = f"{API}/models/{model_id}/assets/model.glb"
    response = client.get(url)
    assert response.status_code == 200 and response.content == GLB
    assert response.headers["content-type"] == "model/gltf-binary"
    assert response.headers["content-length"] == str(len(GLB))
    assert response.headers["accept-ranges"] == "bytes"
    assert "immutable" in response.headers["cache-control"]
    assert response.headers["cache-control"].startswith("public")
    etag = response.headers["etag"]
    assert etag.strip('"') == __import__("hashlib").sha256(GLB).hexdigest()
    assert response.headers["last-modified"].endswith("GMT")

    assert client.get(url, headers={"If-None-Match": etag}).status_code == 304
    assert client.get(url, headers={"If-None-Match": f'"x", W/{etag}'}).status_code == 304
    assert client.get(url, headers={"If-None-Match": '"other"'}).status_code == 200
    since = response.headers["last-modified"]
    assert client.get(url, headers={"If-Modified-Since": since}).status_code == 304
    head = client.head(url)
    assert head.status_code == 200 and head.content == b""
    assert head.headers["content-length"] == str(len(GLB))


@pytest.mark.parametrize(
    ("header", "start", "end"),
    [
        ("bytes=0-99", 0, 100),
        ("bytes=100-", 100, 10240),
        ("bytes=-10", 10230, 10240),
        ("bytes=10000-20000", 10000, 10240),  # clipped to the end
        ("bytes=10239-10239", 10239, 10240),
        ("Bytes=0-9", 0, 10),  # RFC 9110 14.1: range units compare case-insensitively
        ("BYTES=-10", 10230, 10240),
    ],
)
def test_single_range_is_206(client, world, store, tmp_path, header, start, end):
    model_id = make_model(world, store, tmp_path, tablet_id=world.public_a, glb=GLB)
    response = client.get(f"{API}/models/{model_id}/assets/model.glb", headers={"Range": header})
    assert response.status_code == 206
    assert response.content == GLB[start:end]
    assert response.headers["content-range"] == f"bytes {start}-{end - 1}/{len(GLB)}"


def test_unsatisfiable_and_ignored_ranges(client, world, store, tmp_path):
    model_id = make_model(world, store, tmp_path, tablet_id=world.public_a, glb=GLB)
    url = f"{API}/models/{model_id}/assets/model.glb"
    response = client.get(url, headers={"Range": "bytes=20000-"})
    assert response.status_code == 416
    assert response.headers["content-range"] == f"bytes */{len(GLB)}"
    assert response.json()["where"] == "range"
    # Several ranges, or an If-Range that no longer matches: the whole file.
    assert client.get(url, headers={"Range": "bytes=0-1,5-6"}).status_code == 200
    stale = client.get(url, headers={"Range": "bytes=0-1", "If-Range": '"old"'})
    assert stale.status_code == 200 and stale.content == GLB


def test_content_types(client, world, store, tmp_path):
    model_id = make_model(world, store, tmp_path, tablet_id=world.public_a, glb=GLB)
    expected = {
        "mesh.ply": "application/ply",
        "thumbnail.png": "image/png",
        "report.json": "application/json",
        "quality/residual.npy": "application/octet-stream",
    }
    for name, media_type in expected.items():
        response = client.get(f"{API}/models/{model_id}/assets/{name}")
        assert response.headers["content-type"].split(";")[0] == media_type, name


def test_private_models_only_for_their_institution(client, world, store, tmp_path):
    model_id = make_model(world, store, tmp_path, tablet_id=world.private_a, glb=GLB)
    url = f"{API}/models/{model_id}/assets/model.glb"
    for role, status in [
        ("anonymous", 404),
        ("reader", 404),
        ("staff_other", 404),
        ("staff_own", 200),
        ("admin", 200),
    ]:
        assert client.get(url, headers=world.headers(role)).status_code == status, role
        assert client.get(f"{API}/models/{model_id}", headers=world.headers(role)).status_code == (
            status
        )
    response = client.get(url, headers=world.headers("admin"))
    assert response.headers["cache-control"].startswith("private")


def test_unknown_assets_and_models(client, world, store, tmp_path):
    model_id = make_model(world, store, tmp_path, tablet_id=world.public_a, glb=GLB)
    response = client.get(f"{API}/models/{model_id}/assets/secret.txt")
    assert response.status_code == 404 and response.json()["where"] == "name"
    assert client.get(f"{API}/models/{model_id}/assets/../../etc/passwd").status_code == 404
    assert client.get(f"{API}/models/424242").status_code == 404


def test_storage_outage_is_a_clean_503(client, world, store, tmp_path, monkeypatch):
    model_id = make_model(world, store, tmp_path, tablet_id=world.public_a, glb=GLB)
    from backend.storage import StorageError

    def unavailable(*args, **kwargs):
        raise StorageError("object storage unreachable")

    monkeypatch.setattr(store, "open_range", unavailable)
    response = client.get(f"{API}/models/{model_id}/assets/model.glb")
    assert response.status_code == 503
    assert response.json() == {"detail": "object storage unreachable", "where": "storage"}
    assert response.headers["retry-after"] == "30"


def test_assets_from_s3(client, world, app, tmp_path):
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    try:
        host, port = server.get_host_and_port()
        store = S3Storage(
            bucket="models-test",
            endpoint_url=f"http://{host}:{port}",
            access_key_id="testing",
            secret_access_key="testing",
        )
        store.ensure_bucket()
        app.state.storage = store
        model_id = make_model(world, store, tmp_path, tablet_id=world.public_a, glb=GLB)
        url = f"{API}/models/{model_id}/assets/model.glb"
        assert client.get(url).content == GLB
        ranged = client.get(url, headers={"Range": "bytes=1000-1999"})
        assert ranged.status_code == 206 and ranged.content == GLB[1000:2000]
    finally:
        server.stop()


def test_parse_range_rules():
    assert parse_range("bytes=0-0", 5) == (0, 1)
    assert parse_range("bytes=2-", 5) == (2, 5)
    assert parse_range("bytes=-100", 5) == (0, 5)
    assert parse_range("items=0-1", 5) is None
    assert parse_range("bytes=3-1", 5) is None
    assert parse_range("Bytes=1-2", 5) == (1, 3)
    for bad in ("bytes=5-", "bytes=-0"):
        with pytest.raises(ValueError):
            parse_range(bad, 5)
