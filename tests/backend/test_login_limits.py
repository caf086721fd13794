"""Login is rate-limited per account and per address (429 + Retry-After), and argon2 runs at
most ``password_hash_concurrency`` hashes at once (issue 16, item 6)."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
from fastapi.testclient import TestClient

from backend import security
from backend.main import create_app
from backend.security import LoginLimiter
from tests.backend.conftest import PASSWORD, build_world, make_settings

LOGIN = "/api/v1/auth/login"


class Clock:
    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s


@pytest.fixture
def limited(sqlite_url, tmp_path, password_hash):
    """An app allowing 3 failures per account and 5 per address in 60 s, on a fake clock."""
    settings = make_settings(
        sqlite_url,
        tmp_path,
        login_max_attempts_per_account=3,
        login_max_attempts_per_address=5,
        login_window_s=60.0,
    )
    app = create_app(settings)
    clock = Clock()
    app.state.login_limiter = LoginLimiter(per_account=3, per_address=5, window_s=60.0, clock=clock)
    world = build_world(app.state.sessionmaker, password_hash, settings)
    with TestClient(app) as client:
        yield client, world, clock
    app.state.engine.dispose()


def _login(client, email, password=PASSWORD):
    return client.post(LOGIN, json={"email": email, "password": password})


def test_account_limit_answers_429_with_retry_after_then_resets(limited):
    client, world, clock = limited
    email = world.emails["reader"]
    for _ in range(3):
        assert _login(client, email, "wrong password").status_code == 401
    clock.now_s += 10
    blocked = _login(client, email)  # even the right password waits
    assert blocked.status_code == 429
    assert blocked.headers["Retry-After"] == "50"
    assert blocked.json()["where"] == "body.email"
    clock.now_s += 49.5
    assert _login(client, email).status_code == 429
    clock.now_s += 0.6  # the first failure has left the window
    assert _login(client, email).status_code == 200


def test_a_success_clears_the_account(limited):
    client, world, _clock = limited
    email = world.emails["reader"]
    for _ in range(2):
        assert _login(client, email, "wrong password").status_code == 401
    assert _login(client, email).status_code == 200
    for _ in range(2):
        assert _login(client, email, "wrong password").status_code == 401
    assert _login(client, email).status_code == 200


def test_address_limit_across_accounts(limited):
    client, world, clock = limited
    emails = [world.emails[r] for r in ("reader", "staff_own", "staff_other")]
    for i in range(5):
        assert _login(client, emails[i % 3], "wrong password").status_code == 401
    blocked = _login(client, "someone@example.org", "wrong password")
    assert blocked.status_code == 429 and int(blocked.headers["Retry-After"]) == 60
    clock.now_s += 60
    assert _login(client, world.emails["admin"]).status_code == 200


def test_limiter_counts_attempts_in_flight():
    clock = Clock()
    limiter = LoginLimiter(per_account=2, per_address=100, window_s=30, clock=clock)
    assert limiter.attempt(account="a", address="x") is None
    assert limiter.attempt(account="a", address="y") is None
    assert limiter.attempt(account="a", address="z") == 30  # two not yet answered
    limiter.succeeded(account="a", address="x")
    assert limiter.attempt(account="a", address="z") is None


def test_limiter_memory_is_bounded():
    clock = Clock()
    limiter = LoginLimiter(per_account=1, per_address=10**6, window_s=30, clock=clock, max_keys=50)
    for i in range(500):
        limiter.attempt(account=f"user{i}@example.org", address="x")
    assert len(limiter._attempts) <= 50
    clock.now_s += 31
    for i in range(10):
        assert limiter.attempt(account=f"late{i}@example.org", address="x") is None
    assert len(limiter._attempts) <= 50
    # Under pressure everything older than the window went first: the new keys all stayed.
    assert sum(name.startswith("late") for _kind, name in limiter._attempts) == 10


def test_limiter_refuses_nonsense_limits():
    with pytest.raises(ValueError, match="at least 1"):
        LoginLimiter(per_account=0, per_address=1, window_s=1)


class ProbeHasher:
    """Stands in for argon2: records how many hashes run at the same time."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.running = 0
        self.peak = 0

    def _work(self) -> None:
        with self._lock:
            self.running += 1
            self.peak = max(self.peak, self.running)
        time.sleep(0.02)  # long enough for the other threads to pile up
        with self._lock:
            self.running -= 1

    def verify(self, _hash: str, _password: str) -> bool:
        self._work()
        return False

    def hash(self, _password: str) -> str:
        self._work()
        return "$argon2id$probe"


