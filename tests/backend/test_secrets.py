"""Production refuses placeholder and low-entropy secrets (issue 16, item 1)."""

from __future__ import annotations

import random
import secrets
import string

import pytest
from pydantic import ValidationError

from backend.secret_policy import (
    KNOWN_PLACEHOLDERS,
    MIN_SECRET_BITS,
    estimated_bits,
    placeholder_in,
    secret_problem,
)
from backend.settings import Settings

GOOD = "Yq3hV-0sLk2_ZpR8wNe4TfUa7cXm1JbG9oDiHrKv6Qy5"  # secrets.token_urlsafe(33), fixed


def _production(**values) -> Settings:
    values.setdefault("secret_key", GOOD)
    values.setdefault("public_url", "https://library.example.org")
    return Settings(_env_file=None, environment="production", **values)


@pytest.mark.parametrize(
    "value",
    [
        "replace-with-a-long-random-string",
        "REPLACE_WITH_A_LONG_RANDOM_STRING",
        "Replace With A Long Random String!!",
        "r3pl4ce-w1th-a-l0ng-r4nd0m-str1ng",
        "replace-me" * 5,
        "gnirts-modnar-gnol-a-htiw-ecalper",
        "prefix-replace-with-a-long-random-string-suffix",
        "changeme-changeme-changeme-changeme",
        "CHANGE.ME",
    ],
)
def test_placeholders_and_their_variants_are_recognised(value):
    assert placeholder_in(value) is not None
    assert "placeholder" in secret_problem(value)


def test_every_known_placeholder_is_refused():
    for value in KNOWN_PLACEHOLDERS:
        assert secret_problem(value) is not None, value


@pytest.mark.parametrize(
    "value",
    [
        "a" * 40,
        "abcdefghijklmnopqrstuvwxyz0123456789",
        "abcd" * 10,
        "0123456789" * 4,
        "qwertyuiopasdfghjklzxcvbnm1234567890",
        "Password123!" * 3,
    ],
)
def test_low_entropy_secrets_are_refused(value):
    assert estimated_bits(value) < MIN_SECRET_BITS
    assert secret_problem(value) is not None


def test_random_url_safe_secrets_of_32_chars_pass():
    rng = random.Random(16)
    alphabet = string.ascii_letters + string.digits + "-_"
    for _ in range(300):
        value = "".join(rng.choice(alphabet) for _ in range(32))
        assert secret_problem(value) is None, (value, estimated_bits(value))
    for value in (secrets.token_urlsafe(48), secrets.token_hex(32)):
        assert secret_problem(value) is None, value


def test_production_names_the_variable_and_how_to_generate_one(tmp_path):
    with pytest.raises(ValidationError) as caught:
        _production(data_dir=tmp_path, secret_key="x" * 64)
    message = str(caught.value)
    assert "HAMMURABI_SECRET_KEY" in message and "token_urlsafe" in message


def test_production_checks_the_other_secrets_it_holds(tmp_path):
    with pytest.raises(ValidationError) as caught:
        _production(
            data_dir=tmp_path,
            s3_secret_access_key="replace-with-at-least-8-chars",
            database_url="postgresql+psycopg://hammurabi:replace-me@postgres:5432/hammurabi",
        )
    message = str(caught.value)
    assert "HAMMURABI_S3_SECRET_ACCESS_KEY" in message
    assert "HAMMURABI_DATABASE_URL" in message
    assert "postgres:5432" not in message  # the URL (with its password) is not echoed
    good = secrets.token_urlsafe(24)
    settings = _production(
        data_dir=tmp_path,
        s3_secret_access_key=secrets.token_urlsafe(24),
        database_url=f"postgresql+psycopg://hammurabi:{good}@postgres:5432/hammurabi",
    )
    assert settings.signing_secret == GOOD


def test_development_does_not_check(tmp_path):
    settings = Settings(_env_file=None, data_dir=tmp_path, secret_key="changeme")
    assert settings.signing_secret == "changeme"
