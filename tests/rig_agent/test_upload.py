"""Resumable upload: against a fake library in a subprocess (killed with SIGKILL) and mocks."""

from __future__ import annotations

import hashlib
import os

import httpx
import pytest

from rig_agent.spool import Spool
from rig_agent.upload import LibraryClient, UploadError, missing_ranges, upload_scan

TOKEN = "rig-test-token"
CHUNK = 64 * 1024
SIZE = 20 * CHUNK + 1234  # not a multiple of the chunk size


@pytest.fixture
def scan(tmp_path):
    scan = Spool(tmp_path / "spool").create(kind="scan", shots=[], meta={"face": "obverse"})
    (scan.path / "bundle.zip").write_bytes(os.urandom(SIZE))
    scan.update_state(phase="bundled", bundle="bundle.zip")
    return scan


def local_sha(scan) -> str:
    return hashlib.sha256((scan.path / "bundle.zip").read_bytes()).hexdigest()


def client(url: str, **kwargs) -> LibraryClient:
    options = {"retries": 12, "backoff_s": 0.05, "timeout_s": 5.0} | kwargs
    return LibraryClient(url, TOKEN, **options)


def test_upload_completes_with_the_same_checksum(library, scan):
    c = client(library.url)
    result = upload_scan(scan, c, tablet_id=c.find_tablet("P123456"))
    c.close()
    assert result == {"scan": {"id": 1}, "job": {"id": 1}}
    assert library.stored_sha256() == local_sha(scan)
    state = scan.state
    assert state["phase"] == "uploaded" and state["upload"]["confirmed_sha256"] == local_sha(scan)
    assert state["upload"]["ranges"] == [[0, SIZE]]
    assert (scan.path / "bundle.zip").exists()  # the spool keeps it until `clean`


class AgentCrash(Exception):
    pass


def test_upload_resumes_after_the_agent_restarts(library, scan):
    calls = []

    def crash_after_three_chunks(done: int, total: int) -> None:
        calls.append(done)
        if len(calls) == 4:
            raise AgentCrash

    c = client(library.url)
    with pytest.raises(AgentCrash):
        upload_scan(scan, c, tablet_id=7, progress=crash_after_three_chunks)
    c.close()
    assert scan.state["upload"]["ranges"] == [[0, 3 * CHUNK]]
    c = client(library.url)  # a new agent process: only the spool's state carries over
    upload_scan(scan, c, tablet_id=7)
    c.close()
    assert library.received_bytes() == SIZE  # no byte sent twice
    assert library.stored_sha256() == local_sha(scan)


def mock_client(handler, sleeps, **kwargs) -> LibraryClient:
    options = {
        "retries": 3,
        "backoff_s": 0.5,
        "transport": httpx.MockTransport(handler),
        "sleep": sleeps.append,
    } | kwargs
    return LibraryClient("http://library.test", TOKEN, **options)


def test_5xx_and_network_errors_are_retried_with_exponential_backoff():
    answers = iter([httpx.ConnectError("refused"), 503, 502, 200])
    sleeps: list[float] = []

    def handler(request):
        answer = next(answers)
        if isinstance(answer, Exception):
            raise answer
        return httpx.Response(answer, json={"items": [{"id": 3, "designation": "P1"}]})

    assert mock_client(handler, sleeps).find_tablet("P1") == 3
    assert sleeps == [0.5, 1.0, 2.0]


def test_giving_up_says_the_scan_is_safe():
    sleeps: list[float] = []
    c = mock_client(lambda request: httpx.Response(503, json={"detail": "down"}), sleeps)
    with pytest.raises(UploadError, match="stays in the spool") as info:
        c.find_tablet("P1")
    assert "503" in str(info.value) and len(sleeps) == 3


def test_an_invalid_bundle_lists_every_problem(scan):
    def handler(request):
        if request.url.path.endswith("/complete"):
            problems = [
                {"where": "frames[3].file", "message": "missing"},
                {"where": "camera.width", "message": "must be > 0"},
            ]
            return httpx.Response(
                422, json={"detail": "invalid bundle", "where": None, "problems": problems}
            )
        if request.method == "POST":
            return httpx.Response(201, json={"id": "u1", "ranges": [], "chunk_size": 1 << 30})
        return httpx.Response(200, json={"ranges": [[0, SIZE]]})

    with pytest.raises(UploadError) as info:
        upload_scan(scan, mock_client(handler, []), tablet_id=1)
    assert "frames[3].file: missing" in str(info.value) and "camera.width" in str(info.value)
    assert scan.state["phase"] == "bundled"


def test_missing_token_and_missing_tablet():
    with pytest.raises(UploadError, match="RIG_AGENT_API_TOKEN"):
        LibraryClient("http://x", "")
    c = mock_client(lambda r: httpx.Response(200, json={"items": []}), [])
    with pytest.raises(UploadError, match="no tablet"):
        c.find_tablet("P404")


def test_missing_ranges():
    assert missing_ranges([], 10) == [(0, 10)]
    assert missing_ranges([[2, 4], [6, 10]], 12) == [(0, 2), (4, 6), (10, 12)]
    assert missing_ranges([[0, 12]], 12) == []


def test_a_changed_bundle_starts_a_new_upload(library, scan):
    def crash(done: int, total: int) -> None:
        if done >= 2 * CHUNK:
            raise AgentCrash

    c = client(library.url)
    with pytest.raises(AgentCrash):
        upload_scan(scan, c, tablet_id=7, progress=crash)
    first_id = scan.state["upload"]["id"]
    (scan.path / "bundle.zip").write_bytes(os.urandom(SIZE))  # same size, other bytes
    upload_scan(scan, c, tablet_id=7)
    c.close()
    assert scan.state["upload"]["id"] != first_id
    assert scan.state["upload"]["confirmed_sha256"] == local_sha(scan)
