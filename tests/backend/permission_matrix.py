"""Expected HTTP status of EVERY API route for every role: the permission matrix.

``MATRIX["METHOD /api/v1/path/{param}"]`` is a list of :class:`Case`; each case builds the
request for a role from the test ``World`` (see conftest.py) and states the status each role
must get. ``test_permissions.py`` fails when a route of the app has no row here, so a new
route must come with its row (add it in the section of your router).

Roles: anonymous, reader, staff_own (staff of the institution that holds the record),
staff_other (staff of another institution), admin. ``params``/``json``/``query``/``content``
are called once per role, so a case may create a fresh object for each request (deletes).
"""

from __future__ import annotations

import importlib.util
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

ROLES = ("anonymous", "reader", "staff_own", "staff_other", "admin")
PASSWORD = "correct horse battery staple"  # the password of every world user (conftest)

Builder = Callable[[Any, str], Any]  # (world, role) -> value


def _none(_world, _role):
    return None


def _no_params(_world, _role):
    return {}


@dataclass(frozen=True)
class Case:
    label: str
    expect: dict[str, int]
    params: Builder = _no_params
    json: Builder = _none
    query: Builder = _none
    content: Builder = _none
    headers: Builder = _none


def expect(anonymous: int, reader: int, staff_own: int, staff_other: int, admin: int) -> dict:
    return dict(
        anonymous=anonymous,
        reader=reader,
        staff_own=staff_own,
        staff_other=staff_other,
        admin=admin,
    )


def _unique(prefix: str) -> str:
    return f"{prefix}-{uuid.uuid4().hex[:8]}"


_P_NUMBERS = iter(range(900_000, 1_000_000))


def _p_number_held_privately_by_a(world, _role):
    """A body registering a fresh P-number that a new private record of A already holds."""
    p_number = f"P{next(_P_NUMBERS)}"
    world.new_tablet(institution="a", p_number=p_number)
    return {"designation": _unique("New"), "p_number": p_number}


def _fresh_token_of_staff_own(world, _role):
    from backend import crud

    with world.session() as session:
        user = crud.get_user(session, user_id=world.users["staff_own"])
        token, _secret = crud.create_token(session, user=user, name="to revoke")
        return {"token_id": token.id}


_ATF = "@obverse\n1. a-na {d}utu\n2. qi2-bi2-ma\n@reverse\n1. um-ma"
_ANNOTATION = {"reference": "o 1 2", "polygon_mm": [[0, 0, 0], [1, 0, 0], [1, 1, 0]]}


def _private_a_ref(world, _role):
    return {"tablet_id": world.private_a}


def _annotation_by(world, author: str, tablet_id: int) -> dict:
    """A fresh annotation of ``author`` (a role) on a new model of ``tablet_id``."""
    from backend.tables import Annotation

    model_id = world.new_model(tablet_id)
    with world.session() as session:
        annotation = Annotation(
            model_id=model_id,
            tablet_id=tablet_id,
            creator_id=world.users[author],
            reference="o 1 2",
            polygon_mm=_ANNOTATION["polygon_mm"],
        )
        session.add(annotation)
        session.flush()
        return {"annotation_id": annotation.id}


