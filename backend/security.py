"""Passwords (argon2id), API tokens (sha256 of a random secret), signed session cookies and
the login rate limiter.

argon2id needs 64 MiB per hash (RFC 9106's low-memory profile); at most
``set_hash_concurrency(n)`` hashes run at once in this process, the rest wait, so 40
concurrent logins cost ``n`` × 64 MiB, not 40 × 64 MiB.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError
from itsdangerous import BadSignature, SignatureExpired, URLSafeTimedSerializer

TOKEN_PREFIX = "hmr_"
TOKEN_DISPLAY_CHARS = 12  # "hmr_" + 8 characters of the secret, shown in token lists

# argon2-cffi's defaults are RFC 9106's "low memory" argon2id profile.
_hasher = PasswordHasher()
DEFAULT_HASH_CONCURRENCY = 2
_hash_slots = threading.BoundedSemaphore(DEFAULT_HASH_CONCURRENCY)


def set_hash_concurrency(slots: int) -> None:
    """How many argon2 hashes may run at once in this process (``create_app`` sets it from
    ``Settings.password_hash_concurrency``)."""
    global _hash_slots
    if slots < 1:
        raise ValueError(f"password hash concurrency must be at least 1, not {slots}")
    _hash_slots = threading.BoundedSemaphore(slots)


def hash_password(password: str) -> str:
    if not password:
        raise ValueError("password must not be empty")
    with _hash_slots:
        return _hasher.hash(password)


def verify_password(password_hash: str | None, password: str) -> bool:
    if not password_hash:
        return False
    with _hash_slots:
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


class LoginLimiter:
    """Sliding-window limit on login attempts, per account and per client address.

    Each attempt is recorded *before* the password is checked (so concurrent attempts cannot
    slip past the limit) and taken back when it succeeds: in effect the window counts failed
    and in-flight attempts. In-process memory: one server process; with several processes or
    servers each keeps its own counts (docs/admin.md).

    ``clock`` (seconds, monotonic) is injectable for tests.
    """

    def __init__(
        self,
        *,
        per_account: int,
        per_address: int,
        window_s: float,
        clock: Callable[[], float] = time.monotonic,
        max_keys: int = 100_000,
    ):
        if per_account < 1 or per_address < 1 or window_s <= 0:
            raise ValueError("login limits must be at least 1 attempt in a positive window")
        self._limits = {"account": per_account, "address": per_address}
        self._window_s = window_s
        self._clock = clock
        self._max_keys = max_keys
        self._attempts: dict[tuple[str, str], deque[float]] = {}
        self._lock = threading.Lock()

    def attempt(self, *, account: str, address: str) -> int | None:
        """Record an attempt; None when allowed, else the seconds to wait (Retry-After)."""
        now = self._clock()
        keys = (("account", account), ("address", address))
        with self._lock:
            waits = [self._wait_s(key, now) for key in keys]
            if any(w is not None for w in waits):
                return max(w for w in waits if w is not None)
            if len(self._attempts) + len(keys) > self._max_keys:
                self._forget_expired(now, room=len(keys))
            for key in keys:
                self._attempts.setdefault(key, deque()).append(now)
        return None

    def succeeded(self, *, account: str, address: str) -> None:
        """The password was right: the account starts afresh, the address gets its try back."""
        with self._lock:
            self._attempts.pop(("account", account), None)
            times = self._attempts.get(("address", address))
            if times:
                times.pop()

    def _wait_s(self, key: tuple[str, str], now: float) -> int | None:
        times = self._attempts.get(key)
        if not times:
            return None
        while times and times[0] <= now - self._window_s:
            times.popleft()
        if not times:
            del self._attempts[key]
            return None
        if len(times) < self._limits[key[0]]:
            return None
        return max(1, math.ceil(times[0] + self._window_s - now))

    def _forget_expired(self, now: float, *, room: int) -> None:
        for key in list(self._attempts):
            self._wait_s(key, now)
        # Still full (a spray of distinct names): drop the oldest keys rather than grow.
        excess = len(self._attempts) + room - self._max_keys
        for key in list(self._attempts)[: max(0, excess)]:
            del self._attempts[key]
