"""Run the real library service (backend.main.create_app) for the rig agent's upload tests.

A subprocess the tests can kill with SIGKILL and start again on the same data: the first
start migrates a SQLite database under ``--data`` and creates a museum, a staff user with
an API token (written to ``DATA/token.txt``) and the tablet P123456 (its id in
``DATA/tablet_id.txt``). Jobs are recorded, not sent to a broker.
Usage: python real_library.py --port N --data DIR [--chunk-size BYTES]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import uvicorn

from backend import crud
from backend.db import make_engine, make_sessionmaker, migrate, session_scope
from backend.jobs import RecordingDispatcher
from backend.main import create_app
from backend.settings import Settings
from backend.tables import Role


def first_start(url: str, data: Path) -> None:
    migrate(url)
    engine = make_engine(url)
    with session_scope(make_sessionmaker(engine)) as session:
        museum = crud.get_or_create_institution(session, name="Rig Test Museum")
        user = crud.create_user(
            session, email="scanner@example.org", role=Role.staff, institution_id=museum.id
        )
        _token, secret = crud.create_token(session, user=user, name="rig agent")
        tablet = crud.create_tablet(
            session,
            fields={"designation": "Rig test tablet", "p_number": "P123456", "is_public": False},
            institution_id=museum.id,
        )
        session.flush()
        (data / "tablet_id.txt").write_text(str(tablet.id))
    engine.dispose()
    (data / "token.txt").write_text(secret)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--chunk-size", type=int, default=65536)
    args = parser.parse_args()
    args.data.mkdir(parents=True, exist_ok=True)
    url = f"sqlite:///{args.data / 'hammurabi.db'}"
    if not (args.data / "token.txt").exists():
        first_start(url, args.data)
    settings = Settings(
        _env_file=None,
        environment="test",
        data_dir=args.data / "var",
        database_url=url,
        secret_key="rig-agent-test-secret-" + "x" * 40,
        storage_dir=args.data / "storage",
        frontend_dist=args.data / "no-frontend",
        upload_chunk_size_bytes=args.chunk_size,
    )
    app = create_app(settings)
    app.state.dispatcher = RecordingDispatcher()
    uvicorn.run(app, host="127.0.0.1", port=args.port, log_level="warning")


if __name__ == "__main__":
    main()
