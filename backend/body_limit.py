"""A cap on request bodies (a pure ASGI middleware), so that nobody, signed in or not, can
make the service hold an arbitrary body in memory.

Routes parse their JSON body before any dependency runs, authentication included: without a
cap an anonymous ``POST /tablets`` of 400 MB was read and parsed in full (about 0.8 GB of
server memory, minutes of CPU) before its 401. Bodies larger than ``max_bytes`` are refused
with 413 and the usual ``{detail, where}`` JSON: at once when ``Content-Length`` says so,
else (chunked transfer) as soon as the bytes received pass the cap, without reading more.

The routes that stream a body to disk as it arrives (upload chunks, checked against the
upload's own size, quota and free disk in backend.api.uploads) are exempt.
"""

from __future__ import annotations

import re

from starlette.datastructures import Headers
from starlette.exceptions import HTTPException
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from backend.errors import error_body


def too_large_detail(max_bytes: int) -> str:
    return f"the request body is larger than {max_bytes} bytes, the most this service accepts"


class BodyLimit:
    """Refuses request bodies over ``max_bytes`` (413), except on paths ``exempt`` matches."""

    def __init__(self, app: ASGIApp, *, max_bytes: int, exempt: re.Pattern[str]):
        self.app = app
        self.max_bytes = max_bytes
        self.exempt = exempt

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or self.exempt.fullmatch(scope["path"]):
            await self.app(scope, receive, send)
            return
        detail = too_large_detail(self.max_bytes)
        declared = Headers(scope=scope).get("content-length", "").strip()
        if declared.isdigit() and int(declared) > self.max_bytes:
            response = JSONResponse(error_body(detail, "body"), status_code=413)
            await response(scope, receive, send)
            return
        received = 0

        async def receive_capped() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    # Raised inside the route's body parsing: FastAPI re-raises an
                    # HTTPException, and backend.errors answers it as {detail, where}.
                    raise HTTPException(413, detail)
            return message

        await self.app(scope, receive_capped, send)


def upload_chunks_path(api_prefix: str) -> re.Pattern[str]:
    """The path of ``PUT /uploads/{id}/chunks`` (bodies of up to a chunk, streamed to disk)."""
    return re.compile(re.escape(api_prefix) + r"/uploads/[^/]+/chunks")
