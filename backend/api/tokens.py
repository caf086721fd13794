"""API tokens of the signed-in user (rig agents, archives): shown once, stored hashed."""

from __future__ import annotations

from fastapi import APIRouter

from backend import crud
from backend.api.deps import CurrentUser, RowId, SessionDep
from backend.errors import not_found
from backend.schemas import TokenCreate, TokenCreated, TokenOut
from backend.tables import Role

router = APIRouter(prefix="/tokens", tags=["tokens"])


@router.get("", response_model=list[TokenOut])
def list_tokens(session: SessionDep, user: CurrentUser):
    return [TokenOut.model_validate(t) for t in crud.list_tokens(session, user=user)]


@router.post("", response_model=TokenCreated, status_code=201)
def create_token(body: TokenCreate, session: SessionDep, user: CurrentUser):
    token, secret = crud.create_token(session, user=user, name=body.name)
    return TokenCreated(**TokenOut.model_validate(token).model_dump(), secret=secret)


@router.delete("/{token_id}", response_model=TokenOut)
def revoke_token(token_id: RowId, session: SessionDep, user: CurrentUser):
    """Revoke one of your tokens (admins: anyone's)."""
    token = crud.get_token(session, token_id=token_id)
    if token is None or (token.user_id != user.id and user.role != Role.admin):
        raise not_found(f"token {token_id}", where="token_id")
    return TokenOut.model_validate(crud.revoke_token(session, token=token))
