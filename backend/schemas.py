"""Pydantic schemas of the API (request bodies and responses), apart from the tables."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, StrictBool, field_validator
from pydantic_core import PydanticCustomError

from backend.atf import MAX_ATF_CHARS, ReferenceError_, parse_reference
from backend.db import RowId
from backend.iiif import RIGHTS_PATTERN, cdli_url
from backend.licences import LICENCE_DESCRIPTION, check_licence, effective
from backend.tables import Role

P_NUMBER_PATTERN = r"^[PQX][0-9]{6}$"  # ASCII digits: \d also takes "４" (fullwidth)
EMAIL_PATTERN = r"^[^@\s]+@[^@\s]+\.[^@\s]+$"


class ORMModel(BaseModel):
    model_config = ConfigDict(from_attributes=True)


# --- errors (backend.errors sends these; backend.docs puts them into the OpenAPI) ----------


class ErrorOut(BaseModel):
    """Every error: a message for people and the culprit (a field, a path parameter...)."""

    detail: str
    where: str | None


class Problem(BaseModel):
    where: str | None
    message: str


class ValidationErrorOut(ErrorOut):
    """A 422: the first problem in ``detail`` / ``where``, all of them in ``problems``."""

    problems: list[Problem] | None = None


# --- auth and users -------------------------------------------------------------------------


class LoginIn(BaseModel):
    email: str = Field(min_length=3, max_length=320)
    password: str = Field(min_length=1, max_length=1000)


class PasswordChangeIn(BaseModel):
    current_password: str = Field(min_length=1, max_length=1000)
    new_password: str = Field(min_length=8, max_length=1000)


class LicenceFields(BaseModel):
    """A licence URI and a credit line, checked the same way wherever they are set."""

    licence: str | None = Field(
        default=None,
        max_length=300,
        # Documented, and checked by check_licence with a message naming what is expected.
        json_schema_extra={"pattern": RIGHTS_PATTERN.pattern},
        description=LICENCE_DESCRIPTION,
    )
    attribution: str | None = Field(
        default=None, max_length=500, description='the credit line, e.g. "Courtesy of ..."'
    )

    @field_validator("licence", mode="after")
    @classmethod
    def _licence(cls, value):
        return check_licence(value)

    @field_validator("attribution", mode="before")
    @classmethod
    def _attribution(cls, value):
        return (value.strip() or None) if isinstance(value, str) else value


class InstitutionIn(LicenceFields):
    name: str = Field(min_length=1, max_length=200)

    @field_validator("name", mode="after")
    @classmethod
    def _name(cls, value: str) -> str:
        if not value.strip():  # crud refuses a blank name: say so here, not as a 500
            raise ValueError("must not be blank")
        return value.strip()


class InstitutionUpdate(LicenceFields):
    """The defaults of the institution's tablets (``null`` clears one)."""

    model_config = ConfigDict(extra="forbid")


class InstitutionOut(ORMModel):
    id: int
    name: str
    licence: str | None = None
    attribution: str | None = None
    created_at: datetime


class UserOut(ORMModel):
    id: int
    email: str
    role: Role
    institution_id: int | None
    institution: str | None = None
    is_active: bool
    created_at: datetime

    @classmethod
    def of(cls, user) -> UserOut:
        data = {name: getattr(user, name) for name in cls.model_fields if name != "institution"}
        data["institution"] = user.institution.name if user.institution else None
        return cls.model_validate(data)


class SessionOut(BaseModel):
    """Who a browser is signed in as; ``user`` is null for an anonymous reader."""

    user: UserOut | None


class UserCreate(BaseModel):
    email: str = Field(pattern=EMAIL_PATTERN, max_length=320)
    password: str | None = Field(default=None, min_length=8, max_length=1000)
    role: Role = Role.reader
    institution_id: RowId | None = None

    @field_validator("email", mode="before")
    @classmethod
    def _lower(cls, value):
        return value.strip().lower() if isinstance(value, str) else value


class UserUpdate(BaseModel):
    password: str | None = Field(default=None, min_length=8, max_length=1000)
    # Omitted: kept. Never null, and the schema says so (schemathesis found the old
    # `Role | None` documented a null that the route refused).
    role: Role = Field(default=None, description="omit to keep; null is refused")
    institution_id: RowId | None = None
    is_active: StrictBool = Field(default=None, description="omit to keep; null is refused")


class TokenCreate(BaseModel):
    name: str = Field(min_length=1, max_length=200)


class TokenOut(ORMModel):
    id: int
    name: str
    prefix: str
    created_at: datetime
    last_used_at: datetime | None
    revoked_at: datetime | None


class TokenCreated(TokenOut):
    secret: str = Field(description="the token; shown once, never again")


# --- tablets --------------------------------------------------------------------------------

_TEXT_FIELDS = [
    "designation",
    "museum_no",
    "collection",
    "owner",
    "excavation_no",
    "period",
    "provenience",
    "genre",
    "subgenre",
    "language",
    "material",
    "object_type",
    "primary_publication",
    "notes",
]