MATRIX: dict[str, list[Case]] = {
    # --- health, auth, users, tokens, institutions (library core) ---------------------------
    "GET /api/v1/health": [Case("anyone", expect(200, 200, 200, 200, 200))],
    "POST /api/v1/auth/login": [
        Case(
            "own e-mail and password (anonymous: unknown e-mail)",
            expect(401, 200, 200, 200, 200),
            json=lambda w, role: {
                "email": w.emails.get(role, "nobody@example.org"),
                "password": PASSWORD,
            },
        )
    ],
    "POST /api/v1/auth/logout": [Case("anyone", expect(204, 204, 204, 204, 204))],
    "POST /api/v1/auth/password": [
        Case(
            "own password, wrong current one (changes nothing)",
            expect(401, 403, 403, 403, 403),
            json=lambda w, role: {"current_password": "not it", "new_password": "long enough 2"},
        )
    ],
    "GET /api/v1/auth/me": [Case("signed in", expect(401, 200, 200, 200, 200))],
    "GET /api/v1/auth/session": [Case("anyone", expect(200, 200, 200, 200, 200))],
    "GET /api/v1/users": [Case("admins only", expect(401, 403, 403, 403, 200))],
    "POST /api/v1/users": [
        Case(
            "admins only",
            expect(401, 403, 403, 403, 201),
            json=lambda w, role: {"email": f"{_unique('new')}@example.org", "role": "reader"},
        )
    ],
    "GET /api/v1/users/{user_id}": [
        Case(
            "admins only",
            expect(401, 403, 403, 403, 200),
            params=lambda w, role: {"user_id": w.users["reader"]},
        )
    ],
    "PATCH /api/v1/users/{user_id}": [
        Case(
            "admins only",
            expect(401, 403, 403, 403, 200),
            params=lambda w, role: {"user_id": w.users["reader"]},
            json=lambda w, role: {"is_active": True},
        )
    ],
    "GET /api/v1/tokens": [Case("own tokens", expect(401, 200, 200, 200, 200))],
    "POST /api/v1/tokens": [
        Case("own token", expect(401, 201, 201, 201, 201), json=lambda w, r: {"name": "rig"})
    ],
    "DELETE /api/v1/tokens/{token_id}": [
        Case(
            "a token of staff_own: its owner and admins",
            expect(401, 404, 200, 404, 200),
            params=_fresh_token_of_staff_own,
        )
    ],
    "GET /api/v1/institutions": [Case("anyone", expect(200, 200, 200, 200, 200))],
    "POST /api/v1/institutions": [
        Case(
            "admins only",
            expect(401, 403, 403, 403, 201),
            json=lambda w, role: {"name": _unique("Museum")},
        )
    ],
    "PATCH /api/v1/institutions/{institution_id}": [
        Case(
            "institution A's default licence: its staff and admins",
            expect(401, 403, 200, 403, 200),
            params=lambda w, role: {"institution_id": w.institution_a},
            json=lambda w, role: {"licence": "https://creativecommons.org/licenses/by/4.0/"},
        )
    ],
    # --- tablets ----------------------------------------------------------------------------
    "GET /api/v1/tablets": [Case("anyone (results filtered)", expect(200, 200, 200, 200, 200))],
    "POST /api/v1/tablets": [
        Case(
            "staff and admins",
            expect(401, 403, 201, 201, 201),
            json=lambda w, role: {"designation": _unique("New")},
        ),
        Case(
            "for another institution: admins only",
            expect(401, 403, 403, 201, 201),
            json=lambda w, role: {"designation": _unique("New"), "institution_id": w.institution_b},
        ),
        Case(
            "a P-number A holds privately: 409 only for A (no leak); B registers its own",
            expect(401, 403, 409, 201, 201),
            json=_p_number_held_privately_by_a,
        ),
    ],
    "GET /api/v1/tablets/{tablet_id}": [
        Case(
            "private record",
            expect(404, 404, 200, 404, 200),
            params=lambda w, role: {"tablet_id": w.private_a},
        ),
        Case(
            "private record by P-number",
            expect(404, 404, 200, 404, 200),
            params=lambda w, role: {"tablet_id": "P000002"},
        ),
        Case(
            "public record",
            expect(200, 200, 200, 200, 200),
            params=lambda w, role: {"tablet_id": w.public_a},
        ),
    ],
    "PATCH /api/v1/tablets/{tablet_id}": [
        Case(
            "private record",
            expect(404, 404, 200, 404, 200),
            params=lambda w, role: {"tablet_id": w.private_a},
            json=lambda w, role: {"notes": "seen"},
        ),
        Case(
            "public record",
            expect(401, 403, 200, 403, 200),
            params=lambda w, role: {"tablet_id": w.public_a},
            json=lambda w, role: {"notes": "seen"},
        ),
        Case(
            "move to another institution: admins only",
            expect(401, 403, 403, 403, 200),
            params=lambda w, role: {"tablet_id": w.new_tablet(is_public=True)},
            json=lambda w, role: {"institution_id": w.institution_b},
        ),
    ],
    "DELETE /api/v1/tablets/{tablet_id}": [
        Case(
            "private record",
            expect(404, 404, 204, 404, 204),
            params=lambda w, role: {"tablet_id": w.new_tablet()},
        ),
        Case(
            "public record",
            expect(401, 403, 204, 403, 204),
            params=lambda w, role: {"tablet_id": w.new_tablet(is_public=True)},
        ),
    ],
    # --- uploads, scans, jobs, models, iiif (uploads engineer: add your rows here) ------------
    # --- annotations and transliterations (issue 20) ----------------------------------------
    "GET /api/v1/tablets/{tablet_id}/transliteration": [
        Case(
            "private record with ATF",
            expect(404, 404, 200, 404, 200),
            params=lambda w, role: {"tablet_id": w.new_tablet(atf=_ATF)},
        ),
        Case(
            "public record with ATF",
            expect(200, 200, 200, 200, 200),
            params=lambda w, role: {"tablet_id": w.new_tablet(is_public=True, atf=_ATF)},
        ),
    ],
    "GET /api/v1/tablets/{tablet_id}/annotations": [
        Case("private A", expect(404, 404, 200, 404, 200), params=_private_a_ref),
        Case(
            "public A",
            expect(200, 200, 200, 200, 200),
            params=lambda w, role: {"tablet_id": w.public_a},
        ),
    ],
    "GET /api/v1/models/{model_id}/annotations": [
        Case(
            "model of private A",
            expect(404, 404, 200, 404, 200),
            params=lambda w, role: {"model_id": w.new_model(w.private_a)},
        ),
        Case(
            "model of public A",
            expect(200, 200, 200, 200, 200),
            params=lambda w, role: {"model_id": w.new_model(w.public_a)},
        ),
    ],
    "POST /api/v1/models/{model_id}/annotations": [
        Case(
            "on a model of public A: any signed-in user (staff and registered scholars)",
            expect(401, 201, 201, 201, 201),
            params=lambda w, role: {"model_id": w.new_model(w.public_a)},
            json=lambda w, role: _ANNOTATION,
        ),
        Case(
            "on a model of private A: those who may read it",
            expect(404, 404, 201, 404, 201),
            params=lambda w, role: {"model_id": w.new_model(w.private_a)},
            json=lambda w, role: _ANNOTATION,
        ),
    ],
    "GET /api/v1/annotations/{annotation_id}": [
        Case(
            "by the reader, on public A",
            expect(200, 200, 200, 200, 200),
            params=lambda w, role: _annotation_by(w, "reader", w.public_a),
        ),
        Case(
            "by staff of A, on private A",
            expect(404, 404, 200, 404, 200),
            params=lambda w, role: _annotation_by(w, "staff_own", w.private_a),
        ),
    ],
    "PATCH /api/v1/annotations/{annotation_id}": [
        Case(
            "by the reader, on public A: its author, A's staff, admins",
            expect(401, 200, 200, 403, 200),
            params=lambda w, role: _annotation_by(w, "reader", w.public_a),
            json=lambda w, role: {"comment": "seen"},
        ),
        Case(
            "by staff of B, on public A: its author, A's staff, admins",
            expect(401, 403, 200, 200, 200),
            params=lambda w, role: _annotation_by(w, "staff_other", w.public_a),
            json=lambda w, role: {"reading": "lugal"},
        ),
        Case(
            "by staff of A, on private A",
            expect(404, 404, 200, 404, 200),
            params=lambda w, role: _annotation_by(w, "staff_own", w.private_a),
            json=lambda w, role: {"comment": "seen"},
        ),
    ],
    "DELETE /api/v1/annotations/{annotation_id}": [
        Case(
            "by the reader, on public A: its author, A's staff, admins",
            expect(401, 204, 204, 403, 204),
            params=lambda w, role: _annotation_by(w, "reader", w.public_a),
        ),
        Case(
            "by staff of A, on private A",
            expect(404, 404, 204, 404, 204),
            params=lambda w, role: _annotation_by(w, "staff_own", w.private_a),
        ),
    ],
}


