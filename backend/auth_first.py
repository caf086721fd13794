"""Authentication before validation: an anonymous write is a 401, whatever its body.

FastAPI parses the JSON body before it runs any dependency, and validates the body in the
same pass as dependencies that only *read* the user (``OptionalUser``, checked inside the
route): a write by nobody answered 422 about the body's shape, before saying that nobody
may write here at all. The validation-error handler therefore asks first whether the
route needs a user (it depends on ``get_optional_user``, the one source of the caller) and
whether the request names one; if not, the answer is the 401 the route would have given.

"Names one": an ``Authorization`` header (its token is checked by the route as usual) or
a session cookie with a valid signature. A validly signed cookie of a since-ended session
still gets the 422: telling the two apart needs the database, and such a caller did sign
in once.
"""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute

from backend.api.deps import get_optional_user
from backend.errors import _api_error, _validation_error, unauthorized

WRITE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})


def _depends_on(dependant, call) -> bool:
    return any(d.call is call or _depends_on(d, call) for d in dependant.dependencies)


def route_needs_user(route: object) -> bool:
    """Whether ``route`` reads who is asking (so anonymous writes to it are refused)."""
    return isinstance(route, APIRoute) and _depends_on(route.dependant, get_optional_user)


def names_a_caller(request: Request) -> bool:
    """Whether the request carries credentials: a bearer header or a validly signed cookie."""
    if request.headers.get("authorization"):
        return True
    cookie = request.cookies.get(request.app.state.settings.session_cookie_name)
    return bool(cookie) and request.app.state.session_signer.loads(cookie) is not None


async def _validation_error_after_auth(request: Request, exc: RequestValidationError):
    if (
        request.method in WRITE_METHODS
        and route_needs_user(request.scope.get("route"))
        and not names_a_caller(request)
    ):
        return await _api_error(request, unauthorized())
    return await _validation_error(request, exc)


def install(app: FastAPI) -> None:
    """Replace the validation-error handler (backend.errors) with the auth-first one."""
    app.add_exception_handler(RequestValidationError, _validation_error_after_auth)
