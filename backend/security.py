"""Passwords (argon2id), API tokens (sha256 of a random secret) and signed session cookies."""

from __future__ import annotations

import hashlib
import hmac
import secrets

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError
from itsdangerous import BadSignature, SignatureExpired, URLSafeTimedSerializer

TOKEN_PREFIX = "hmr_"
TOKEN_DISPLAY_CHARS = 12  # "hmr_" + 8 characters of the secret, shown in token lists

# argon2-cffi's defaults are RFC 9106's "low memory" argon2id profile.
_hasher = PasswordHasher()


def hash_password(password: str) -> str:
    if not password:
        raise ValueError("password must not be empty")
    return _hasher.hash(password)


def verify_password(password_hash: str | None, password: str) -> bool:
    if not password_hash:
        return False
    try:
        return _hasher.verify(password_hash, password)
    except (VerificationError, InvalidHashError):
        return False


def new_token_secret() -> str:
    """A fresh API token secret: ``hmr_`` + 43 url-safe characters (256 random bits)."""
    return TOKEN_PREFIX + secrets.token_urlsafe(32)


def token_hash(secret: str) -> str:
    """What we store: sha256 hex of the secret (secrets are random, so no salt is needed)."""
    return hashlib.sha256(secret.encode()).hexdigest()


def token_display_prefix(secret: str) -> str:
    return secret[:TOKEN_DISPLAY_CHARS]


def constant_time_equal(a: str, b: str) -> bool:
    return hmac.compare_digest(a.encode(), b.encode())


class SessionSigner:
    """Signs and reads the session cookie: ``{"uid": user_id}`` with a timestamp."""

    def __init__(self, secret: str, *, max_age_s: int):
        self._serializer = URLSafeTimedSerializer(secret, salt="hammurabi-session")
        self._max_age_s = max_age_s

    def dumps(self, user_id: int) -> str:
        return self._serializer.dumps({"uid": user_id})

    def loads(self, cookie: str) -> int | None:
        """The user id in a valid, unexpired cookie; None for anything else."""
        try:
            data = self._serializer.loads(cookie, max_age=self._max_age_s)
        except (BadSignature, SignatureExpired):
            return None
        uid = data.get("uid") if isinstance(data, dict) else None
        return uid if isinstance(uid, int) else None
