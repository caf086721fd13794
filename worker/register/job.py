"""The registration job of a whole tablet (called by ``worker.tasks.register_tablet``).

Fetches the latest model of each scan of the job's tablet, registers them
(:func:`worker.register.run.register_model_dirs`) and stores the result as a tablet-level
model (no scan) through ``backend.jobs.mark_succeeded``: its assets are ``model.glb`` (the
one-node-per-face scene, so the viewer shows the whole tablet), ``faces/<label>/*.png`` (each
face's full-resolution normals blended across the seams, quality weight and shading maps),
``faces/<label>/quality/*.npy`` (the face's quality maps), ``faces/<label>/trust.*`` and
``uncertainty_um.npy`` (its trust assets), ``faces/<label>/height.npy``, ``faces/<label>/photos/*`` and
``faces/<label>/gloss.*`` (the face's photographs and measured gloss), ``merged.ply``,
``transforms.json``, ``report.json``, ``fatcross/*.png`` and ``tiles/`` (each face's
streaming tiles and the root tileset, ``worker.tiles.tablet``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
from sqlalchemy import select

from backend import jobs
from backend.licences import effective
from backend.tables import Job, Model, Tablet
from worker.assets import AssetError, derive_assets
from worker.register.io import (
    GLOSS_FILES,
    QUALITY_MAPS,
    SHADING_MAPS,
    RegisterInputError,
    face_asset_dir,
    photo_asset_names,
    write_output_dir,
)
from worker.register.plates import DEFAULT_LICENCE
from worker.register.run import register_model_dirs
from worker.tiles import TileError
from worker.tiles.tablet import build_tablet_tiles

__all__ = ["MODEL_FILES", "run_job"]

log = logging.getLogger("worker.register.job")

MODEL_FILES = (
    "report.json",
    "height.npy",
    "normals.npy",
    "mask.png",
    "albedo.png",
    *SHADING_MAPS,
    *(f"quality/{name}" for name in QUALITY_MAPS),
    *GLOSS_FILES,
)


def _fetch_photos(storage, prefix: str, d: Path) -> None:
    """The face model's photographs (``photos/index.json`` and the JPEGs it lists) into
    ``d/photos``; none when the model has no index or it is unusable (logged: they are an
    extra, the registration goes on without them)."""
    if not storage.exists(f"{prefix}/photos/index.json"):
        return
    (d / "photos").mkdir(exist_ok=True)
    index = storage.get_file(f"{prefix}/photos/index.json", d / "photos" / "index.json")
    try:
        names = photo_asset_names(index.read_bytes())
    except ValueError as exc:
        log.warning("%s: photographs left out: %s", prefix, exc)
        return
    for name in names:
        if storage.exists(f"{prefix}/{name}"):
            storage.get_file(f"{prefix}/{name}", d / name)


def _latest_models(session, tablet_id: int) -> list[tuple[int, str]]:
    """(scan id, storage prefix) of the newest model of every scan of the tablet."""
    rows = session.execute(
        select(Model.scan_id, Model.storage_prefix, Model.version)
        .where(Model.tablet_id == tablet_id, Model.scan_id.is_not(None))
        .order_by(Model.scan_id, Model.version)
    ).all()
    latest: dict[int, str] = {}
    for scan_id, prefix, _ in rows:
        latest[scan_id] = prefix
    return sorted(latest.items())


def _fail(session_factory, job_id: int, message: str) -> str:
    with session_factory() as session, contextlib.suppress(jobs.JobStateError):
        jobs.mark_failed(session, job_id=job_id, error=message)
    return "failed"


def plate_licence_line(tablet) -> str:
    """The plates' licence line: the licence and attribution that apply to the tablet
    (its own, else its institution's), never one it was not given."""
    if tablet is None:
        return DEFAULT_LICENCE
    stated = effective(tablet)
    parts = [stated.licence or DEFAULT_LICENCE]
    if stated.attribution:
        parts.append(stated.attribution)
    return " · ".join(parts)


def _tablet_tiles(out: Path, transforms: dict, progress: Callable[..., None]) -> None:
    """Each face's tiles and the tablet's root tileset (worker.tiles.tablet); a tablet that
    cannot be tiled is still stored (the viewer falls back to model.glb)."""
    faces = {}
    for label, t in transforms.get("scans", {}).items():
        matrix = np.eye(4)
        matrix[:3, :3] = np.asarray(t["rotation"], float)
        matrix[:3, 3] = np.asarray(t["translation_mm"], float)
        face_dir = Path(t["model_dir"])
        faces[face_asset_dir(label)] = (face_dir, matrix)
    try:
        for face_dir, _ in faces.values():
            if not all((face_dir / n).is_file() for n in ("curvature.png", "accessibility.png")):
                derive_assets(face_dir)  # a face model made before these maps existed
        build_tablet_tiles(out, faces, progress=lambda stage, f: progress("tiles", 0.8 + 0.1 * f))
    except (TileError, AssetError) as exc:
        log.warning("%s: no tiles: %s", out, exc)


def run_job(job_id: int, session_factory, storage, progress: Callable[..., None]) -> str:
    """Register the tablet of job ``job_id``; "succeeded" or "failed" (with a message)."""
    with session_factory() as session:
        job = session.get(Job, job_id)
        if job is None:
            raise LookupError(f"job {job_id}: not found")
        tablet = session.get(Tablet, job.tablet_id)
        name = (tablet.designation if tablet is not None else None) or f"tablet-{job.tablet_id}"
        # Plates are named by the P-number when there is one (P451806_fatcross_natural.png)
        # and titled by it and the designation, as CDLI shows them.
        p_number = tablet.p_number if tablet is not None else None
        title = f"{p_number} ({name})" if p_number and p_number != name else name
        name = p_number or name
        licence = plate_licence_line(tablet)
        models = _latest_models(session, job.tablet_id)
    if len(models) < 2:
        return _fail(
            session_factory,
            job_id,
            f"registration needs models of two or more scans; the tablet has {len(models)}",
        )
    work = Path(tempfile.mkdtemp(prefix=f"hammurabi-register-{job_id}-"))
    try:
        progress("fetch", 0.05, force=True)
        dirs = []
        for scan_id, prefix in models:
            d = work / f"scan-{scan_id}"
            d.mkdir()
            (d / "quality").mkdir()
            for file in MODEL_FILES:
                if storage.exists(f"{prefix}/{file}"):
                    storage.get_file(f"{prefix}/{file}", d / file)
            _fetch_photos(storage, prefix, d)
            dirs.append(str(d))
        progress("register", 0.2, force=True)
        safe = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name)
        try:
            files, report = register_model_dirs(dirs, name=safe, designation=title, licence=licence)
        except (RegisterInputError, ValueError) as exc:
            return _fail(session_factory, job_id, f"registration: {exc}")
        files["model.glb"] = files["tablet.glb"]
        out = write_output_dir(work / "out", files)
        progress("tiles", 0.8, force=True)
        _tablet_tiles(out, json.loads(files["transforms.json"]), progress)
        progress("store", 0.9, force=True)
        with session_factory() as session:
            jobs.mark_succeeded(
                session, job_id=job_id, model_dir=out, storage=storage, report=report
            )
        return "succeeded"
    finally:
        shutil.rmtree(work, ignore_errors=True)
