"""The ``hammurabi`` command: serve, worker, migrate, create-user, create-token, import-catalogue.

Settings come from the environment (``HAMMURABI_*``, see docs/admin.md). Every command that
touches the database first brings it to the latest migration. Errors are one clear line on
stderr and exit status 2; secrets (API tokens) are the only thing printed on stdout.
"""

from __future__ import annotations

import argparse
import getpass
import os
import sys
from pathlib import Path

from pydantic import ValidationError

from backend import crud
from backend.db import make_engine, make_sessionmaker, migrate, session_scope
from backend.settings import Settings
from backend.tables import Role

EXIT_USAGE = 2


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


def _settings() -> Settings:
    try:
        return Settings()
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc']) or 'settings'}: {e['msg']}" for e in exc.errors()
        )
        raise CliError(f"invalid settings: {problems}") from None


def _migrated_sessionmaker(settings: Settings):
    url = settings.resolved_database_url
    try:
        migrate(url)
    except Exception as exc:  # connection refused, bad URL, permissions...
        raise CliError(f"cannot migrate the database {_safe_url(url)}: {exc}") from exc
    return make_sessionmaker(make_engine(url))


def _safe_url(url: str) -> str:
    from sqlalchemy.engine import make_url

    return make_url(url).render_as_string(hide_password=True)


def cmd_migrate(args: argparse.Namespace) -> int:
    settings = _settings()
    _migrated_sessionmaker(settings)
    print(f"database {_safe_url(settings.resolved_database_url)} is up to date", file=sys.stderr)
    return 0


def _start_sweeper(settings: Settings, factory) -> None:
    """The job sweeper in the service too (backend.sweeper): jobs the broker could not take
    are sent once it is back, lost jobs re-sent, abandoned uploads expired, even when no
    worker is running."""
    from backend.queue import dispatcher_from_settings
    from backend.sweeper import Sweeper

    Sweeper(factory, dispatcher_from_settings(settings), settings).start()


def _with_dev_public_url(settings: Settings, *, host: str, port: int) -> Settings:
    """Without HAMMURABI_PUBLIC_URL (allowed outside production) absolute URLs name the
    address we listen on; also put in the environment for ``--workers`` processes."""
    if settings.public_url is not None:
        return settings
    if host in ("", "0.0.0.0", "::"):
        host = "127.0.0.1"
    public_url = f"http://{f'[{host}]' if ':' in host else host}:{port}"
    os.environ["HAMMURABI_PUBLIC_URL"] = public_url
    return settings.model_copy(update={"public_url": public_url})


def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from backend.main import create_app

    settings = _with_dev_public_url(_settings(), host=args.host, port=args.port)
    _start_sweeper(settings, _migrated_sessionmaker(settings))
    options = dict(host=args.host, port=args.port, log_level=args.log_level)
    if args.workers > 1:
        # Each worker process builds its app from the same environment (create_app()).
        # A worker must answer the supervisor's health check; importing the app takes
        # longer than uvicorn's 5 s default on a busy machine, so allow a minute.
        uvicorn.run(
            "backend.main:create_app",
            factory=True,
            workers=args.workers,
            timeout_worker_healthcheck=60,
            **options,
        )
    else:
        uvicorn.run(create_app(settings), **options)
    return 0


def cmd_worker(args: argparse.Namespace) -> int:
    """Migrate, then become a Celery worker of ``worker.celery_app`` (exec: signals go to it).

    Started by name: the library package never imports the numerical code.
    """
    settings = _settings()
    _migrated_sessionmaker(settings)
    argv = [
        sys.executable,
        "-m",
        "celery",
        "-A",
        "worker.celery_app",
        "worker",
        "--queues",
        settings.job_queue,
        "--concurrency",
        str(args.concurrency),
        "--loglevel",
        args.log_level,
        "--without-gossip",
        "--without-mingle",
    ]
    if args.hostname:
        argv += ["--hostname", args.hostname]
    sys.stdout.flush()
    sys.stderr.flush()
    os.execv(sys.executable, argv)
    return 0  # pragma: no cover (exec does not return)


PASSWORD_ARGV_REFUSED = (
    "--password is not accepted: a password on the command line is visible to every user in "
    "`ps` and stays in the shell history; type it at the prompt, or pipe it with "
    "--password-stdin (e.g. from a password manager)"
)
MIN_PASSWORD_CHARS = 8