class TabletFields(LicenceFields):
    """Catalogue fields shared by create and update (all optional here)."""

    model_config = ConfigDict(extra="forbid")

    p_number: str | None = Field(default=None, pattern=P_NUMBER_PATTERN)
    museum_no: str | None = Field(default=None, max_length=300)
    collection: str | None = Field(default=None, max_length=300)
    owner: str | None = Field(default=None, max_length=300)
    excavation_no: str | None = Field(default=None, max_length=300)
    period: str | None = Field(default=None, max_length=200)
    provenience: str | None = Field(default=None, max_length=200)
    genre: str | None = Field(default=None, max_length=200)
    subgenre: str | None = Field(default=None, max_length=300)
    language: str | None = Field(default=None, max_length=200)
    material: str | None = Field(default=None, max_length=200)
    object_type: str | None = Field(default=None, max_length=200)
    height_mm: float | None = Field(default=None, gt=0, le=2000)
    width_mm: float | None = Field(default=None, gt=0, le=2000)
    thickness_mm: float | None = Field(default=None, gt=0, le=2000)
    primary_publication: str | None = Field(default=None, max_length=5000)
    notes: str | None = Field(default=None, max_length=20000)
    atf: str | None = Field(
        default=None,
        max_length=MAX_ATF_CHARS,
        description="the transliteration in ATF (@obverse, numbered lines '1. a-na ...')",
    )
    is_public: StrictBool | None = None  # 0 / "yes" are refused, not read as booleans
    extra: dict[str, Any] | None = None

    @field_validator("atf", mode="before")
    @classmethod
    def _atf_lines(cls, value):
        # One newline style; a blank text is no text (lines are kept: they are the data).
        if isinstance(value, str):
            value = value.replace("\r\n", "\n").replace("\r", "\n").strip("\n")
            return value if value.strip() else None
        return value

    @field_validator(*[f for f in _TEXT_FIELDS if f != "designation"], mode="before")
    @classmethod
    def _blank_is_none(cls, value):
        if isinstance(value, str):
            value = value.strip()
            return value or None
        return value


class TabletCreate(TabletFields):
    designation: str = Field(min_length=1, max_length=300)
    institution_id: RowId | None = Field(
        default=None, description="admins only; staff create for their own institution"
    )


class TabletUpdate(TabletFields):
    designation: str | None = Field(default=None, min_length=1, max_length=300)
    institution_id: RowId | None = Field(default=None, description="admins only")


class TabletOut(ORMModel):
    id: int
    url: str = ""
    designation: str
    p_number: str | None
    museum_no: str | None
    collection: str | None
    owner: str | None
    excavation_no: str | None
    period: str | None
    provenience: str | None
    genre: str | None
    subgenre: str | None
    language: str | None
    material: str | None
    object_type: str | None
    height_mm: float | None
    width_mm: float | None
    thickness_mm: float | None
    primary_publication: str | None
    notes: str | None
    atf: str | None = Field(default=None, description="the transliteration (ATF)")
    licence: str | None = Field(description="the record's own licence (null: the institution's)")
    attribution: str | None
    effective_licence: str | None = Field(
        default=None, description="the licence that applies: the record's or its institution's"
    )
    effective_attribution: str | None = None
    cdli_url: str | None = Field(default=None, description="the CDLI artifact page (P-numbers)")
    institution_id: int | None
    institution: str | None = None
    is_public: bool
    has_3d: bool
    extra: dict[str, Any]
    created_at: datetime
    updated_at: datetime

    @classmethod
    def of(cls, tablet, *, api_prefix: str = "/api/v1") -> TabletOut:
        derived = ("url", "institution", "effective_licence", "effective_attribution", "cdli_url")
        data = {name: getattr(tablet, name) for name in cls.model_fields if name not in derived}
        data["url"] = f"{api_prefix}/tablets/{tablet.id}"
        data["institution"] = tablet.institution.name if tablet.institution else None
        applies = effective(tablet)
        data["effective_licence"] = applies.licence
        data["effective_attribution"] = applies.attribution
        data["cdli_url"] = cdli_url(tablet.p_number)
        return cls.model_validate(data)


class FacetValue(BaseModel):
    value: str | bool | None
    count: int


class SearchPage(BaseModel):
    items: list[TabletOut]
    total: int
    page: int
    page_size: int
    facets: dict[str, list[FacetValue]]


# --- transliterations and annotations (issue 20) --------------------------------------------


class SignOut(BaseModel):
    index: int
    text: str
    reference: str = Field(description="the ATF-style reference of the sign, e.g. 'o 2 3'")


class LineOut(BaseModel):
    number: str
    text: str
    signs: list[SignOut]


class SurfaceOut(BaseModel):
    surface: str = Field(description="o, r, le, re, te or be")
    name: str
    lines: list[LineOut]


class TransliterationOut(BaseModel):
    tablet_id: int
    surfaces: list[SurfaceOut]
    problems: list[str] = Field(description="lines that were not understood (skipped)")


