"""Institutions that hold tablets: anyone may list them, admins create them, admins and the
institution's staff set its default licence and attribution."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path

from backend import crud
from backend.api.deps import AdminUser, SessionDep, StaffUser
from backend.errors import conflict, forbidden, not_found
from backend.schemas import InstitutionIn, InstitutionOut, InstitutionUpdate
from backend.tables import Institution, Role

router = APIRouter(prefix="/institutions", tags=["institutions"])


@router.get("", response_model=list[InstitutionOut])
def list_institutions(session: SessionDep):
    return [InstitutionOut.model_validate(i) for i in crud.list_institutions(session)]


@router.post("", response_model=InstitutionOut, status_code=201)
def create_institution(body: InstitutionIn, session: SessionDep, _admin: AdminUser):
    if crud.get_institution_by_name(session, name=body.name.strip()) is not None:
        raise conflict(f"an institution {body.name!r} already exists", where="body.name")
    institution = crud.get_or_create_institution(session, name=body.name)
    institution.licence, institution.attribution = body.licence, body.attribution
    session.flush()
    return InstitutionOut.model_validate(institution)


@router.patch("/{institution_id}", response_model=InstitutionOut)
def update_institution(
    body: InstitutionUpdate,
    session: SessionDep,
    user: StaffUser,
    institution_id: Annotated[int, Path(ge=1, le=2**31 - 1)],
):
    """The default licence and attribution of the institution's tablets and models."""
    institution = session.get(Institution, institution_id)
    if institution is None:
        raise not_found(f"institution {institution_id}", where="institution_id")
    if user.role != Role.admin and user.institution_id != institution.id:
        raise forbidden("staff change their own institution only", where="institution_id")
    for name, value in body.model_dump(exclude_unset=True).items():
        setattr(institution, name, value)
    session.flush()
    return InstitutionOut.model_validate(institution)
