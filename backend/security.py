"""Passwords (argon2id), API tokens (sha256 of a random secret) and signed session cookies."""

from __future__ import annotations

import hashlib
import hmac
import secrets
from dataclasses import dataclass

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


@dataclass(frozen=True)
class SessionClaim:
    """What a valid session cookie says: the user and the user's session version then."""

    user_id: int
    session_version: int


class SessionSigner:
    """Signs and reads the session cookie: ``{"uid": user_id, "sv": session_version}`` with a
    timestamp. The cookie is valid only while ``users.session_version`` still equals ``sv``
    (checked by backend.api.deps), so bumping it revokes every cookie of the user."""

    def __init__(self, secret: str, *, max_age_s: int):
        self._serializer = URLSafeTimedSerializer(secret, salt="hammurabi-session")
        self._max_age_s = max_age_s

    def dumps(self, user_id: int, session_version: int) -> str:
        return self._serializer.dumps({"uid": user_id, "sv": session_version})

    def loads(self, cookie: str) -> SessionClaim | None:
        """The claim of a valid, unexpired cookie; None for anything else (cookies from before
        session versions, without ``sv``, included)."""
        try:
            data = self._serializer.loads(cookie, max_age=self._max_age_s)
        except (BadSignature, SignatureExpired):
            return None
        if not isinstance(data, dict):
            return None
        uid, version = data.get("uid"), data.get("sv")
        if type(uid) is not int or type(version) is not int:
            return None
        return SessionClaim(user_id=uid, session_version=version)
