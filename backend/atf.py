"""A small pure parser for the subset of ATF that ties a sign to a place on the tablet.

ATF (ASCII Transliteration Format, CDLI/ORACC: https://oracc.museum.upenn.edu/doc/help/editinginatf/)
writes a transliteration as structure lines (``@obverse``, ``@reverse``, ``@left`` …),
numbered text lines (``1. a-na {d}utu``, primed ``1'.`` where the start is broken) and lines
we skip here (``&`` text headers, ``#`` comments and protocols, ``$`` state notes, ``>>`` links,
``==`` parallels). A sign is a word part between spaces, hyphens and dots; a determinative in
braces (``{d}``) is a sign of its own. Flags (``#?!*``) and brackets stay in a sign's text (they
are what the editor saw) and are stripped only to compare readings.

A reference is ATF-style ``<surface> <line> <sign>``: ``o 2 3`` is the third sign of line 2 of
the obverse. Surfaces: ``o`` obverse, ``r`` reverse, ``le`` ``re`` ``te`` ``be`` the left,
right, top and bottom edges (``l.e.`` etc. accepted, as CDLI writes them).

No I/O: text in, dataclasses out; problems are returned (or raised as :class:`ReferenceError_`
with the part that is wrong), never printed.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

# Surface abbreviation (as in references) -> ATF structure keyword.
SURFACES: dict[str, str] = {
    "o": "obverse",
    "r": "reverse",
    "le": "left",
    "re": "right",
    "te": "top",
    "be": "bottom",
}
_KEYWORD_TO_ABBREV = {keyword: abbrev for abbrev, keyword in SURFACES.items()}
# Other spellings of a surface in references (CDLI writes "l.e."; people write "obv.").
_ALIASES = {
    "obv": "o",
    "obverse": "o",
    "rev": "r",
    "reverse": "r",
    "l.e": "le",
    "r.e": "re",
    "t.e": "te",
    "b.e": "be",
    "left": "le",
    "right": "re",
    "top": "te",
    "bottom": "be",
}
# ASCII digits only (Python's \d also takes other scripts' digits): the documented pattern.
_LINE_NUMBER = re.compile(r"^([1-9][0-9]{0,3})('{1,2}|[a-z])?$")
_SIGN_NUMBER = re.compile(r"^[1-9][0-9]{0,3}$")
_TEXT_LINE = re.compile(r"^([0-9]+'{0,2}[a-z]?)\.\s*(.*)$")
_SIGN = re.compile(r"\{[^{}\s]*\}|[^\s{}.\-]+")
_FLAGS = re.compile(r"[#?!*\[\]⸢⸣<>()]")
MAX_ATF_CHARS = 200_000


@dataclass(frozen=True)
class Sign:
    index: int  # 1-based position in its line
    text: str  # as written (flags and brackets kept)


@dataclass(frozen=True)
class Line:
    number: str  # "2", "3'", "4a"
    text: str
    signs: tuple[Sign, ...]


@dataclass
class Surface:
    abbrev: str  # o, r, le, re, te, be
    name: str  # obverse, reverse, left, ...
    lines: list[Line] = field(default_factory=list)


@dataclass
class Transliteration:
    surfaces: list[Surface]
    problems: list[str]  # "line N: ..." for lines that were skipped

    def surface(self, abbrev: str) -> Surface | None:
        return next((s for s in self.surfaces if s.abbrev == abbrev), None)


@dataclass(frozen=True)
class Reference:
    surface: str  # abbreviation
    line: str  # line number as in ATF ("2", "3'")
    sign: int  # 1-based

    @property
    def text(self) -> str:
        return f"{self.surface} {self.line} {self.sign}"


class ReferenceError_(ValueError):
    """A reference that cannot be read; ``part`` names the culprit (surface, line, sign)."""

    def __init__(self, part: str, message: str):
        super().__init__(message)
        self.part = part


def split_signs(text: str) -> tuple[Sign, ...]:
    """The signs of a line's text: separated by spaces, hyphens and dots; ``{d}`` apart."""
    return tuple(Sign(i, s) for i, s in enumerate(_SIGN.findall(text), 1))


def bare(sign_text: str) -> str:
    """A sign without flags and brackets, lower case: for comparing readings."""
    return _FLAGS.sub("", sign_text).lower()


