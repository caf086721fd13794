"""A small stand-in for the library's upload API, run as a subprocess by the upload tests.

State lives in ``--data`` (one JSON file and one part file per upload, written before
answering), so the server can be killed with SIGKILL and restarted like the real one.
Usage: python fake_library.py --port N --data DIR --token T [--chunk-size BYTES]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import uuid
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlsplit


def merge(ranges, start, end):
    out = []
    for lo, hi in sorted([*ranges, [start, end]]):
        if out and lo <= out[-1][1]:
            out[-1][1] = max(out[-1][1], hi)
        else:
            out.append([lo, hi])
    return out


def make_handler(data: Path, token: str, chunk_size: int):
    class Handler(BaseHTTPRequestHandler):
        def log_message(self, *args):
            pass

        def reply(self, code, body):
            raw = json.dumps(body).encode()
            self.send_response(code)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(raw)))
            self.end_headers()
            self.wfile.write(raw)

        def authorised(self):
            if self.headers.get("Authorization") != f"Bearer {token}":
                self.reply(401, {"detail": "invalid token", "where": "authorization"})
                return False
            return True

        def body(self):
            return self.rfile.read(int(self.headers.get("Content-Length") or 0))

        def state(self, upload_id):
            path = data / f"{upload_id}.json"
            return json.loads(path.read_text()) if path.exists() else None

        def save(self, upload):
            tmp = data / f".{upload['id']}.tmp"
            tmp.write_text(json.dumps(upload))
            os.replace(tmp, data / f"{upload['id']}.json")

        def out(self, upload):
            received = sum(b - a for a, b in upload["ranges"])
            return {**upload, "received_bytes": received, "chunk_size": chunk_size}

        def do_GET(self):
            if not self.authorised():
                return
            url = urlsplit(self.path)
            if url.path == "/api/v1/tablets":
                q = parse_qs(url.query).get("q", [""])[0]
                items = [{"id": 7, "designation": "P123456"}] if q == "P123456" else []
                return self.reply(200, {"items": items, "total": len(items)})
            match = re.fullmatch(r"/api/v1/uploads/([0-9a-f-]+)", url.path)
            upload = match and self.state(match[1])
            if not upload:
                return self.reply(404, {"detail": "no such upload", "where": "upload_id"})
            return self.reply(200, self.out(upload))

        def do_POST(self):
            if not self.authorised():
                return
            url = urlsplit(self.path)
            body = json.loads(self.body() or b"{}")
            if url.path == "/api/v1/uploads":
                upload = {
                    "id": str(uuid.uuid4()),
                    "tablet_id": body["tablet_id"],
                    "filename": body["filename"],
                    "size_bytes": body["size_bytes"],
                    "ranges": [],
                    "state": "open",
                }
                with open(data / f"{upload['id']}.part", "wb") as handle:
                    handle.truncate(body["size_bytes"])
                self.save(upload)
                return self.reply(201, self.out(upload))
            match = re.fullmatch(r"/api/v1/uploads/([0-9a-f-]+)/complete", url.path)
            upload = match and self.state(match[1])
            if not upload:
                return self.reply(404, {"detail": "no such upload", "where": "upload_id"})
            if upload["state"] == "complete":
                return self.reply(200, {"scan": {"id": 1}, "job": {"id": 1}})
            if upload["ranges"] != [[0, upload["size_bytes"]]]:
                return self.reply(409, {"detail": "bytes missing", "where": "ranges"})
            digest = hashlib.sha256((data / f"{upload['id']}.part").read_bytes()).hexdigest()
            if digest != body.get("sha256"):
                return self.reply(
                    422, {"detail": f"sha256 mismatch: got {digest}", "where": "sha256"}
                )
            upload["state"] = "complete"
            self.save(upload)
            return self.reply(201, {"scan": {"id": 1}, "job": {"id": 1}})

        def do_PUT(self):
            if not self.authorised():
                return
            url = urlsplit(self.path)
            match = re.fullmatch(r"/api/v1/uploads/([0-9a-f-]+)/chunks", url.path)
            upload = match and self.state(match[1])
            if not upload:
                return self.reply(404, {"detail": "no such upload", "where": "upload_id"})
            offset = int(parse_qs(url.query)["offset"][0])
            chunk = self.body()
            fd = os.open(data / f"{upload['id']}.part", os.O_WRONLY)
            try:
                os.pwrite(fd, chunk, offset)
                os.fsync(fd)
            finally:
                os.close(fd)
            upload["ranges"] = merge(upload["ranges"], offset, offset + len(chunk))
            self.save(upload)
            with open(data / "received.log", "a") as log:
                log.write(f"{offset} {len(chunk)}\n")
            return self.reply(200, self.out(upload))

    return Handler


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--token", required=True)
    parser.add_argument("--chunk-size", type=int, default=65536)
    args = parser.parse_args()
    args.data.mkdir(parents=True, exist_ok=True)
    server = ThreadingHTTPServer(
        ("127.0.0.1", args.port), make_handler(args.data, args.token, args.chunk_size)
    )
    server.allow_reuse_address = True
    print("ready", flush=True)
    server.serve_forever()


if __name__ == "__main__":
    main()
