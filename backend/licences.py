"""Licence and attribution of a record: its own, else its tablet's, else its institution's.

A licence is a Creative Commons or RightsStatements.org URI (what IIIF ``rights`` accepts);
an attribution is the credit line a reuser must show ("Courtesy of ..."). Manifests, exports
and citations all ask :func:`effective` so they never disagree.
"""

from __future__ import annotations

from dataclasses import dataclass

from backend.iiif import is_rights_uri

LICENCE_DESCRIPTION = (
    "a Creative Commons licence or RightsStatements.org statement URI, e.g. "
    "https://creativecommons.org/licenses/by/4.0/ ; null: the institution's default"
)


@dataclass(frozen=True)
class Licence:
    licence: str | None
    attribution: str | None


def check_licence(value: str | None) -> str | None:
    """``value``, or ValueError naming what a licence must be."""
    if value is None:
        return None
    if not is_rights_uri(value):
        raise ValueError(f"must be {LICENCE_DESCRIPTION.split(' ; ')[0]}, not {value!r}")
    return value


def effective(tablet, model=None) -> Licence:
    """The licence and attribution that apply to ``model`` of ``tablet`` (or the tablet)."""
    institution = getattr(tablet, "institution", None)
    chain = [c for c in (model, tablet, institution) if c is not None]
    licence = next((c.licence for c in chain if c.licence), None)
    attribution = next((c.attribution for c in chain if c.attribution), None)
    if attribution is None:
        holder = tablet.owner or (institution.name if institution is not None else None)
        attribution = f"Courtesy of {holder}" if holder else None
    return Licence(licence=licence, attribution=attribution)
