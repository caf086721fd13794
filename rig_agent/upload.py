"""Resumable, chunked upload of a scan's bundle to the library (``/api/v1/uploads``).

Protocol (docs/architecture.md, docs/uploads.md): ``POST /uploads`` creates an upload
and says the chunk size; ``PUT /uploads/{id}/chunks?offset=N`` stores a chunk (any
order, repeatable); ``GET /uploads/{id}`` gives the received ``ranges`` (half-open
``[start, end)``); ``POST /uploads/{id}/complete {sha256}`` checks the whole file and
makes the scan and its reconstruction job.

The upload id, the bundle's sha256 and the ranges the server confirmed are kept in
the scan's ``state.json``, so a restarted agent continues where it stopped. Network
errors and 5xx answers are retried with exponential backoff; nothing is removed from
the spool here — only a later ``rig-agent clean`` deletes scans the library confirmed.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx

from rig_agent.spool import SpoolScan

RETRY_STATUS = {500, 502, 503, 504, 507}
MAX_BACKOFF_S = 30.0


class UploadError(RuntimeError):
    """The library refused the upload or could not be reached; the message says why."""


def sha256_file(path: Path, *, block: int = 1 << 20) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(block):
            digest.update(chunk)
    return digest.hexdigest()


def missing_ranges(ranges: list[list[int]], size: int) -> list[tuple[int, int]]:
    """The gaps of sorted half-open ``ranges`` in ``[0, size)``."""
    gaps, cursor = [], 0
    for start, end in sorted(ranges):
        if start > cursor:
            gaps.append((cursor, start))
        cursor = max(cursor, end)
    if cursor < size:
        gaps.append((cursor, size))
    return gaps


def _detail(response: httpx.Response) -> str:
    try:
        body = response.json()
    except ValueError:
        return response.text[:300] or response.reason_phrase
    if not isinstance(body, dict):
        return str(body)[:300]
    text = str(body.get("detail", body))
    if body.get("where"):
        text += f" (at {body['where']})"
    for problem in body.get("problems") or []:
        text += f"\n  - {problem.get('where')}: {problem.get('message')}"
    return text


class LibraryClient:
    """HTTP client of the library's API with an API token, retrying transient failures."""

    def __init__(
        self,
        base_url: str,
        token: str,
        *,
        retries: int = 8,
        backoff_s: float = 0.5,
        timeout_s: float = 60.0,
        transport: httpx.BaseTransport | None = None,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if not token:
            raise UploadError(
                "no API token: set `api_token` in the config file or RIG_AGENT_API_TOKEN "
                "(create one in the library under your account's tokens)"
            )
        self.base_url = base_url.rstrip("/")
        self.retries, self.backoff_s, self.sleep = retries, backoff_s, sleep
        self.http = httpx.Client(
            base_url=self.base_url + "/api/v1",
            headers={"Authorization": f"Bearer {token}"},
            timeout=timeout_s,
            transport=transport,
        )

    def close(self) -> None:
        self.http.close()

    def request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        """Send with retries; returns 2xx/4xx responses, raises UploadError when retries run out."""
        attempt = 0
        while True:
            try:
                response = self.http.request(method, path, **kwargs)
                if response.status_code not in RETRY_STATUS:
                    return response
                problem = f"the library answered {response.status_code}: {_detail(response)}"
            except httpx.TransportError as exc:
                problem = (
                    f"cannot reach the library at {self.base_url} ({exc.__class__.__name__}: {exc})"
                )
            if attempt >= self.retries:
                raise UploadError(
                    f"{problem}; gave up after {attempt + 1} attempts. The scan stays in the spool: "
                    "run `rig-agent upload` again when the network is back"
                )
            self.sleep(min(MAX_BACKOFF_S, self.backoff_s * 2**attempt))
            attempt += 1

    def expect(self, response: httpx.Response, *codes: int, what: str) -> Any:
        if response.status_code not in codes:
            raise UploadError(f"{what} failed: {response.status_code} {_detail(response)}")
        return response.json() if response.content else None

    def find_tablet(self, designation: str) -> int:
        """The library id of the tablet whose designation or P-number is ``designation``."""
        response = self.request("GET", "/tablets", params={"q": designation, "page_size": 50})
        body = self.expect(response, 200, what=f"looking up tablet {designation!r}")
        matches = [
            t
            for t in body.get("items", [])
            if designation in (t.get("designation"), t.get("p_number"))
        ]
        if len(matches) != 1:
            raise UploadError(
                f"the library has {'no' if not matches else 'several'} tablet(s) with designation "
                f"{designation!r}; create it in the catalogue or pass --tablet-id"
            )
        return int(matches[0]["id"])


def upload_scan(
    scan: SpoolScan,
    client: LibraryClient,
    *,
    tablet_id: int,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Upload ``scan``'s bundle.zip, resuming a previous attempt; returns ``{scan, job}``."""
    try:
        return _upload(scan, client, tablet_id=tablet_id, progress=progress)
    except _UploadGone:
        # The server lost or expired the upload: start a new one (the bytes are still here).
        scan.update_state(upload=None)
        return _upload(scan, client, tablet_id=tablet_id, progress=progress)


class _UploadGone(Exception):
    pass


def _upload(
    scan: SpoolScan,
    client: LibraryClient,
    *,
    tablet_id: int,
    progress: Callable[[int, int], None] | None,
) -> dict[str, Any]:
    bundle = scan.path / (scan.state.get("bundle") or "bundle.zip")
    if not bundle.is_file():
        raise UploadError(f"scan {scan.id[:8]} has no bundle yet; run `rig-agent scan`/`resume`")
    size, digest = bundle.stat().st_size, sha256_file(bundle)
    record = dict(scan.state.get("upload") or {})
    same = (record.get("size_bytes"), record.get("sha256"), record.get("tablet_id"))
    if same != (size, digest, tablet_id):  # another file or tablet: never mix bytes
        record = {"size_bytes": size, "tablet_id": tablet_id, "sha256": digest}
    upload = _resume_or_create(scan, client, record, bundle.name)
    ranges = upload["ranges"]
    chunk = int(upload.get("chunk_size") or 8 << 20)

    def confirm(ranges_now: list[list[int]]) -> None:
        record["ranges"] = ranges_now
        scan.update_state(upload=record)
        if progress:
            progress(sum(end - start for start, end in ranges_now), size)

    confirm(ranges)
    with open(bundle, "rb") as handle:
        for gap_start, gap_end in missing_ranges(ranges, size):
            for offset in range(gap_start, gap_end, chunk):
                handle.seek(offset)
                data = handle.read(min(chunk, gap_end - offset))
                response = client.request(
                    "PUT",
                    f"/uploads/{record['id']}/chunks",
                    params={"offset": offset},
                    content=data,
                )
                if response.status_code in (404, 409, 410):
                    raise _UploadGone
                body = client.expect(response, 200, 201, 204, what=f"sending bytes {offset}…")
                if isinstance(body, dict) and "ranges" in body:
                    confirm(body["ranges"])
                else:
                    confirm(_merge(record.get("ranges", []), offset, offset + len(data)))
    response = client.request(
        "POST", f"/uploads/{record['id']}/complete", json={"sha256": record["sha256"]}
    )
    if response.status_code == 422:
        raise UploadError(f"the library refused scan {scan.id[:8]}: {_detail(response)}")
    result = client.expect(response, 200, 201, what="completing the upload")
    scan.update_state(
        phase="uploaded",
        upload=record | {"confirmed_sha256": record["sha256"]},
        library={"scan_id": result["scan"]["id"], "job_id": result["job"]["id"]},
    )
    return result


def _resume_or_create(
    scan: SpoolScan, client: LibraryClient, record: dict[str, Any], filename: str
) -> dict[str, Any]:
    if record.get("id"):
        response = client.request("GET", f"/uploads/{record['id']}")
        if response.status_code == 200:
            upload = response.json()
            if upload.get("size_bytes") == record["size_bytes"]:
                return upload
        elif response.status_code not in (404, 409, 410):
            client.expect(response, 200, what="checking the earlier upload")
    response = client.request(
        "POST",
        "/uploads",
        json={
            "tablet_id": record["tablet_id"],
            "filename": filename,
            "size_bytes": record["size_bytes"],
        },
    )
    upload = client.expect(response, 200, 201, what="starting the upload")
    record.update(id=upload["id"], ranges=[])
    scan.update_state(upload=record)
    return upload


def _merge(ranges: list[list[int]], start: int, end: int) -> list[list[int]]:
    merged: list[list[int]] = []
    for lo, hi in sorted([*ranges, [start, end]]):
        if merged and lo <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], hi)
        else:
            merged.append([lo, hi])
    return merged
