"""Errors as JSON ``{"detail": str, "where": str | null}`` everywhere.

Routes and dependencies raise :class:`ApiError` (or FastAPI's ``HTTPException``); validation
errors are reshaped to name the offending field in ``where`` and list every problem in
``problems: [{where, message}]``; unexpected exceptions become a 500 without a traceback.
"""

from __future__ import annotations

import logging
import re

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

log = logging.getLogger("backend")
HTTP_METHODS = {"get", "put", "post", "delete", "options", "head", "patch", "trace"}


class ApiError(Exception):
    """An error with an HTTP status, a message for people and the culprit (field, id...)."""

    def __init__(
        self,
        status_code: int,
        detail: str,
        *,
        where: str | None = None,
        problems: list[dict[str, str]] | None = None,
        headers: dict[str, str] | None = None,
    ):
        super().__init__(detail)
        self.status_code = status_code
        self.detail = detail
        self.where = where
        self.problems = problems
        self.headers = headers


def not_found(what: str, where: str | None = None) -> ApiError:
    return ApiError(404, f"{what} not found", where=where)


def forbidden(detail: str, where: str | None = None) -> ApiError:
    return ApiError(403, detail, where=where)


def unauthorized(detail: str = "authentication required") -> ApiError:
    return ApiError(401, detail, headers={"WWW-Authenticate": "Bearer"})


def conflict(detail: str, where: str | None = None) -> ApiError:
    return ApiError(409, detail, where=where)


def error_body(detail: str, where: str | None, problems: list | None = None) -> dict:
    body: dict = {"detail": detail, "where": where}
    if problems is not None:
        body["problems"] = problems
    return body


def _loc_to_where(loc: tuple | list) -> str:
    # ("body", "tablet", "height_mm") -> "body.tablet.height_mm"; ("query", "page") -> "query.page"
    return ".".join(str(part) for part in loc)


async def _api_error(_request: Request, exc: ApiError) -> JSONResponse:
    return JSONResponse(
        error_body(exc.detail, exc.where, exc.problems),
        status_code=exc.status_code,
        headers=exc.headers,
    )


def allowed_methods(request: Request) -> str:
    """Every method the OpenAPI document lists for this path (Starlette's 405 names only the
    first matching route's, e.g. ``GET`` for a path that also takes ``POST``)."""
    methods: set[str] = set()
    path = request.url.path
    for template, item in request.app.openapi().get("paths", {}).items():
        pattern = re.sub(r"\\\{[^/]+?\\\}", "[^/]+", re.escape(template))
        if re.fullmatch(pattern, path):
            methods.update(m.upper() for m in item if m in HTTP_METHODS)
    if "GET" in methods:
        methods.add("HEAD")
    return ", ".join(sorted(methods))


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
    headers = dict(getattr(exc, "headers", None) or {})
    if exc.status_code == 405:
        headers["Allow"] = allowed_methods(request) or headers.get("Allow", "")
    return JSONResponse(
        error_body(detail, None), status_code=exc.status_code, headers=headers or None
    )


async def _validation_error(_request: Request, exc: RequestValidationError) -> JSONResponse:
    problems = [
        {"where": _loc_to_where(err.get("loc", ())), "message": str(err.get("msg", "invalid"))}
        for err in exc.errors()
    ]
    first = problems[0] if problems else {"where": None, "message": "invalid request"}
    detail = f"{first['where']}: {first['message']}" if first["where"] else first["message"]
    return JSONResponse(error_body(detail, first["where"], problems), status_code=422)


async def _unexpected_error(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return JSONResponse(error_body("internal server error", None), status_code=500)


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(ApiError, _api_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(Exception, _unexpected_error)
