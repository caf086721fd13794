"""Web sessions: password login sets a signed, HttpOnly, SameSite=Lax cookie.

The cookie carries the user's session version; logout bumps it, so a copy of the cookie
kept by anyone stops working at once (and so do the user's other browsers' sessions).
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from backend import crud
from backend.api.deps import CurrentUser, SessionDep, SettingsDep
from backend.errors import ApiError
from backend.schemas import LoginIn, UserOut

router = APIRouter(prefix="/auth", tags=["auth"])


@router.post("/login", response_model=UserOut)
def login(
    body: LoginIn, request: Request, response: Response, session: SessionDep, settings: SettingsDep
):
    user = crud.authenticate(session, email=body.email, password=body.password)
    if user is None:
        raise ApiError(401, "wrong e-mail or password", where="body.password")
    response.set_cookie(
        settings.session_cookie_name,
        request.app.state.session_signer.dumps(user.id, user.session_version),
        max_age=settings.session_max_age_s,
        httponly=True,
        samesite="lax",
        secure=settings.cookie_secure,
        path="/",
    )
    return UserOut.of(user)


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
