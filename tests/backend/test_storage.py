"""The storage interface, run against a local directory and an S3 server (moto, server mode)."""

from __future__ import annotations

import errno
import hashlib
import os
from pathlib import Path

import boto3
import pytest
from botocore.config import Config
from hypothesis import given, settings
from hypothesis import strategies as st
from moto.server import ThreadedMotoServer

from backend.storage import (
    ChecksumMismatch,
    LocalStorage,
    ObjectNotFound,
    S3Storage,
    StorageError,
    check_key,
)
from backend.storage import local as storage_mod


@pytest.fixture(scope="module")
def s3_endpoint():
    """A real HTTP S3 endpoint on a free loopback port, like a MinIO would be."""
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    yield f"http://{host}:{port}"
    server.stop()


def make_s3(endpoint: str, bucket: str) -> S3Storage:
    store = S3Storage(
        bucket=bucket,
        endpoint_url=endpoint,
        access_key_id="testing",
        secret_access_key="testing",
        region="us-east-1",
    )
    store.ensure_bucket()
    return store


@pytest.fixture(params=["local", "s3"])
def store(request, tmp_path):
    if request.param == "local":
        return LocalStorage(tmp_path / "store")
    endpoint = request.getfixturevalue("s3_endpoint")
    # A bucket per test: tests share the module's server but never its objects.
    return make_s3(endpoint, f"t-{os.urandom(6).hex()}")


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def test_put_bytes_round_trip(store):
    data = os.urandom(3 * storage_mod.COPY_CHUNK_BYTES + 17)
    stat = store.put_bytes("scans/1/bundle.zip", data)
    assert stat.key == "scans/1/bundle.zip"
    assert stat.size_bytes == len(data)
    assert stat.etag == sha(data)
    assert store.stat("scans/1/bundle.zip") == stat
    assert store.exists("scans/1/bundle.zip")
    assert store.read_bytes("scans/1/bundle.zip") == data


def test_put_file_verifies_the_checksum_it_is_given(store, tmp_path):
    src = tmp_path / "src.bin"
    data = os.urandom(10_000)
    src.write_bytes(data)
    assert store.put_file("a/b.bin", src, sha256=sha(data).upper()).etag == sha(data)
    assert store.read_bytes("a/b.bin") == data


def test_checksum_mismatch_keeps_nothing_and_leaves_the_old_object(store, tmp_path):
    store.put_bytes("a/old.bin", b"old contents")
    bad = "0" * 64
    with pytest.raises(ChecksumMismatch) as info:
        store.put_bytes("a/old.bin", b"new contents", sha256=bad)
    assert info.value.expected == bad and info.value.actual == sha(b"new contents")
    assert store.read_bytes("a/old.bin") == b"old contents"
    src = tmp_path / "new.bin"
    src.write_bytes(b"fresh")
    with pytest.raises(ChecksumMismatch):
        store.put_file("a/new.bin", src, sha256=bad)
    assert not store.exists("a/new.bin")
    assert store.list("a/") == ["a/old.bin"]


def test_missing_objects(store):
    with pytest.raises(ObjectNotFound) as info:
        store.stat("nope/x")
    assert info.value.status_code == 404
    with pytest.raises(ObjectNotFound):
        store.open_range("nope/x")
    assert not store.exists("nope/x")
    store.delete("nope/x")  # deleting nothing is fine


def test_delete_and_list(store):
    for key in ["m/1/v1/model.glb", "m/1/v1/mesh.ply", "m/1/v10/model.glb", "m/2/x", "z"]:
        store.put_bytes(key, key.encode())
    assert store.list("m/1/v1/") == ["m/1/v1/mesh.ply", "m/1/v1/model.glb"]
    # A plain string prefix, as in S3: "m/1/v1" also matches "m/1/v10/...".
    assert store.list("m/1/v1") == ["m/1/v1/mesh.ply", "m/1/v1/model.glb", "m/1/v10/model.glb"]
    assert store.list() == sorted(
        ["m/1/v1/model.glb", "m/1/v1/mesh.ply", "m/1/v10/model.glb", "m/2/x", "z"]
    )
    store.delete("m/1/v1/mesh.ply")
    assert store.list("m/1/v1/") == ["m/1/v1/model.glb"]
    assert store.delete_prefix("m/1") == 2
    assert store.list() == ["m/2/x", "z"]


