"""The FastAPI application: ``create_app(settings)``.

API under ``/api/v1`` (Swagger UI at ``/docs``, ReDoc at ``/docs/redoc``, both offline:
backend.docs), errors as ``{detail, where}``, CORS for
reads, and the built frontend (``frontend/dist``) at ``/`` when it exists.

Routers: one per resource, listed in ``ROUTERS``. Modules listed in ``OPTIONAL_ROUTERS``
(uploads, scans, jobs, models, iiif: the uploads engineer's) are included when they exist;
each must expose ``router = APIRouter(prefix="/<resource>", ...)``.
"""

from __future__ import annotations

import importlib
import logging
from contextlib import asynccontextmanager

import anyio.to_thread
from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.staticfiles import StaticFiles

from backend import auth_first
from backend.api import annotations, auth, institutions, tablets, tokens, users
from backend.api.deps import SessionGate
from backend.body_limit import BodyLimit, upload_chunks_path
from backend.db import make_engine, make_sessionmaker, server_pool_size
from backend.docs import DOCS_PATH, install_docs
from backend.errors import install_error_handlers
from backend.headers import SecurityHeaders
from backend.search import FacetSnapshot, invalidate_on_tablet_writes
from backend.security import SessionSigner
from backend.settings import Settings, get_settings

log = logging.getLogger("backend")

ROUTERS = (
    auth.router,
    users.router,
    tokens.router,
    institutions.router,
    tablets.router,
    annotations.router,
)
OPTIONAL_ROUTERS = ("uploads", "scans", "jobs", "models", "iiif")


def _optional_routers() -> list:
    found = []
    for name in OPTIONAL_ROUTERS:
        module_name = f"backend.api.{name}"
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name != module_name:  # a real missing dependency must not be hidden
                raise
            continue
        found.append(module.router)
    return found


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings if settings is not None else get_settings()
    engine = make_engine(
        settings.resolved_database_url, pool_size=server_pool_size(settings.http_threads)
    )

    @asynccontextmanager
    async def lifespan(_app: FastAPI):
        # Threads, admitted sessions and connections come from one setting (backend.db).
        anyio.to_thread.current_default_thread_limiter().total_tokens = settings.http_threads
        yield
        engine.dispose()

    app = FastAPI(
        title="Digital Hammurabi library",
        version="1",
        docs_url=None,  # our own pages, from our own files: backend.docs
        redoc_url=None,
        openapi_url=f"{settings.api_prefix}/openapi.json",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.engine = engine
    app.state.sessionmaker = make_sessionmaker(engine)
    app.state.session_gate = SessionGate(settings.http_threads)
    app.state.session_signer = SessionSigner(
        settings.signing_secret, max_age_s=settings.session_max_age_s
    )
    app.state.facet_snapshot = FacetSnapshot()
    invalidate_on_tablet_writes(app.state.sessionmaker, app.state.facet_snapshot)
    install_error_handlers(app)
    auth_first.install(app)  # anonymous writes: 401 before any 422 about the body
    # Reads are open to any origin (catalogue data, models for other viewers); writes need a
    # token or a same-site cookie, so no credentials are allowed cross-origin.
    app.add_middleware(
        CORSMiddleware,
        allow_origins=settings.cors_allow_origins,
        allow_methods=["GET", "HEAD", "OPTIONS"],
        allow_headers=["Authorization", "Range", "Accept"],
        expose_headers=["Content-Range", "ETag", "X-Total-Count", "Content-Disposition"],
        allow_credentials=False,
    )
    app.add_middleware(
        BodyLimit,
        max_bytes=settings.request_max_body_bytes,
        exempt=upload_chunks_path(settings.api_prefix),
    )
    app.add_middleware(SecurityHeaders, settings=settings, docs_path=DOCS_PATH)
    install_docs(
        app,
        openapi_url=app.openapi_url,
        title=app.title,
        limits={(f"{settings.api_prefix}/tablets", "page_size"): settings.search_max_page_size},
    )

    @app.get(f"{settings.api_prefix}/health", tags=["health"])
    def health() -> dict[str, str]:
        return {"status": "ok"}

    for router in (*ROUTERS, *_optional_routers()):
        app.include_router(router, prefix=settings.api_prefix)

    dist = settings.resolved_frontend_dist
    if dist is not None and dist.is_dir():
        app.mount("/", StaticFiles(directory=dist, html=True), name="frontend")
    return app
