"""Security headers on every response (a pure ASGI middleware, so streamed bodies such as
model downloads pass through untouched).

- ``X-Content-Type-Options: nosniff``: an uploaded file is never run as a script or page.
- ``Content-Security-Policy``: only this origin's scripts and styles; images and fetches may
  also be ``blob:``/``data:`` (three.js' GLTFLoader turns a GLB's embedded textures into
  blob URLs and fetches them, and ``createImageBitmap`` reads albedo PNGs from blobs);
  ``frame-ancestors 'none'`` (with ``X-Frame-Options: DENY`` for old browsers) stops
  click-jacking. The API pages (``/docs``, backend.docs) need inline styles (ReDoc) and a
  blob: worker, so they alone get a policy allowing exactly that.
- ``Referrer-Policy: same-origin``: links to other sites do not leak tablet URLs.
- ``Strict-Transport-Security`` only when the request came over TLS or the public base URL
  is https: sent over plain HTTP it would be ignored at best and lock out a dev server at
  worst.

A header a route set itself is kept.
"""

from __future__ import annotations

from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from backend.settings import Settings

CSP = "; ".join(
    (
        "default-src 'self'",
        # 'wasm-unsafe-eval': compiling WebAssembly only (the meshoptimizer decoder of streamed
        # tiles, frontend/src/viewer/tiles.js); JavaScript eval stays forbidden.
        "script-src 'self' 'wasm-unsafe-eval'",
        "style-src 'self'",
        "img-src 'self' data: blob:",
        "connect-src 'self' data: blob:",
        "worker-src 'self' blob:",
        "font-src 'self'",
        "object-src 'none'",
        "base-uri 'self'",
        "form-action 'self'",
        "frame-ancestors 'none'",
    )
)
# Swagger UI and ReDoc from our own files (backend.docs): no CDN, no inline script; ReDoc
# styles with inline <style> elements and parses the schema in a blob: worker.
DOCS_CSP = "; ".join(
    (
        "default-src 'self'",
        # 'wasm-unsafe-eval': compiling WebAssembly only (the meshoptimizer decoder of streamed
        # tiles, frontend/src/viewer/tiles.js); JavaScript eval stays forbidden.
        "script-src 'self' 'wasm-unsafe-eval'",
        "style-src 'self' 'unsafe-inline'",
        "img-src 'self' data:",
        "connect-src 'self'",
        "worker-src 'self' blob:",
        "font-src 'self' data:",
        "object-src 'none'",
        "base-uri 'self'",
        "frame-ancestors 'none'",
    )
)
HSTS = "max-age=31536000; includeSubDomains"


class SecurityHeaders:
    """Adds the headers above to every HTTP response of ``app``."""

    def __init__(self, app: ASGIApp, *, settings: Settings, docs_path: str = "/docs"):
        self.app = app
        self.docs_path = docs_path
        self.always_tls = public_url_is_https(settings)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        extra = self.headers_for(scope)

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in extra:
                    if name not in headers:
                        headers.append(name, value)
            await send(message)

        await self.app(scope, receive, send_with_headers)

    def headers_for(self, scope: Scope) -> list[tuple[str, str]]:
        is_docs = scope["path"] == self.docs_path or scope["path"].startswith(self.docs_path + "/")
        headers = [
            ("X-Content-Type-Options", "nosniff"),
            ("Content-Security-Policy", DOCS_CSP if is_docs else CSP),
            ("X-Frame-Options", "DENY"),
            ("Referrer-Policy", "same-origin"),
        ]
        if self.always_tls or scope.get("scheme") == "https":
            headers.append(("Strict-Transport-Security", HSTS))
        return headers


def public_url_is_https(settings: Settings) -> bool:
    return settings.resolved_public_url.startswith("https://")