def _read_password(args: argparse.Namespace) -> str | None:
    """The new account's password: asked twice on the terminal, or one line of stdin."""
    if args.password is not None:
        raise CliError(PASSWORD_ARGV_REFUSED)
    if args.no_password:
        return None
    if args.password_stdin:
        password = sys.stdin.readline().removesuffix("\n").removesuffix("\r")
        if not password:
            raise CliError("--password-stdin: stdin gave no password (an empty first line)")
    elif sys.stdin.isatty():
        password = getpass.getpass("password: ")
        if getpass.getpass("again: ") != password:
            raise CliError("the two passwords differ")
    else:
        raise CliError(
            "no terminal to ask the password on: pipe it with --password-stdin, "
            "or give --no-password for a token-only account"
        )
    if len(password) < MIN_PASSWORD_CHARS:
        raise CliError(f"password: at least {MIN_PASSWORD_CHARS} characters")
    return password


def cmd_create_user(args: argparse.Namespace) -> int:
    role = Role(args.role)
    if role == Role.staff and not args.institution:
        raise CliError("--institution is required for staff users")
    password = _read_password(args)
    with session_scope(_migrated_sessionmaker(_settings())) as session:
        institution_id = None
        if args.institution:
            institution_id = crud.get_or_create_institution(session, name=args.institution).id
        try:
            user = crud.create_user(
                session,
                email=args.email,
                role=role,
                password=password,
                institution_id=institution_id,
            )
        except ValueError as exc:
            raise CliError(str(exc)) from None
        print(f"created {user.role.value} {user.email} (id {user.id})", file=sys.stderr)
    return 0


def cmd_create_token(args: argparse.Namespace) -> int:
    with session_scope(_migrated_sessionmaker(_settings())) as session:
        user = crud.get_user_by_email(session, email=args.email)
        if user is None:
            raise CliError(f"no user {args.email}")
        token, secret = crud.create_token(session, user=user, name=args.name)
        print(
            f"token {token.name!r} (id {token.id}) for {user.email}; it is shown only once:",
            file=sys.stderr,
        )
    print(secret)
    return 0


def cmd_import_catalogue(args: argparse.Namespace) -> int:
    from backend.catalogue import import_catalogue

    path = Path(args.file)
    if not path.is_file():
        raise CliError(f"{path}: no such file")
    with session_scope(_migrated_sessionmaker(_settings())) as session:
        institution_id = None
        if args.institution:
            institution_id = crud.get_or_create_institution(session, name=args.institution).id
        try:
            summary = import_catalogue(
                session,
                path,
                institution_id=institution_id,
                is_public=args.public,
                max_reasons=args.reasons,
            )
        except (ValueError, UnicodeDecodeError) as exc:
            raise CliError(str(exc)) from None
    print(summary.text(), file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hammurabi", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    serve = commands.add_parser("serve", help="migrate, then run the web service (uvicorn)")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8000)
    serve.add_argument("--log-level", default="info")
    serve.add_argument(
        "--workers", type=int, default=1, help="server processes (one per core in production)"
    )
    serve.set_defaults(handler=cmd_serve)

    work = commands.add_parser(
        "worker", help="migrate, then run a reconstruction worker (Celery, worker.celery_app)"
    )
    work.add_argument("--concurrency", type=int, default=1, help="jobs at once (processes)")
    work.add_argument("--log-level", default="info")
    work.add_argument("--hostname", help="worker name, e.g. w1@%%h (default celery@<host>)")
    work.set_defaults(handler=cmd_worker)

    commands.add_parser("migrate", help="bring the database to the latest schema").set_defaults(
        handler=cmd_migrate
    )

    user = commands.add_parser("create-user", help="create a user account")
    user.add_argument("email")
    user.add_argument("--role", choices=[r.value for r in Role], required=True)
    user.add_argument("--institution", help="name; created if new (required for staff)")
    secret = user.add_mutually_exclusive_group()
    secret.add_argument(
        "--password-stdin",
        action="store_true",
        help="read the password from the first line of stdin (default: asked twice on the "
        "terminal)",
    )
    secret.add_argument("--no-password", action="store_true", help="token-only account")
    # Kept only to refuse it with the reason (PASSWORD_ARGV_REFUSED), not listed in --help.
    secret.add_argument("--password", help=argparse.SUPPRESS)
    user.set_defaults(handler=cmd_create_user)

    token = commands.add_parser("create-token", help="create an API token (printed once)")
    token.add_argument("email")
    token.add_argument("--name", required=True, help="what the token is for, e.g. 'rig 1'")
    token.set_defaults(handler=cmd_create_token)

    imp = commands.add_parser("import-catalogue", help="import catalogue records (CSV, JSONL)")
    imp.add_argument("file")
    imp.add_argument("--institution", help="institution holding the records (created if new)")
    visibility = imp.add_mutually_exclusive_group()
    visibility.add_argument("--public", dest="public", action="store_true", default=None)
    visibility.add_argument("--private", dest="public", action="store_false")
    imp.add_argument("--reasons", type=int, default=20, help="how many reasons to list")
    imp.set_defaults(handler=cmd_import_catalogue)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.handler(args)
    except CliError as exc:
        print(f"hammurabi {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