@pytest.mark.parametrize("slots", [1, 2])
def test_concurrent_hashes_never_exceed_the_bound(monkeypatch, slots):
    probe = ProbeHasher()
    monkeypatch.setattr(security, "_hasher", probe)
    monkeypatch.setattr(security, "_hash_slots", security._hash_slots)  # restored afterwards
    security.set_hash_concurrency(slots)
    with ThreadPoolExecutor(max_workers=20) as pool:
        jobs = [pool.submit(security.verify_password, "$argon2id$x", "pw") for _ in range(30)]
        jobs += [pool.submit(security.hash_password, "pw") for _ in range(10)]
        for job in jobs:
            job.result()
    assert probe.peak == slots


def test_concurrent_wrong_logins_are_bounded_through_the_app(limited, monkeypatch):
    client, world, _clock = limited
    probe = ProbeHasher()
    monkeypatch.setattr(security, "_hasher", probe)
    monkeypatch.setattr(security, "_hash_slots", security._hash_slots)
    security.set_hash_concurrency(2)
    client.app.state.login_limiter = LoginLimiter(per_account=100, per_address=100, window_s=60)
    with ThreadPoolExecutor(max_workers=12) as pool:
        codes = list(
            pool.map(
                lambda _: _login(client, world.emails["reader"], "nope").status_code, range(24)
            )
        )
    assert codes == [401] * 24
    assert probe.peak == 2


def test_settings_size_the_hash_slots(sqlite_url, tmp_path, monkeypatch):
    monkeypatch.setattr(security, "_hash_slots", security._hash_slots)
    app = create_app(make_settings(sqlite_url, tmp_path, password_hash_concurrency=3))
    with TestClient(app) as client:
        client.post(LOGIN, json={"email": "nobody@example.org", "password": "x"})
    assert security._hash_slots._initial_value == 3
    app.state.engine.dispose()


class BlockedHasher(ProbeHasher):
    """Every hash waits until released: the slots stay full for as long as the test likes."""

    def __init__(self) -> None:
        super().__init__()
        self.release = threading.Event()

    def _work(self) -> None:
        with self._lock:
            self.running += 1
            self.peak = max(self.peak, self.running)
        self.release.wait(60)
        with self._lock:
            self.running -= 1


def test_logins_waiting_for_a_hash_slot_hold_no_worker_thread(limited, monkeypatch):
    """45 logins stuck behind 2 busy argon2 slots; a synchronous route (which needs one of
    anyio's 40 worker threads) must still answer."""
    client, world, _clock = limited
    probe = BlockedHasher()
    monkeypatch.setattr(security, "_hasher", probe)
    monkeypatch.setattr(security, "_hash_slots", security._hash_slots)
    security.set_hash_concurrency(2)
    client.app.state.login_limiter = LoginLimiter(per_account=100, per_address=100, window_s=60)
    pool = ThreadPoolExecutor(max_workers=46)
    try:
        logins = [pool.submit(_login, client, world.emails["reader"], "nope") for _ in range(45)]
        deadline = time.monotonic() + 30
        while probe.running < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert probe.running == 2
        listing = pool.submit(client.get, "/api/v1/tablets")
        assert listing.result(timeout=20).status_code == 200
        assert probe.running == 2 and not any(f.done() for f in logins)
    finally:
        probe.release.set()
        codes = [f.result(timeout=60).status_code for f in logins]
        pool.shutdown()
    assert codes == [401] * 45 and probe.peak == 2
