"""Scans of a tablet: ``GET /tablets/{id}/scans`` and ``GET /scans/{id}``.

A scan is one face of one tablet as uploaded (its bundle is kept in storage); it carries its
latest reconstruction job and the model versions made from it.
"""

from __future__ import annotations

from datetime import datetime

from fastapi import APIRouter
from pydantic import BaseModel
from sqlalchemy import select
from sqlalchemy.orm import Session

from backend.api.deps import OptionalUser, ReadableTablet, RowId, SessionDep, SettingsDep
from backend.api.jobs import JobOut
from backend.api.models import ModelOut, StorageErrorRoute, check_tablet_access, models_of_scan
from backend.errors import not_found
from backend.tables import Scan
from backend.uploads import latest_job


class ScanOut(BaseModel):
    id: int
    tablet_id: int
    face: str
    scan_uid: str | None
    size_bytes: int
    bundle_sha256: str
    captured_at: str | None
    created_at: datetime
    latest_job: JobOut | None
    models: list[ModelOut]
    simulated: bool  # scan.tablet free metadata says so (worker.bundle.is_simulated)

    @classmethod
    def of(cls, session: Session, scan: Scan, *, api_prefix: str) -> ScanOut:
        from worker.bundle import is_simulated  # as backend.uploads: loaded on first use

        job = latest_job(session, scan_id=scan.id)
        return cls(
            id=scan.id,
            tablet_id=scan.tablet_id,
            face=scan.face,
            scan_uid=scan.scan_uid,
            size_bytes=scan.size_bytes,
            bundle_sha256=scan.bundle_sha256,
            captured_at=(scan.manifest or {}).get("scan", {}).get("captured_at"),
            created_at=scan.created_at,
            latest_job=JobOut.of(job) if job is not None else None,
            models=[ModelOut.of(m, api_prefix=api_prefix) for m in models_of_scan(session, scan)],
            simulated=is_simulated((scan.manifest or {}).get("scan", {}).get("tablet")),
        )


router = APIRouter(tags=["scans"], route_class=StorageErrorRoute)


@router.get("/tablets/{tablet_id}/scans", response_model=list[ScanOut])
def list_scans(tablet: ReadableTablet, session: SessionDep, settings: SettingsDep):
    scans = session.scalars(select(Scan).where(Scan.tablet_id == tablet.id).order_by(Scan.id))
    return [ScanOut.of(session, s, api_prefix=settings.api_prefix) for s in scans]


@router.get("/scans/{scan_id}", response_model=ScanOut)
def read_scan(
    scan_id: RowId,
    session: SessionDep,
    user: OptionalUser,
    settings: SettingsDep,
):
    scan = session.get(Scan, scan_id)
    if scan is None:
        raise not_found(f"scan {scan_id}", where="scan_id")
    check_tablet_access(
        session, user, scan.tablet_id, what=f"scan {scan_id}", where="scan_id", edit=False
    )
    return ScanOut.of(session, scan, api_prefix=settings.api_prefix)
