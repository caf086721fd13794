"""Dependencies as types: the session, the settings, who is asking, and checked resources.

Routes never repeat 401/403/404 checks: they ask for ``CurrentUser``, ``AdminUser``,
``StaffUser``, ``ReadableTablet`` or ``EditableTablet`` and get either the object or the
right error.

- ``SessionDep``: a session committed when the route function returns (scope="function", so
  a failing commit is a 500 and never a success response), rolled back on errors.
- Authentication: ``Authorization: Bearer <api token>`` or the signed session cookie. A
  bad bearer token is a 401 (a rig agent must notice); a bad cookie is just anonymous, and
  so is a cookie whose session version is no longer the user's (logged out, password
  changed, account disabled).
- Tablet path parameter ``{tablet_id}``: our integer id or the P-number (``P001229``); a
  record the user may not read is a 404 (its existence is not revealed); a readable record
  the user may not edit is a 403.

For resources reached through a tablet (scans, uploads, jobs, models) use
:func:`require_readable_tablet` / :func:`require_editable_tablet` with the tablet id you
loaded, so the same rule applies everywhere.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Path, Request
from fastapi.security import APIKeyCookie, HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from backend import crud
from backend.db import session_scope
from backend.errors import ApiError, forbidden, not_found, unauthorized
from backend.security import SessionSigner
from backend.settings import Settings
from backend.tables import Role, Tablet, User

TABLET_REF_PATTERN = r"^(\d{1,18}|[PQX]\d{6})$"


async def get_settings(request: Request) -> Settings:
    # async: a plain attribute read must not cost a hop to the thread pool
    return request.app.state.settings


def get_session(request: Request) -> Iterator[Session]:
    with session_scope(request.app.state.sessionmaker) as session:
        yield session


SettingsDep = Annotated[Settings, Depends(get_settings)]
SessionDep = Annotated[Session, Depends(get_session, scope="function")]

# Declared for OpenAPI ("Authorize" in /docs); we read the values ourselves.
_bearer = HTTPBearer(auto_error=False, description="API token (hmr_...)")
_cookie = APIKeyCookie(name="hammurabi_session", auto_error=False, description="web session")


def get_optional_user(
    request: Request,
    session: SessionDep,
    bearer: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
    _cookie_value: Annotated[str | None, Depends(_cookie)],
) -> User | None:
    if request.headers.get("authorization"):
        if bearer is None or not bearer.credentials:
            raise unauthorized("malformed Authorization header: use 'Bearer <token>'")
        user = crud.user_for_token(session, secret=bearer.credentials)
        if user is None:
            raise unauthorized("invalid or revoked API token")
        return user
    settings: Settings = request.app.state.settings
    cookie = request.cookies.get(settings.session_cookie_name)
    if cookie:
        signer: SessionSigner = request.app.state.session_signer
        claim = signer.loads(cookie)
        if claim is not None:
            user = session.get(User, claim.user_id)
            if (
                user is not None
                and user.is_active
                and user.session_version == claim.session_version
            ):
                return user
    return None


OptionalUser = Annotated[User | None, Depends(get_optional_user)]


def get_current_user(user: OptionalUser) -> User:
    if user is None:
        raise unauthorized()
    return user


CurrentUser = Annotated[User, Depends(get_current_user)]


def get_admin_user(user: CurrentUser) -> User:
    if user.role != Role.admin:
        raise forbidden("admins only")
    return user


def get_staff_user(user: CurrentUser) -> User:
    if user.role not in (Role.admin, Role.staff):
        raise forbidden("staff or admins only")
    return user


AdminUser = Annotated[User, Depends(get_admin_user)]
StaffUser = Annotated[User, Depends(get_staff_user)]


# --- tablets --------------------------------------------------------------------------------


def load_tablet(session: Session, tablet_ref: str | int, user: User | None) -> Tablet | None:
    ref = str(tablet_ref)
    if ref.isdigit():
        return crud.get_tablet(session, tablet_id=int(ref))
    # A P-number may be held by several institutions: the one this user means (crud).
    return crud.get_tablet_by_p_number(session, p_number=ref, user=user)


def require_readable_tablet(
    session: Session, user: User | None, tablet_ref: str | int, *, where: str = "tablet_id"
) -> Tablet:
    """The tablet, or a 404 when it does not exist or ``user`` may not see it."""
    tablet = load_tablet(session, tablet_ref, user)
    if tablet is None or not crud.can_read_tablet(user, tablet):
        raise not_found(f"tablet {tablet_ref}", where=where)
    return tablet


def require_editable_tablet(
    session: Session, user: User | None, tablet_ref: str | int, *, where: str = "tablet_id"
) -> Tablet:
    """The tablet, or 404 (not visible), 401 (anonymous) or 403 (not theirs to edit)."""
    tablet = require_readable_tablet(session, user, tablet_ref, where=where)
    if user is None:
        raise unauthorized()
    if not crud.can_edit_tablet(user, tablet):
        raise forbidden(f"tablet {tablet_ref} belongs to another institution", where=where)
    return tablet


TabletRef = Annotated[
    str, Path(pattern=TABLET_REF_PATTERN, description="our id, or the P-number (P001229)")
]


def get_readable_tablet(tablet_id: TabletRef, session: SessionDep, user: OptionalUser) -> Tablet:
    return require_readable_tablet(session, user, tablet_id)


def get_editable_tablet(tablet_id: TabletRef, session: SessionDep, user: OptionalUser) -> Tablet:
    return require_editable_tablet(session, user, tablet_id)


ReadableTablet = Annotated[Tablet, Depends(get_readable_tablet)]
EditableTablet = Annotated[Tablet, Depends(get_editable_tablet)]

__all__ = [
    "AdminUser",
    "ApiError",
    "CurrentUser",
    "EditableTablet",
    "OptionalUser",
    "ReadableTablet",
    "SessionDep",
    "SettingsDep",
    "StaffUser",
    "load_tablet",
    "require_editable_tablet",
    "require_readable_tablet",
]
