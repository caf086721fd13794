"""Reads and writes of users, tokens, institutions and tablets.

Keyword-only functions that add/flush but never commit: the session scope (API request or CLI
command, see backend.db.session_scope) is the one place that commits. Who may see or edit
what is decided here too (:func:`visible_clause`, :func:`can_edit_tablet`), so the API
dependencies and the search module share one rule:

- admin: every record;
- staff: public records plus every record of their institution; edit their institution's;
- reader and anonymous: public records only; edit nothing.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Any

from sqlalchemy import ColumnElement, case, or_, select, true
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from backend import security
from backend.tables import ApiToken, Institution, Model, Role, Tablet, User

# Writing last_used_at on every request would turn each read into a write; a minute is plenty.
TOKEN_TOUCH_INTERVAL = timedelta(minutes=1)


def _now() -> datetime:
    return datetime.now(UTC)


def _aware(value: datetime | None) -> datetime | None:
    # SQLite returns naive datetimes even for timezone=True columns; they were stored in UTC.
    if value is not None and value.tzinfo is None:
        return value.replace(tzinfo=UTC)
    return value


# --- institutions ---------------------------------------------------------------------------


def get_institution_by_name(session: Session, *, name: str) -> Institution | None:
    return session.scalar(select(Institution).where(Institution.name == name))


def get_or_create_institution(session: Session, *, name: str) -> Institution:
    name = name.strip()
    if not name:
        raise ValueError("institution name must not be empty")
    institution = get_institution_by_name(session, name=name)
    if institution is None:
        institution = Institution(name=name)
        session.add(institution)
        session.flush()
    return institution


def list_institutions(session: Session) -> list[Institution]:
    return list(session.scalars(select(Institution).order_by(Institution.name)))


# --- users ----------------------------------------------------------------------------------


def get_user(session: Session, *, user_id: int) -> User | None:
    return session.get(User, user_id)


def get_user_by_email(session: Session, *, email: str) -> User | None:
    return session.scalar(select(User).where(User.email == email.strip().lower()))


def list_users(session: Session) -> list[User]:
    return list(session.scalars(select(User).order_by(User.email)))


def create_user(
    session: Session,
    *,
    email: str,
    role: Role,
    password: str | None = None,
    institution_id: int | None = None,
) -> User:
    """A new user; raises ValueError naming the field when the combination is not allowed."""
    email = email.strip().lower()
    if "@" not in email:
        raise ValueError(f"email: {email!r} is not an e-mail address")
    if role == Role.staff and institution_id is None:
        raise ValueError("institution_id: staff users must belong to an institution")
    if get_user_by_email(session, email=email) is not None:
        raise ValueError(f"email: a user {email} already exists")
    user = User(
        email=email,
        role=role,
        institution_id=institution_id,
        password_hash=security.hash_password(password) if password else None,
        is_active=True,
    )
    session.add(user)
    session.flush()
    return user


def revoke_sessions(session: Session, *, user: User) -> None:
    """Make every session cookie of ``user`` signed so far unusable (a new login still works).

    Incremented in SQL so two concurrent revocations cannot collapse into one.
    """
    user.session_version = User.session_version + 1
    session.flush()
    session.refresh(user, ["session_version"])


def update_user(session: Session, *, user: User, changes: dict[str, Any]) -> User:
    """Apply ``changes``; a new password or disabling the account revokes its sessions."""
    revoke = False
    if "password" in changes:
        password = changes.pop("password")
        if password:
            user.password_hash = security.hash_password(password)
            revoke = True
    if changes.get("is_active") is False and user.is_active:
        revoke = True
    for key, value in changes.items():
        setattr(user, key, value)
    if user.role == Role.staff and user.institution_id is None:
        raise ValueError("institution_id: staff users must belong to an institution")
    session.flush()
    if revoke:
        revoke_sessions(session, user=user)
    return user


def authenticate(session: Session, *, email: str, password: str) -> User | None:
    user = get_user_by_email(session, email=email)
    return user if password_matches(user, password) else None


def password_matches(user: User | None, password: str) -> bool:
    """Whether ``user`` exists, is active and has this password (no database access, so it
    may run after the session is closed)."""
    if user is None or not user.is_active or not user.password_hash:
        # Hash anyway so that unknown e-mails take as long as wrong passwords.
        security.verify_password(_DUMMY_HASH, password)
        return False
    return security.verify_password(user.password_hash, password)


_DUMMY_HASH = security.hash_password("not a real password")


# --- API tokens -----------------------------------------------------------------------------


def create_token(session: Session, *, user: User, name: str) -> tuple[ApiToken, str]:
    """A new token of ``user``; returns the row and the secret (shown once, stored hashed)."""
    secret = security.new_token_secret()
    token = ApiToken(
        user_id=user.id,
        name=name.strip() or "token",
        token_hash=security.token_hash(secret),
        prefix=security.token_display_prefix(secret),
    )
    session.add(token)
    session.flush()
    return token, secret


def list_tokens(session: Session, *, user: User) -> list[ApiToken]:
    return list(
        session.scalars(select(ApiToken).where(ApiToken.user_id == user.id).order_by(ApiToken.id))
    )


def get_token(session: Session, *, token_id: int) -> ApiToken | None:
    return session.get(ApiToken, token_id)


def revoke_token(session: Session, *, token: ApiToken) -> ApiToken:
    if token.revoked_at is None:
        token.revoked_at = _now()
        session.flush()
    return token


def user_for_token(session: Session, *, secret: str) -> User | None:
    """The active user owning the unrevoked token ``secret``, or None."""
    if not secret.startswith(security.TOKEN_PREFIX):
        return None
    token = session.scalar(
        select(ApiToken).where(ApiToken.token_hash == security.token_hash(secret))
    )
    if token is None or token.revoked_at is not None:
        return None
    user = session.get(User, token.user_id)
    if user is None or not user.is_active:
        return None
    now = _now()
    last = _aware(token.last_used_at)
    if last is None or now - last > TOKEN_TOUCH_INTERVAL:
        token.last_used_at = now
        session.flush()
    return user


# --- tablets and who may see them -----------------------------------------------------------


def visible_clause(user: User | None) -> ColumnElement[bool]:
    """SQL condition on ``tablets`` selecting the records ``user`` may read."""
    if user is not None and user.role == Role.admin:
        return true()
    if user is not None and user.role == Role.staff and user.institution_id is not None:
        return or_(Tablet.is_public.is_(True), Tablet.institution_id == user.institution_id)
    return Tablet.is_public.is_(True)


def can_read_tablet(user: User | None, tablet: Tablet) -> bool:
    # Private records are seen exactly by those who may edit them: their institution, admins.
    return tablet.is_public or can_edit_tablet(user, tablet)


def can_edit_tablet(user: User | None, tablet: Tablet) -> bool:
    if user is None:
        return False
    if user.role == Role.admin:
        return True
    return (
        user.role == Role.staff
        and user.institution_id is not None
        and tablet.institution_id == user.institution_id
    )


def get_tablet(session: Session, *, tablet_id: int) -> Tablet | None:
    return session.get(Tablet, tablet_id)


def get_tablet_by_p_number(session: Session, *, p_number: str, user: User | None) -> Tablet | None:
    """The record ``user`` means by ``p_number``, among the records ``user`` may read.

    A P-number is unique per institution, so several records may carry it; the caller's
    own institution's record comes first, then the record of no institution (the shared
    catalogue), then the oldest public one. Records the caller may not read are never
    considered: whether they exist is not revealed.
    """
    own = user.institution_id if user is not None and user.role == Role.staff else None
    whens = [(Tablet.institution_id == own, 0)] if own is not None else []
    rank = case(*whens, (Tablet.institution_id.is_(None), 1), else_=2)
    return session.scalars(
        select(Tablet)
        .where(Tablet.p_number == p_number, visible_clause(user))
        .order_by(rank, Tablet.id)
        .limit(1)
    ).first()


def p_number_taken(
    session: Session, *, p_number: str, institution_id: int | None, exclude_id: int | None = None
) -> bool:
    """Whether ``institution_id`` (None: no institution) already has a record ``p_number``.

    Only that institution's records count: its staff may see all of them, so a conflict
    reveals nothing, and no other institution can block the P-number.
    """
    scope = (
        Tablet.institution_id.is_(None)
        if institution_id is None
        else Tablet.institution_id == institution_id
    )
    query = select(Tablet.id).where(Tablet.p_number == p_number, scope)
    if exclude_id is not None:
        query = query.where(Tablet.id != exclude_id)
    return session.scalar(query.limit(1)) is not None


def create_tablet(
    session: Session, *, fields: dict[str, Any], institution_id: int | None
) -> Tablet:
    """A new catalogue record; ValueError naming the field on a duplicate P-number.

    Duplicate means: the same P-number among records of the same institution (or, for a
    record of no institution, among records of no institution); see :func:`p_number_taken`.
    """
    p_number = fields.get("p_number")
    if p_number and p_number_taken(session, p_number=p_number, institution_id=institution_id):
        raise ValueError(f"p_number: this institution already has a record {p_number}")
    values = {k: v for k, v in fields.items() if v is not None}
    values.setdefault("extra", {})
    values.setdefault("is_public", False)
    tablet = Tablet(**values, institution_id=institution_id, has_3d=False)
    session.add(tablet)
    try:
        session.flush()
    except IntegrityError as exc:
        if p_number and "p_number" in str(exc.orig):
            # Registered concurrently in the same institution; the caller rolls back.
            raise ValueError(
                f"p_number: this institution already has a record {p_number}"
            ) from None
        raise
    return tablet


def update_tablet(session: Session, *, tablet: Tablet, changes: dict[str, Any]) -> Tablet:
    """Apply ``changes``; ValueError when the P-number is taken in the record's (new)
    institution."""
    p_number = changes.get("p_number", tablet.p_number)
    institution_id = changes.get("institution_id", tablet.institution_id)
    moved = p_number != tablet.p_number or institution_id != tablet.institution_id
    if (
        p_number
        and moved
        and p_number_taken(
            session, p_number=p_number, institution_id=institution_id, exclude_id=tablet.id
        )
    ):
        raise ValueError(f"p_number: that institution already has a record {p_number}")
    for key, value in changes.items():
        setattr(tablet, key, value)
    tablet.updated_at = _now()
    session.flush()
    return tablet


def delete_tablet(session: Session, *, tablet: Tablet) -> None:
    session.delete(tablet)
    session.flush()


def refresh_has_3d(session: Session, *, tablet_id: int) -> bool:
    """Recompute the maintained ``tablets.has_3d`` flag; call after adding/removing models."""
    tablet = session.get(Tablet, tablet_id)
    if tablet is None:
        raise ValueError(f"tablet_id: no tablet {tablet_id}")
    has = session.scalar(select(Model.id).where(Model.tablet_id == tablet_id).limit(1)) is not None
    if tablet.has_3d != has:
        tablet.has_3d = has
        session.flush()
    return has
