"""How strong a production secret must be: not a known placeholder or anything made from one,
and enough estimated entropy. Pure functions of the value; backend.settings applies them to
every secret it holds when ``HAMMURABI_ENVIRONMENT=production``.
"""

from __future__ import annotations

import math
import re
import string

MIN_SECRET_CHARS = 32
MIN_SECRET_BITS = 128
GENERATE_HINT = 'generate one with: python -c "import secrets; print(secrets.token_urlsafe(48))"'

# Values shipped in .env.example, docs and tutorials, and the usual defaults. The production
# code keeps its own list (it must not depend on a file of the source tree being present);
# tests/test_compose.py checks that every value of .env.example is refused.
KNOWN_PLACEHOLDERS = (
    "replace-with-a-long-random-string",
    "replace-with-at-least-8-chars",
    "replace-me",
    "replace",
    "changeme",
    "change-me",
    "changethis",
    "change-this",
    "secret",
    "secret-key",
    "your-secret-key",
    "supersecret",
    "password",
    "passw0rd",
    "hammurabi",
    "minioadmin",
    "postgres",
    "admin",
    "default",
    "example",
    "placeholder",
    "insecure",
    "development",
    "dev",
    "test",
    "todo",
    "xxx",
    "letmein",
    "qwerty",
    "12345678",
)
# Look-alike characters folded before comparing ("R3pl4ce-me" is still "replace-me").
_LOOKALIKES = str.maketrans("013457@$!|", "oieastasil")
# A placeholder at least this long (normalised) is refused anywhere inside a secret; shorter
# ones only as the whole secret, since "dev" occurs by chance in 1 of ~500 random keys.
_CONTAINED_MIN_CHARS = 6
_KEYBOARD_ROWS = ("1234567890", "qwertyuiop", "asdfghjkl", "zxcvbnm")


def _normalised(value: str) -> str:
    """Lower case, look-alikes folded, everything but letters and digits dropped."""
    return re.sub(r"[^a-z0-9]", "", value.lower().translate(_LOOKALIKES))


def _shortest_unit(value: str) -> str:
    """``value`` without repetition: "abcabcabc" -> "abc"."""
    for size in range(1, len(value) // 2 + 1):
        if len(value) % size == 0 and value[:size] * (len(value) // size) == value:
            return value[:size]
    return value


_NORMALISED_PLACEHOLDERS = tuple(_normalised(p) for p in KNOWN_PLACEHOLDERS)


def placeholder_in(value: str) -> str | None:
    """The known placeholder ``value`` equals, contains or repeats, if any.

    Compared after :func:`_normalised`, forwards and reversed, whole or de-repeated.
    """
    norm = _normalised(value)
    candidates = {norm, norm[::-1], _shortest_unit(norm), _shortest_unit(norm)[::-1]}
    for original, placeholder in zip(KNOWN_PLACEHOLDERS, _NORMALISED_PLACEHOLDERS, strict=True):
        for candidate in candidates:
            if candidate == placeholder or (
                len(placeholder) >= _CONTAINED_MIN_CHARS and placeholder in candidate
            ):
                return original
    return None


def _alphabet_size(value: str) -> int:
    """Size of the character classes ``value`` draws from (hex counts as one class of 16)."""
    if set(value) <= set("0123456789abcdef") or set(value) <= set("0123456789ABCDEF"):
        return 16
    classes = (string.ascii_lowercase, string.ascii_uppercase, string.digits, string.punctuation)
    size = sum(len(chars) for chars in classes if any(c in chars for c in value))
    if any(c.isspace() for c in value):
        size += 1
    if any(ord(c) > 127 for c in value):
        size += 100
    return max(size, 1)


def _predictable_chars(value: str) -> int:
    """Characters that continue a pattern: a run with a constant step of -1, 0 or +1
    ("aaa", "abc", "321"), a stretch of a keyboard row ("qwe"), or a repeat of the three
    characters some period earlier ("abcabc"). By chance a random key has almost none."""
    codes = [ord(c) for c in value]
    rows = "".join(f" {row} {row[::-1]}" for row in _KEYBOARD_ROWS)
    count = 0
    for i in range(2, len(codes)):
        step = codes[i] - codes[i - 1]
        trigram = value[i - 2 : i + 1].lower()
        if (
            (abs(step) <= 1 and step == codes[i - 1] - codes[i - 2])
            or trigram in rows
            or any(codes[i - 2 : i + 1] == codes[i - 2 - p : i + 1 - p] for p in range(1, i - 1))
        ):
            count += 1
    return count


def estimated_bits(value: str) -> float:
    """A conservative estimate of the entropy of ``value`` in bits.

    ``(len - predictable) * log2(alphabet) * variety``: the alphabet is the sum of the
    character classes used (as in NIST SP 800-63-1 appendix A and zxcvbn's brute-force
    bound), characters continuing a sequence, keyboard walk or repetition count nothing
    (zxcvbn's sequence/spatial/repeat matchers, much simplified), and ``variety`` is the
    number of distinct characters over the number expected from a uniform draw of ``len``
    from the alphabet, ``K (1 - (1 - 1/K)^len)`` (capped at 1). A ``token_urlsafe(24)``
    (32 characters, 192 random bits) scores 132-260, ``"a" * 32`` under 1.
    """
    if not value:
        return 0.0
    alphabet = _alphabet_size(value)
    expected_distinct = alphabet * (1 - (1 - 1 / alphabet) ** len(value))
    variety = min(1.0, len(set(value)) / expected_distinct)
    return (len(value) - _predictable_chars(value)) * math.log2(alphabet) * variety


def secret_problem(value: str | None, *, min_chars: int = MIN_SECRET_CHARS) -> str | None:
    """Why ``value`` is not acceptable as a production secret, or None when it is."""
    if not value or not value.strip():
        return "is not set"
    placeholder = placeholder_in(value)
    if placeholder is not None:
        return f"is (or is made from) the placeholder {placeholder!r}"
    if len(value) < min_chars:
        return f"is too short ({len(value)} characters, need at least {min_chars})"
    bits = estimated_bits(value)
    if bits < MIN_SECRET_BITS:
        return f"is too predictable (about {bits:.0f} bits of entropy, need {MIN_SECRET_BITS})"
    return None