@settings(max_examples=25, deadline=None)
@given(data=st.data())
def test_open_range_equals_slicing(data, tmp_path_factory):
    store = LocalStorage(tmp_path_factory.mktemp("ranges"))
    blob = bytes(range(256)) * 9000  # > 2 copy chunks, so ranges span chunk boundaries
    store.put_bytes("blob", blob)
    start = data.draw(st.integers(0, len(blob)))
    end = data.draw(st.one_of(st.none(), st.integers(start, len(blob))))
    got = b"".join(store.open_range("blob", start, end))
    assert got == blob[start:end]


def test_open_range_on_both_backends(store):
    blob = os.urandom(2 * storage_mod.COPY_CHUNK_BYTES + 5)
    store.put_bytes("blob", blob)
    n = len(blob)
    for start, end in [(0, None), (0, 1), (n - 1, n), (5, n - 5), (n, n), (1000, 1000)]:
        assert b"".join(store.open_range("blob", start, end)) == blob[start:end]
    for start, end in [(-1, 3), (4, 3), (0, n + 1), (n + 1, None)]:
        with pytest.raises(ValueError, match="range"):
            store.open_range("blob", start, end)


def test_put_tree_and_get_file(store, tmp_path):
    model = tmp_path / "model"
    (model / "quality").mkdir(parents=True)
    files = {"model.glb": b"glb", "report.json": b"{}", "quality/residual.npy": b"npy"}
    for rel, content in files.items():
        (model / rel).write_bytes(content)
    stats = store.put_tree("models/7/v1", model)
    assert sorted(s.key for s in stats) == sorted(f"models/7/v1/{rel}" for rel in files)
    for rel, content in files.items():
        out = store.get_file(f"models/7/v1/{rel}", tmp_path / "out.bin")
        assert out.read_bytes() == content


def test_put_tree_rolls_back_on_failure(store, tmp_path, monkeypatch):
    model = tmp_path / "model"
    model.mkdir()
    for name in ["a.bin", "b.bin", "c.bin"]:
        (model / name).write_bytes(name.encode())
    real_put_file = store.put_file

    def failing_put_file(key, path, *, sha256=None):
        if key.endswith("c.bin"):
            raise StorageError("object storage answered SlowDown", key=key)
        return real_put_file(key, path, sha256=sha256)

    monkeypatch.setattr(store, "put_file", failing_put_file)
    with pytest.raises(StorageError):
        store.put_tree("models/1/v1", model)
    assert store.list("models/") == []


