"""The ATF subset parser and ATF-style references (backend.atf): pure functions."""

from __future__ import annotations

import pytest

from backend.atf import (
    ReferenceError_,
    bare,
    check_against,
    parse_atf,
    parse_reference,
    split_signs,
)

LETTER = """&P123456 = AbB 1, 1
#atf: lang akk
@tablet
@obverse
1. a-na {d}utu-ha-zi-ir
2. qi2-bi2-ma
$ rest of obverse broken
@reverse
1'. [um]-ma# {m}ha-am-mu-ra-pi#?
2'. dub.sar
# a comment
@left
1. 3(disz) iti
something odd
"""


def test_surfaces_lines_and_signs():
    parsed = parse_atf(LETTER)
    assert [s.abbrev for s in parsed.surfaces] == ["o", "r", "le"]
    obverse, reverse, left = parsed.surfaces
    assert [line.number for line in obverse.lines] == ["1", "2"]
    assert [s.text for s in obverse.lines[0].signs] == ["a", "na", "{d}", "utu", "ha", "zi", "ir"]
    assert [s.index for s in obverse.lines[1].signs] == [1, 2, 3]
    assert [line.number for line in reverse.lines] == ["1'", "2'"]
    # Flags and brackets stay in the sign (the editor's observation); dots separate logograms.
    assert [s.text for s in reverse.lines[0].signs][:2] == ["[um]", "ma#"]
    assert [s.text for s in reverse.lines[1].signs] == ["dub", "sar"]
    assert [s.text for s in left.lines[0].signs] == ["3(disz)", "iti"]
    assert parsed.problems == ["line 14: not a numbered text line ('something odd')"]


def test_lines_before_any_surface_are_on_the_obverse_and_crlf_is_fine():
    parsed = parse_atf("1. lugal\r\n2. e2-gal\r\n@reverse\r\n1. x")
    assert [s.abbrev for s in parsed.surfaces] == ["o", "r"]
    assert [ln.text for ln in parsed.surfaces[0].lines] == ["lugal", "e2-gal"]
    assert parse_atf("").surfaces == [] and parse_atf("").problems == []


def test_split_and_bare():
    assert [s.text for s in split_signs("  ")] == []
    assert [s.text for s in split_signs("{gisz}tukul-ti")] == ["{gisz}", "tukul", "ti"]
    assert bare("⸢ma⸣#?") == "ma" and bare("[LUGAL]!") == "lugal"


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("o 2 3", "o 2 3"),
        ("  O  12 1 ", "o 12 1"),
        ("r 3' 4", "r 3' 4"),
        ("l.e. 1 2", "le 1 2"),
        ("obv 1. 1", "o 1 1"),
        ("be 4a 10", "be 4a 10"),
    ],
)
def test_references_that_read(text, expected):
    assert parse_reference(text).text == expected


@pytest.mark.parametrize(
    ("text", "part", "words"),
    [
        ("x 2 3", "surface", "surface 'x' is not one of o, r, le, re, te, be"),
        ("o zero 3", "line", "line 'zero' is not a line number"),
        ("o 0 3", "line", "line '0'"),
        ("o 2 0", "sign", "sign '0' is not a sign number"),
        ("o 2 b", "sign", "sign 'b'"),
        ("o 2", "reference", "has 2 part(s); need 3"),
        ("", "reference", "must be like 'o 2 3'"),
    ],
)
def test_bad_references_name_the_bad_part(text, part, words):
    with pytest.raises(ReferenceError_) as caught:
        parse_reference(text)
    assert caught.value.part == part and words in str(caught.value)


def test_a_reference_must_name_a_sign_of_the_text():
    parsed = parse_atf(LETTER)
    assert check_against(parse_reference("o 1 3"), parsed).text == "{d}"
    assert check_against(parse_reference("r 1' 1"), parsed).text == "[um]"
    for text, part, words in [
        ("te 1 1", "surface", "has no top (surface 'te'; it has o, r, le)"),
        ("o 9 1", "line", "the obverse has no line '9' (it has 1, 2)"),
        ("o 2 4", "sign", "line 2 of the obverse has 3 sign(s), not 4"),
    ]:
        with pytest.raises(ReferenceError_) as caught:
            check_against(parse_reference(text), parsed)
        assert caught.value.part == part and words in str(caught.value), str(caught.value)


@pytest.mark.parametrize("text", ["o ٣ 1", "o 1 ٣", "o 12345 1", "o 1 12345", "o 1 01"])
def test_only_ascii_numbers_within_the_documented_pattern(text):
    with pytest.raises(ReferenceError_):
        parse_reference(text)


def test_a_reference_prefix_is_recognised_for_search():
    from backend.atf import reference_prefix

    assert reference_prefix("R 1") == "r 1" and reference_prefix("o 2 3") == "o 2 3"
    assert reference_prefix("be") == "be" and reference_prefix("obv") is None
    assert reference_prefix("lugal") is None and reference_prefix("o 2 x") is None