# --- uploads, scans, jobs, models (rows written by the library-core engineer from the routes'
# docstrings; their owner adjusts them) --------------------------------------------------------


def _upload_of_private_a(world, _role):
    """An open upload (with its empty part file) of the private tablet of A."""
    from backend import crud, uploads
    from backend.tables import User

    with world.session() as session:
        upload = uploads.create_upload(
            session,
            tablet=crud.get_tablet(session, tablet_id=world.private_a),
            user=session.get(User, world.users["staff_own"]),
            filename="scan.zip",
            size_bytes=4,
            uploads_dir=world.settings.data_dir / "uploads",
            limits=uploads.UploadLimits.of(world.settings),
        )
        return {"upload_id": upload.id}


# A model with what both IIIF manifests need: a GLB, an albedo and its image grid.
_MODEL_ASSETS = {
    name: {"size_bytes": 4, "sha256": "0" * 64} for name in ("model.glb", "albedo.png")
}
_MODEL_REPORT = {"pixel_size_um": 50, "image_size": {"width": 8, "height": 6}}


def _private_tablet_of_a_with_model(world, _role):
    tablet_id = world.new_tablet()
    world.new_model(tablet_id, assets=_MODEL_ASSETS, report=_MODEL_REPORT)
    return {"tablet_id": tablet_id}


