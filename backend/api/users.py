"""User accounts (admins only): list, create, read, change (role, institution, active)."""

from __future__ import annotations

from fastapi import APIRouter

from backend import crud
from backend.api.deps import AdminUser, RowId, SessionDep, require_institution
from backend.errors import ApiError, not_found
from backend.schemas import UserCreate, UserOut, UserUpdate

router = APIRouter(prefix="/users", tags=["users"])


@router.get("", response_model=list[UserOut])
def list_users(session: SessionDep, _admin: AdminUser):
    return [UserOut.of(u) for u in crud.list_users(session)]


@router.post("", response_model=UserOut, status_code=201)
def create_user(body: UserCreate, session: SessionDep, _admin: AdminUser):
    require_institution(session, body.institution_id)
    try:
        user = crud.create_user(
            session,
            email=body.email,
            role=body.role,
            password=body.password,
            institution_id=body.institution_id,
        )
    except ValueError as exc:
        field = str(exc).split(":")[0]
        status = 409 if "already exists" in str(exc) else 422
        raise ApiError(status, str(exc), where=f"body.{field}") from exc
    return UserOut.of(user)


@router.get("/{user_id}", response_model=UserOut)
def read_user(user_id: RowId, session: SessionDep, _admin: AdminUser):
    user = crud.get_user(session, user_id=user_id)
    if user is None:
        raise not_found(f"user {user_id}", where="user_id")
    return UserOut.of(user)


@router.patch("/{user_id}", response_model=UserOut)
def update_user(user_id: RowId, body: UserUpdate, session: SessionDep, _admin: AdminUser):
    user = crud.get_user(session, user_id=user_id)
    if user is None:
        raise not_found(f"user {user_id}", where="user_id")
    changes = body.model_dump(exclude_unset=True)
    for required in ("role", "is_active"):
        if required in changes and changes[required] is None:
            raise ApiError(422, f"{required}: must not be null", where=f"body.{required}")
    require_institution(session, changes.get("institution_id"))
    try:
        user = crud.update_user(session, user=user, changes=changes)
    except ValueError as exc:
        raise ApiError(422, str(exc), where="body.institution_id") from exc
    return UserOut.of(user)
