"""Institutions that hold tablets: anyone may list them, admins create them."""

from __future__ import annotations

from fastapi import APIRouter

from backend import crud
from backend.api.deps import AdminUser, SessionDep
from backend.errors import conflict
from backend.schemas import InstitutionIn, InstitutionOut

router = APIRouter(prefix="/institutions", tags=["institutions"])


@router.get("", response_model=list[InstitutionOut])
def list_institutions(session: SessionDep):
    return [InstitutionOut.model_validate(i) for i in crud.list_institutions(session)]


@router.post("", response_model=InstitutionOut, status_code=201)
def create_institution(body: InstitutionIn, session: SessionDep, _admin: AdminUser):
    if crud.get_institution_by_name(session, name=body.name.strip()) is not None:
        raise conflict(f"an institution {body.name!r} already exists", where="body.name")
    return InstitutionOut.model_validate(crud.get_or_create_institution(session, name=body.name))