REFERENCE_PATTERN = (
    r"^ *(o|r|obv|rev|le|re|te|be|l\.e\.|r\.e\.|t\.e\.|b\.e\.) +"
    r"[1-9][0-9]{0,3}('{1,2}|[a-z])?\.? +[1-9][0-9]{0,3} *$"
)
Coordinate = Annotated[float, Field(allow_inf_nan=False, ge=-10_000, le=10_000)]
PixelCoordinate = Annotated[float, Field(allow_inf_nan=False, ge=-1, le=1_000_000)]
PointMm = Annotated[list[Coordinate], Field(min_length=3, max_length=3)]
PointPx = Annotated[list[PixelCoordinate], Field(min_length=2, max_length=2)]
MAX_POLYGON_POINTS = 500


class AnnotationFields(BaseModel):
    model_config = ConfigDict(extra="forbid")

    reading: str | None = Field(default=None, max_length=200, description="e.g. 'lugal'")
    comment: str | None = Field(default=None, max_length=10_000)
    polygon_px: list[PointPx] | None = Field(
        default=None,
        min_length=3,
        max_length=MAX_POLYGON_POINTS,
        description="the same points in the image grid [[col, row], ...] of image_face's "
        "image; omitted on a face model: computed from polygon_mm and the pixel size",
    )
    image_face: str | None = Field(
        default=None,
        pattern=r"^[a-z]{1,32}$",
        description="the face whose image polygon_px is on (default: the model's face)",
    )

    @field_validator("reading", "comment", mode="before")
    @classmethod
    def _blank_is_none(cls, value):
        return (value.strip() or None) if isinstance(value, str) else value


def _reference(value):
    if not isinstance(value, str):
        return value
    try:
        return parse_reference(value).text
    except ReferenceError_ as exc:
        # The message names the bad part (surface, line or sign) without pydantic's prefix.
        raise PydanticCustomError("reference", str(exc)) from exc


class AnnotationIn(AnnotationFields):
    """A new annotation of a model version: a region tied to a sign of the text."""

    reference: str = Field(
        max_length=40,
        json_schema_extra={"pattern": REFERENCE_PATTERN},
        description="ATF-style: surface line sign, e.g. 'o 2 3' = obverse, line 2, sign 3 "
        "(surfaces o, r, le, re, te, be)",
    )
    polygon_mm: list[PointMm] = Field(
        min_length=3,
        max_length=MAX_POLYGON_POINTS,
        description="the region's outline [[x, y, z], ...] in the model's scan frame, mm",
    )

    @field_validator("reference", mode="before")
    @classmethod
    def _check_reference(cls, value):
        return _reference(value)


class AnnotationUpdate(AnnotationFields):
    """Fields left out stay; ``null`` clears reading, comment or the image polygon."""

    reference: str = Field(
        default=None,
        max_length=40,
        json_schema_extra={"pattern": REFERENCE_PATTERN},
        description="omit to keep; null is refused",
    )
    polygon_mm: list[PointMm] = Field(
        default=None, min_length=3, max_length=MAX_POLYGON_POINTS, description="omit to keep"
    )

    @field_validator("reference", mode="before")
    @classmethod
    def _check_reference(cls, value):
        return _reference(value)


class TextualBodyOut(BaseModel):
    type: str = "TextualBody"
    purpose: str = Field(description="identifying (the reference), describing, commenting")
    value: str
    format: str = "text/plain"


class SelectorOut(BaseModel):
    type: str = Field(description="WktSelector (mm), SvgSelector or FragmentSelector (pixels)")
    value: str
    conformsTo: str | None = None


class SourceOut(BaseModel):
    id: str
    type: str
    format: str | None = None


class TargetOut(BaseModel):
    type: str = "SpecificResource"
    source: SourceOut
    selector: list[SelectorOut]


class CreatorOut(BaseModel):
    id: str
    type: str = "Person"
    name: str


class ReferenceOut(BaseModel):
    text: str
    surface: str
    line: str
    sign: int


class WebAnnotationOut(BaseModel):
    """A W3C Web Annotation (JSON-LD) plus plain facts for our clients (model version)."""

    model_config = ConfigDict(populate_by_name=True)

    context: str = Field(alias="@context")
    id: str
    type: str = "Annotation"
    motivation: str
    created: datetime
    modified: datetime
    creator: CreatorOut | None = None
    body: list[TextualBodyOut]
    target: list[TargetOut]
    annotationId: int
    tabletId: int
    modelId: int
    modelVersion: int
    face: str = Field(description="the model's face, or 'tablet' for a whole-tablet model")
    reference: ReferenceOut
    reading: str | None = None
    comment: str | None = None
    polygonMm: list[list[float]]
    polygonPx: list[list[float]] | None = None
    imageFace: str | None = None
    creatorId: int | None = None


class AnnotationPageOut(BaseModel):
    model_config = ConfigDict(populate_by_name=True)

    context: str = Field(alias="@context")
    id: str
    type: str = "AnnotationPage"
    startIndex: int = 0
    total: int
    items: list[WebAnnotationOut]