def test_local_disk_full_is_507_and_keeps_the_old_object(tmp_path, monkeypatch):
    store = LocalStorage(tmp_path / "store")
    store.put_bytes("a/x.bin", b"first version")

    def no_space(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(storage_mod.os, "fsync", no_space)
    with pytest.raises(StorageError) as info:
        store.put_bytes("a/x.bin", b"second version")
    assert info.value.status_code == 507
    assert info.value.key == "a/x.bin"
    monkeypatch.undo()
    assert store.read_bytes("a/x.bin") == b"first version"
    assert list((tmp_path / "store" / ".tmp").iterdir()) == []  # no temp file left behind


def test_local_io_error_is_503(tmp_path, monkeypatch):
    store = LocalStorage(tmp_path / "store")

    def io_error(fd):
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(storage_mod.os, "fsync", io_error)
    with pytest.raises(StorageError) as info:
        store.put_bytes("a/x.bin", b"data")
    assert info.value.status_code == 503
    monkeypatch.undo()
    assert not store.exists("a/x.bin")


def test_local_stat_hashes_files_it_did_not_write(tmp_path):
    store = LocalStorage(tmp_path / "store")
    store.put_bytes("a/x.bin", b"ours")
    # Replaced behind the store's back (size changes): the stale sidecar must not be trusted.
    (tmp_path / "store" / "a" / "x.bin").write_bytes(b"someone else's")
    assert store.stat("a/x.bin").etag == sha(b"someone else's")
    (tmp_path / "store" / "b").mkdir()
    (tmp_path / "store" / "b" / "y.bin").write_bytes(b"external")
    assert store.stat("b/y.bin").etag == sha(b"external")
    assert store.list() == ["a/x.bin", "b/y.bin"]  # sidecars and temp files are not keys


def test_unreachable_s3_is_503():
    client = boto3.client(
        "s3",
        endpoint_url="http://127.0.0.1:9",  # discard port: connection refused
        aws_access_key_id="testing",
        aws_secret_access_key="testing",
        region_name="us-east-1",
        config=Config(retries={"max_attempts": 1}, connect_timeout=1),
    )
    store = S3Storage(bucket="b", client=client)
    with pytest.raises(StorageError) as info:
        store.put_bytes("a/x", b"data")
    assert info.value.status_code == 503
    with pytest.raises(StorageError):
        store.stat("a/x")


def test_missing_bucket_is_a_storage_error(s3_endpoint):
    store = S3Storage(
        bucket="no-such-bucket",
        endpoint_url=s3_endpoint,
        access_key_id="testing",
        secret_access_key="testing",
    )
    with pytest.raises(StorageError) as info:
        store.put_bytes("a/x", b"data")
    assert info.value.status_code == 503


@pytest.mark.parametrize(
    "key", ["", "/abs", "a/../b", "a//b", "a\\b", "a\x00b", ".tmp/x", "a/.sha256", "dir/"]
)
def test_bad_keys_are_refused(key, tmp_path):
    with pytest.raises(ValueError, match="key"):
        check_key(key)
    with pytest.raises(ValueError, match="key"):
        LocalStorage(tmp_path).put_bytes(key, b"x")


def test_put_tree_needs_a_directory(tmp_path):
    with pytest.raises(ValueError, match="directory"):
        LocalStorage(tmp_path / "s").put_tree("models/1", tmp_path / "missing")


def test_put_file_of_missing_path_names_it(tmp_path):
    with pytest.raises(ValueError, match="missing.bin"):
        LocalStorage(tmp_path / "s").put_file("a", Path(tmp_path / "missing.bin"))


def test_large_files_go_to_s3_in_parts(s3_endpoint, tmp_path):
    store = S3Storage(
        bucket=f"t-{os.urandom(6).hex()}",
        endpoint_url=s3_endpoint,
        access_key_id="testing",
        secret_access_key="testing",
        multipart_threshold_bytes=5 << 20,  # S3's smallest part size
    )
    store.ensure_bucket()
    data = os.urandom((5 << 20) * 2 + 1234)  # three parts
    src = tmp_path / "big.bin"
    src.write_bytes(data)
    stat = store.put_file("scans/1/bundle.zip", src, sha256=sha(data))
    assert stat.size_bytes == len(data) and stat.etag == sha(data)
    head = store.client.head_object(Bucket=store.bucket, Key="scans/1/bundle.zip")
    assert head["ETag"].strip('"').endswith("-3")  # really a 3-part upload
    assert (
        b"".join(store.open_range("scans/1/bundle.zip", 5 << 20, (5 << 20) + 10))
        == data[5 << 20 : (5 << 20) + 10]
    )
    with pytest.raises(ChecksumMismatch):
        store.put_file("scans/2/bundle.zip", src, sha256="1" * 64)
    assert not store.exists("scans/2/bundle.zip")


def test_multipart_threshold_below_s3_part_size_is_refused():
    with pytest.raises(ValueError, match="multipart_threshold_bytes"):
        S3Storage(bucket="bkt", client=object(), multipart_threshold_bytes=1 << 20)


def test_storage_from_settings(tmp_path, s3_endpoint):
    from backend.settings import Settings
    from backend.storage import storage_from_settings

    local = storage_from_settings(Settings(_env_file=None, environment="test", data_dir=tmp_path))
    assert isinstance(local, LocalStorage) and local.root == tmp_path / "storage"
    s3 = storage_from_settings(
        Settings(
            _env_file=None,
            environment="test",
            data_dir=tmp_path,
            storage_backend="s3",
            s3_endpoint_url=s3_endpoint,
            s3_bucket="from-settings",
            s3_access_key_id="testing",
            s3_secret_access_key="testing",
        )
    )
    assert isinstance(s3, S3Storage) and s3.bucket == "from-settings"
    s3.ensure_bucket()
    assert s3.put_bytes("k/v", b"1").size_bytes == 1
