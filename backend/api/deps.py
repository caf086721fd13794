"""Dependencies as types: the session, the settings, who is asking, and checked resources.

Routes never repeat 401/403/404 checks: they ask for ``CurrentUser``, ``AdminUser``,
``StaffUser``, ``ReadableTablet`` or ``EditableTablet`` and get either the object or the
right error.

- ``SessionDep``: a session committed when the route function returns (scope="function", so
  a failing commit is a 500 and never a success response), rolled back on errors. At most
  ``http_threads`` requests hold one at once (:class:`SessionGate`; why: backend.db), and it
  is ended in a thread outside the pool's limit, so a request never holds a connection or
  a lock while it waits for a pool thread that only it could free.
- Ids in paths, queries and bodies are ``RowId`` (1 … 2**31-1, backend.db): out of range
  is a 422 naming the parameter, on SQLite and PostgreSQL alike.
- Authentication: ``Authorization: Bearer <api token>`` or the signed session cookie. A
  bad bearer token is a 401 (a rig agent must notice); a bad cookie is just anonymous, and
  so is a cookie whose session version is no longer the user's (logged out, password
  changed, account disabled). Authentication ends its own short transaction (the token's
  ``last_used_at`` write included), so that write lock is never held while the route waits
  for its thread.
- Tablet path parameter ``{tablet_id}``: our integer id or the P-number (``P001229``; the
  letter in either case, as scholars type it); a record the user may not read is a 404 (its
  existence is not revealed); a readable record the user may not edit is a 403.

For resources reached through a tablet (scans, uploads, jobs, models) use
:func:`require_readable_tablet` / :func:`require_editable_tablet` with the tablet id you
loaded, so the same rule applies everywhere.
"""

from __future__ import annotations

import asyncio
import weakref
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Annotated

import anyio
from fastapi import Depends, Path, Request
from fastapi.security import APIKeyCookie, HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from backend import crud
from backend.db import MAX_ID, RowId
from backend.errors import ApiError, forbidden, not_found, unauthorized
from backend.security import SessionSigner
from backend.settings import Settings
from backend.tables import Institution, Role, Tablet, User

# ASCII digits (\d takes any Unicode digit); the P-number's letter in either case, as
# scholars type it ("p451806"), read as the upper case it is stored in (load_tablet).
TABLET_REF_PATTERN = r"^([0-9]{1,18}|[PQXpqx][0-9]{6})$"


async def get_settings(request: Request) -> Settings:
    # async: a plain attribute read must not cost a hop to the thread pool
    return request.app.state.settings


class Admission:
    """One request's place in a :class:`SessionGate`; :meth:`release` gives it back early."""

    def __init__(self, semaphore: anyio.Semaphore):
        self._semaphore = semaphore
        self.held = True

    def release(self) -> None:
        if self.held:
            self.held = False
            self._semaphore.release()


class SessionGate:
    """Admits at most ``slots`` requests holding a session at once (see the module docstring).

    One :class:`anyio.Semaphore` per event loop (a TestClient may run several loops).
    """

    def __init__(self, slots: int):
        if slots < 1:
            raise ValueError(f"slots: need at least 1, got {slots}")
        self.slots = slots
        self._semaphores: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

    @asynccontextmanager
    async def admitted(self) -> AsyncIterator[Admission]:
        loop = asyncio.get_running_loop()
        semaphore = self._semaphores.get(loop)
        if semaphore is None:
            semaphore = self._semaphores[loop] = anyio.Semaphore(self.slots)
        await semaphore.acquire()
        admission = Admission(semaphore)
        try:
            yield admission
        finally:
            admission.release()


async def run_unlimited(func, *args):
    """``func(*args)`` in a worker thread outside the pool's capacity limit.

    For ending a session that holds a connection (commit, rollback, close): waiting for a
    thread of the shared pool while holding it is the deadlock this module avoids.
    FastAPI ends sync ``yield`` dependencies the same way.
    """
    return await anyio.to_thread.run_sync(func, *args, limiter=anyio.CapacityLimiter(1))


def _end_session(session: Session, ok: bool) -> None:
    try:
        if ok:
            session.commit()
        else:
            session.rollback()
    finally:
        session.close()


async def get_session(request: Request) -> AsyncIterator[Session]:
    """The request's session: admitted by the app's :class:`SessionGate`, committed when the
    route returns and rolled back when it raises (as ``backend.db.session_scope``)."""
    async with request.app.state.session_gate.admitted() as admission:
        # Making a session does no I/O: no thread needed. Ending one does.
        session = request.app.state.sessionmaker()
        session.info["admission"] = admission
        try:
            yield session
        except BaseException:
            await run_unlimited(_end_session, session, False)
            raise
        await run_unlimited(_end_session, session, True)


async def release_session(session: Session) -> None:
    """Commit the request's ``session`` now and give its place in the gate back.

    For a route that is done with the database before a long wait (a request body trickling
    in) so that it does not keep other requests from the database meanwhile. The session
    must not be used again (objects loaded from it stay readable); for more database work,
    enter ``request.app.state.session_gate.admitted()`` again and use a new session.
    """
    await run_unlimited(session.commit)
    session.info["admission"].release()


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
        # Ends the transaction that may have taken the write lock (last_used_at) in this
        # very hop, before the route waits for its own thread.
        session.commit()
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


# The role checks below only read loaded columns: async, so they cost no hop to the pool.


async def get_current_user(user: OptionalUser) -> User:
    if user is None:
        raise unauthorized()
    return user


CurrentUser = Annotated[User, Depends(get_current_user)]


async def get_admin_user(user: CurrentUser) -> User:
    if user.role != Role.admin:
        raise forbidden("admins only")
    return user


async def get_staff_user(user: CurrentUser) -> User:
    if user.role not in (Role.admin, Role.staff):
        raise forbidden("staff or admins only")
    return user


AdminUser = Annotated[User, Depends(get_admin_user)]
StaffUser = Annotated[User, Depends(get_staff_user)]


# --- tablets --------------------------------------------------------------------------------


def require_institution(session: Session, institution_id: int | None) -> None:
    """A 422 naming ``body.institution_id`` when that institution does not exist (rather
    than the database's foreign-key error, a 500)."""
    if institution_id is not None and session.get(Institution, institution_id) is None:
        raise ApiError(422, f"no institution {institution_id}", where="body.institution_id")


def load_tablet(session: Session, tablet_ref: str | int, user: User | None) -> Tablet | None:
    ref = str(tablet_ref).upper()
    if ref.isdigit():
        tablet_id = int(ref)
        # Past MAX_ID no row can exist (and PostgreSQL's INTEGER would overflow).
        return crud.get_tablet(session, tablet_id=tablet_id) if tablet_id <= MAX_ID else None
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
    str, Path(pattern=TABLET_REF_PATTERN, description="our id, or the P-number (P001229; any case)")
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
    "RowId",
    "SessionDep",
    "SettingsDep",
    "StaffUser",
    "load_tablet",
    "release_session",
    "require_editable_tablet",
    "require_institution",
    "require_readable_tablet",
]
