"""Web sessions: password login sets a signed, HttpOnly, SameSite=Lax cookie.

The cookie carries the user's session version; logout bumps it, so a copy of the cookie
kept by anyone stops working at once (and so do the user's other browsers' sessions).
"""

from __future__ import annotations

import threading

import anyio
from anyio import to_thread
from fastapi import APIRouter, Request, Response

from backend import crud, security
from backend.api.deps import CurrentUser, OptionalUser, SessionDep, SettingsDep
from backend.db import session_scope
from backend.errors import ApiError
from backend.schemas import LoginIn, PasswordChangeIn, SessionOut, UserOut
from backend.settings import Settings
from backend.tables import User

router = APIRouter(prefix="/auth", tags=["auth"])
_state_lock = threading.Lock()


def login_limiter(request: Request) -> security.LoginLimiter:
    """The app's limiter, made on first use from its settings (a test may set its own in
    ``app.state.login_limiter`` first); also sizes the process's argon2 slots."""
    state = request.app.state
    with _state_lock:
        if getattr(state, "login_limiter", None) is None:
            settings: Settings = state.settings
            security.set_hash_concurrency(settings.password_hash_concurrency)
            state.login_limiter = security.LoginLimiter(
                per_account=settings.login_max_attempts_per_account,
                per_address=settings.login_max_attempts_per_address,
                window_s=settings.login_window_s,
            )
        return state.login_limiter


def _login_slots(request: Request) -> anyio.Semaphore:
    """Logins wait for a hash slot here, on the event loop, holding no worker thread: 40
    waiting logins must not take the 40 threads every synchronous route needs."""
    state = request.app.state
    with _state_lock:
        if getattr(state, "login_slots", None) is None:
            state.login_slots = anyio.Semaphore(state.settings.password_hash_concurrency)
        return state.login_slots


def _user_by_email(factory, email: str) -> User | None:
    with session_scope(factory) as session:
        return crud.get_user_by_email(session, email=email)


def _active_user(factory, user_id: int) -> User | None:
    with session_scope(factory) as session:
        user = crud.get_user(session, user_id=user_id)
        return user if user is not None and user.is_active else None


def _attempt(
    request: Request, limiter: security.LoginLimiter, *, account: str, where: str
) -> dict[str, str]:
    """Count a password attempt; 429 with Retry-After when over a limit."""
    who = {
        "account": account.strip().lower(),
        "address": request.client.host if request.client else "unknown",
    }
    wait_s = limiter.attempt(**who)
    if wait_s is not None:
        raise ApiError(
            429,
            f"too many failed logins for this account or address; try again in {wait_s} s",
            where=where,
            headers={"Retry-After": str(wait_s)},
        )
    return who


def _set_session_cookie(response: Response, request: Request, settings, user: User) -> None:
    response.set_cookie(
        settings.session_cookie_name,
        request.app.state.session_signer.dumps(user.id, user.session_version),
        max_age=settings.session_max_age_s,
        httponly=True,
        samesite="lax",
        secure=settings.cookie_secure,
        path="/",
    )


@router.post(
    "/login",
    response_model=UserOut,
    responses={429: {"description": "too many failed logins; see Retry-After"}},
)
async def login(body: LoginIn, request: Request, response: Response, settings: SettingsDep):
    # async, with two short transactions instead of SessionDep: while a login waits for one
    # of the few argon2 slots it holds neither a worker thread nor a database connection.
    limiter = login_limiter(request)
    who = _attempt(request, limiter, account=body.email, where="body.email")
    factory = request.app.state.sessionmaker
    # Each transaction takes its place in the session gate (backend.db explains why).
    gate = request.app.state.session_gate
    async with gate.admitted():
        candidate = await to_thread.run_sync(_user_by_email, factory, body.email)
    async with _login_slots(request):
        matches = await to_thread.run_sync(crud.password_matches, candidate, body.password)
    user = None
    if matches:
        async with gate.admitted():
            user = await to_thread.run_sync(_active_user, factory, candidate.id)
    if user is None:  # wrong password, or disabled or deleted meanwhile
        raise ApiError(401, "wrong e-mail or password", where="body.password")
    limiter.succeeded(**who)
    _set_session_cookie(response, request, settings, user)
    return UserOut.of(user)


def _set_password(factory, user_id: int, password: str) -> User:
    with session_scope(factory) as session:
        user = crud.get_user(session, user_id=user_id)
        return crud.update_user(session, user=user, changes={"password": password})


@router.post(
    "/password",
    status_code=204,
    responses={
        403: {"description": "the current password is wrong"},
        429: {"description": "too many wrong passwords; see Retry-After"},
    },
)
async def change_password(
    body: PasswordChangeIn,
    request: Request,
    settings: SettingsDep,
    user: CurrentUser,
    session: SessionDep,
) -> Response:
    """Change one's own password. Every session of the user ends (a stolen cookie too); the
    browser that asked gets a fresh cookie. API tokens stay valid (revoke them apart)."""
    # The session that found ``user`` (the same SessionDep) gives its connection back before
    # this request may wait for a hash slot.
    await to_thread.run_sync(session.commit)
    limiter = login_limiter(request)
    who = _attempt(request, limiter, account=user.email, where="body.current_password")
    async with _login_slots(request):
        matches = await to_thread.run_sync(crud.password_matches, user, body.current_password)
    if not matches:
        raise ApiError(403, "the current password is wrong", where="body.current_password")
    limiter.succeeded(**who)
    factory = request.app.state.sessionmaker
    async with _login_slots(request):
        user = await to_thread.run_sync(_set_password, factory, user.id, body.new_password)
    response = Response(status_code=204)
    _set_session_cookie(response, request, settings, user)
    return response


@router.post("/logout", status_code=204)
def logout(request: Request, session: SessionDep, settings: SettingsDep) -> Response:
    claim = request.app.state.session_signer.loads(
        request.cookies.get(settings.session_cookie_name, "")
    )
    if claim is not None:
        user = crud.get_user(session, user_id=claim.user_id)
        if user is not None and user.session_version == claim.session_version:
            crud.revoke_sessions(session, user=user)
    response = Response(status_code=204)
    response.delete_cookie(
        settings.session_cookie_name,
        path="/",
        httponly=True,
        samesite="lax",
        secure=settings.cookie_secure,
    )
    return response


@router.get("/me", response_model=UserOut)
def me(user: CurrentUser):
    return UserOut.of(user)


@router.get("/session", response_model=SessionOut)
def session_state(user: OptionalUser):
    """The signed-in user or null, always 200: pages ask on every load, and a reader who is
    not signed in is not an error (``/auth/me`` answers them 401, which browsers log as a
    failed request on every anonymous page view). A revoked or forged cookie reads as
    anonymous, exactly as on every other route."""
    return SessionOut(user=UserOut.of(user) if user is not None else None)