def _private_a(world, _role):
    return {"tablet_id": world.private_a}


def _public_tablet_with_model(world, _role):
    tablet_id = world.new_tablet(is_public=True)
    world.new_model(tablet_id, assets=_MODEL_ASSETS, report=_MODEL_REPORT)
    return {"tablet_id": tablet_id}


_OPTIONAL_ROWS = {
    "POST /api/v1/uploads": [
        Case(
            "for the private tablet of A",
            expect(401, 404, 201, 404, 201),
            json=lambda w, role: {
                "tablet_id": w.private_a,
                "filename": "scan.zip",
                "size_bytes": 4,
            },
        ),
        Case(
            "for the public tablet of A",
            expect(401, 403, 201, 403, 201),
            json=lambda w, role: {"tablet_id": w.public_a, "filename": "s.zip", "size_bytes": 4},
        ),
    ],
    "GET /api/v1/uploads/{upload_id}": [
        Case("upload of private A", expect(401, 404, 200, 404, 200), params=_upload_of_private_a)
    ],
    "DELETE /api/v1/uploads/{upload_id}": [
        Case("upload of private A", expect(401, 404, 204, 404, 204), params=_upload_of_private_a)
    ],
    "PUT /api/v1/uploads/{upload_id}/chunks": [
        Case(
            "upload of private A",
            expect(401, 404, 200, 404, 200),
            params=_upload_of_private_a,
            query=lambda w, role: {"offset": 0},
            content=lambda w, role: b"abcd",
        )
    ],
    "POST /api/v1/uploads/{upload_id}/complete": [
        Case(
            "upload of private A, wrong sha256 (allowed roles get the 4xx of the check)",
            expect(401, 404, 409, 404, 409),
            params=_upload_of_private_a,
            json=lambda w, role: {"sha256": "0" * 64},
        )
    ],
    "GET /api/v1/tablets/{tablet_id}/scans": [
        Case("private A", expect(404, 404, 200, 404, 200), params=_private_a),
        Case(
            "public A",
            expect(200, 200, 200, 200, 200),
            params=lambda w, role: {"tablet_id": w.public_a},
        ),
    ],
    "GET /api/v1/tablets/{tablet_id}/iiif/manifest.json": [
        Case(
            "private tablet of A with a model",
            expect(404, 404, 200, 404, 200),
            params=_private_tablet_of_a_with_model,
        ),
        Case(
            "public tablet with a model",
            expect(200, 200, 200, 200, 200),
            params=_public_tablet_with_model,
        ),
        Case(
            "public tablet without a model yet",
            expect(404, 404, 404, 404, 404),
            params=lambda w, role: {"tablet_id": w.new_tablet(is_public=True)},
        ),
    ],
    "GET /api/v1/tablets/{tablet_id}/iiif/canvas/{part}": [
        Case(
            "unknown part of private A: nobody learns more than 404",
            expect(404, 404, 404, 404, 404),
            params=lambda w, role: {"tablet_id": w.private_a, "part": "nothing"},
        ),
        Case(
            "the obverse Canvas of a private tablet of A with a model",
            expect(404, 404, 200, 404, 200),
            params=lambda w, role: {
                **_private_tablet_of_a_with_model(w, role),
                "part": "obverse",
            },
        ),
    ],
    "GET /api/v1/tablets/{tablet_id}/iiif/3d/manifest.json": [
        Case(
            "private tablet of A with a model",
            expect(404, 404, 200, 404, 200),
            params=_private_tablet_of_a_with_model,
        ),
        Case(
            "public tablet with a model",
            expect(200, 200, 200, 200, 200),
            params=_public_tablet_with_model,
        ),
    ],
    "GET /api/v1/tablets/{tablet_id}/iiif/3d/scene/{part}": [
        Case(
            "the obverse Scene of a private tablet of A with a model",
            expect(404, 404, 200, 404, 200),
            params=lambda w, role: {
                **_private_tablet_of_a_with_model(w, role),
                "part": "obverse",
            },
        ),
    ],
    "GET /api/v1/scans/{scan_id}": [
        Case(
            "scan of private A",
            expect(404, 404, 200, 404, 200),
            params=lambda w, role: {"scan_id": w.new_scan(w.private_a)},
        )
    ],
    "GET /api/v1/jobs/{job_id}": [
        Case(
            "job of private A",
            expect(404, 404, 200, 404, 200),
            params=lambda w, role: {"job_id": w.new_job(w.private_a)},
        )
    ],
    "POST /api/v1/jobs/{job_id}/retry": [
        Case(
            "queued job of public A (allowed roles: 409, only failed jobs are retried)",
            expect(401, 403, 409, 403, 409),
            params=lambda w, role: {"job_id": w.new_job(w.public_a)},
        ),
        Case(
            "queued job of private A",
            expect(404, 404, 409, 404, 409),
            params=lambda w, role: {"job_id": w.new_job(w.private_a)},
        ),
    ],
    "GET /api/v1/models": [
        Case(
            "whole-tablet models of private A",
            expect(404, 404, 200, 404, 200),
            query=lambda w, role: {"tablet_id": w.private_a},
        ),
        Case(
            "whole-tablet models of public A",
            expect(200, 200, 200, 200, 200),
            query=lambda w, role: {"tablet_id": w.public_a},
        ),
    ],
    "GET /api/v1/models/{model_id}": [
        Case(
            "model of private A",
            expect(404, 404, 200, 404, 200),
            params=lambda w, role: {"model_id": w.new_model(w.private_a)},
        )
    ],
    "PATCH /api/v1/models/{model_id}": [
        Case(
            "licence of a model of public A: A's staff and admins",
            expect(401, 403, 200, 403, 200),
            params=lambda w, role: {"model_id": w.new_model(w.public_a)},
            json=lambda w, role: {"licence": "https://creativecommons.org/licenses/by/4.0/"},
        ),
        Case(
            "licence of a model of private A",
            expect(404, 404, 200, 404, 200),
            params=lambda w, role: {"model_id": w.new_model(w.private_a)},
            json=lambda w, role: {"attribution": "Scanned by Museum A"},
        ),
    ],
    "GET /api/v1/models/{model_id}/assets/{name}": [
        Case(
            "unknown asset of a model of private A: nobody learns more than 404",
            expect(404, 404, 404, 404, 404),
            params=lambda w, role: {"model_id": w.new_model(w.private_a), "name": "x.glb"},
        )
    ],
    "HEAD /api/v1/models/{model_id}/assets/{name}": [
        Case(
            "unknown asset of a model of private A: nobody learns more than 404",
            expect(404, 404, 404, 404, 404),
            params=lambda w, role: {"model_id": w.new_model(w.private_a), "name": "x.glb"},
        )
    ],
}


# Rows of the optional routers (backend.main.OPTIONAL_ROUTERS) apply when the router exists.
def _module_of(route: str) -> str:
    path = route.split(" ", 1)[1]
    if "/iiif/" in path:
        return "iiif"
    if path.endswith("/scans") or "/scans/" in path:
        return "scans"
    return path.split("/")[3]  # /api/v1/<resource>/...


for _route, _cases in _OPTIONAL_ROWS.items():
    if importlib.util.find_spec(f"backend.api.{_module_of(_route)}") is not None:
        MATRIX[_route] = _cases