def parse_atf(text: str) -> Transliteration:
    """Surfaces and numbered lines of an ATF text (the subset described in the module doc).

    Text lines before any surface line go to the obverse (ATF's default). Lines that are
    neither structure nor numbered text nor one of the skipped kinds are reported.
    """
    surfaces: list[Surface] = []
    problems: list[str] = []
    current: Surface | None = None
    for number, raw in enumerate(text.replace("\r\n", "\n").replace("\r", "\n").split("\n"), 1):
        line = raw.strip()
        if not line or line[0] in "&#$" or line.startswith((">>", "<<", "||", "==")):
            continue
        if line.startswith("@"):
            keyword = line[1:].split()[0].lower() if len(line) > 1 else ""
            if keyword in _KEYWORD_TO_ABBREV:
                abbrev = _KEYWORD_TO_ABBREV[keyword]
                current = next((s for s in surfaces if s.abbrev == abbrev), None)
                if current is None:
                    current = Surface(abbrev, keyword)
                    surfaces.append(current)
            elif keyword == "edge":
                # "@edge" alone names no side: kept as the bottom edge, the usual one.
                current = _surface(surfaces, "be")
            # @tablet, @column, @seal, @h1 …: structure we do not need for references.
            continue
        match = _TEXT_LINE.match(line)
        if match is None:
            problems.append(f"line {number}: not a numbered text line ({line[:40]!r})")
            continue
        if current is None:
            current = _surface(surfaces, "o")
        current.lines.append(
            Line(number=match.group(1), text=match.group(2), signs=split_signs(match.group(2)))
        )
    return Transliteration(surfaces=surfaces, problems=problems)


def _surface(surfaces: list[Surface], abbrev: str) -> Surface:
    found = next((s for s in surfaces if s.abbrev == abbrev), None)
    if found is None:
        found = Surface(abbrev, SURFACES[abbrev])
        surfaces.append(found)
    return found


def parse_reference(text: str) -> Reference:
    """``"o 2 3"`` -> Reference("o", "2", 3); ReferenceError_ naming the bad part."""
    if not isinstance(text, str) or not text.strip():
        raise ReferenceError_("reference", "must be like 'o 2 3' (surface, line, sign)")
    parts = text.strip().split()
    if len(parts) != 3:
        raise ReferenceError_(
            "reference",
            f"{text.strip()!r} has {len(parts)} part(s); need 3: surface, line, sign "
            "(e.g. 'o 2 3' = obverse, line 2, sign 3)",
        )
    surface_text, line_text, sign_text = parts
    key = surface_text.lower().rstrip(".")
    surface = key if key in SURFACES else _ALIASES.get(key)
    if surface is None:
        raise ReferenceError_(
            "surface",
            f"surface {surface_text!r} is not one of {', '.join(SURFACES)} "
            "(obverse, reverse, left, right, top, bottom edge)",
        )
    line_text = line_text.rstrip(".")
    line_match = _LINE_NUMBER.match(line_text)
    if line_match is None or int(line_match.group(1)) == 0:
        raise ReferenceError_(
            "line", f"line {line_text!r} is not a line number (1, 2, 3' or 4a; from 1)"
        )
    if not _SIGN_NUMBER.match(sign_text):
        raise ReferenceError_("sign", f"sign {sign_text!r} is not a sign number (1 to 9999)")
    return Reference(surface=surface, line=line_text, sign=int(sign_text))


def reference_prefix(text: str) -> str | None:
    """A query that is the start of a reference (``r``, ``r 1``, ``o 2 3``), normalised; None
    for other text. Lets a search for ``r 1`` find line 1 of the reverse, not every "r"."""
    parts = text.strip().split()
    if not 1 <= len(parts) <= 3:
        return None
    key = parts[0].lower().rstrip(".")
    surface = key if key in SURFACES else _ALIASES.get(key)
    if surface is None or (len(parts) == 1 and key not in SURFACES):
        return None
    if len(parts) == 3:
        try:
            return parse_reference(text).text
        except ReferenceError_:
            return None
    if len(parts) == 2:
        line = parts[1].rstrip(".")
        match = _LINE_NUMBER.match(line)
        return f"{surface} {line}" if match and int(match.group(1)) > 0 else None
    return surface


def check_against(reference: Reference, transliteration: Transliteration) -> Sign:
    """The sign ``reference`` names in ``transliteration``; ReferenceError_ when it has none."""
    surface = transliteration.surface(reference.surface)
    if surface is None:
        have = ", ".join(s.abbrev for s in transliteration.surfaces) or "none"
        raise ReferenceError_(
            "surface",
            f"the transliteration has no {SURFACES[reference.surface]} "
            f"(surface {reference.surface!r}; it has {have})",
        )
    line = next((ln for ln in surface.lines if ln.number == reference.line), None)
    if line is None:
        numbers = ", ".join(ln.number for ln in surface.lines[:12]) or "no lines"
        raise ReferenceError_(
            "line",
            f"the {surface.name} has no line {reference.line!r} (it has {numbers}"
            f"{', …' if len(surface.lines) > 12 else ''})",
        )
    if reference.sign > len(line.signs):
        raise ReferenceError_(
            "sign",
            f"line {line.number} of the {surface.name} has {len(line.signs)} sign(s), "
            f"not {reference.sign}",
        )
    return line.signs[reference.sign - 1]
