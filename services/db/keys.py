"""API keys (table ``api_keys``): create, verify, list, revoke; their webhook signing secrets; and
the audit trail of job access (table ``job_audit``): who (key id) did what to which job, when, in
which request.

A key is ``spine_<id>_<secret>``: a 12-hex-digit id, visible in logs, listings and the audit
trail, and a 256-bit random secret. Only the SHA-256 digest of the whole key is stored; a
presented key is looked up by its id and its digest compared in constant time. A high-entropy
key needs no salt nor slow hash: nothing can be guessed from its digest.

A key's ``name`` is the client it belongs to: it is the ``owner`` of the jobs created with the
key, so that a client keeps its jobs when its key is rotated (a new key, same name). The
``client`` role sees only its own jobs; ``admin`` sees every job. A name belongs to one role: a key
is not created under a name that keys of the other role use (``NameTaken``), so that an admin key
never signs a client's webhooks nor is revoked with the client's keys.

Each key also carries a Standard Webhooks signing secret (``whsec_<base64 of 32 random bytes>``),
made with the key and stored as is (it must be, to sign): the webhooks of a client's jobs are
signed with the secret of that client's most recent active ``client`` key that has one
(``key_webhook_secret``, which ``services.webhooks.signing.secret_for`` reads). A client whose
``client`` keys are all revoked (``client_revoked``) has no signing secret at all: its webhooks are
not sent, since it may no longer read its jobs.

The times written here are the database's clock (``services.db.clock``), never the writing process's:
a key's ``created_at`` (which key of a client is the most recent, the one that signs) and ``revoked_at``,
and an audit row's ``at`` (the order of the actions on a job, whichever API host or CLI wrote them).
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import re
import secrets
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, cast

from sqlalchemy import Table, case, func, insert, select, update
from sqlalchemy.orm import Session

from services.core.webhook_policy import decode_secret
from services.db.clock import db_now
from services.db.models import ApiKey, JobAudit

Role = Literal["admin", "client"]
ROLES: tuple[Role, ...] = ("admin", "client")
KEY_PREFIX = "spine_"
KEY_PATTERN = re.compile(r"^spine_([0-9a-f]{12})_([A-Za-z0-9_-]{43})$")
NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._@-]{0,63}$")


@dataclass(frozen=True)
class Caller:
    """The authenticated client of a request."""

    key_id: str
    name: str
    role: str

    @property
    def is_admin(self) -> bool:
        return self.role == "admin"

    @property
    def owner(self) -> str:
        """The owner of the jobs this caller creates (and whose idempotency keys it shares)."""
        return self.name

    @property
    def read_scope(self) -> str | None:
        """The owner whose jobs this caller may see and cancel; None (all) for an admin."""
        return None if self.is_admin else self.name


def digest(key: str) -> str:
    return hashlib.sha256(key.encode()).hexdigest()


def new_key() -> tuple[str, str]:
    """A fresh (key id, whole key)."""
    key_id = secrets.token_hex(6)
    return key_id, f"{KEY_PREFIX}{key_id}_{secrets.token_urlsafe(32)}"


def key_id_of(key: str) -> str | None:
    """The id of a well-formed key, else None."""
    match = KEY_PATTERN.match(key)
    return match.group(1) if match else None


class BadKeyName(ValueError):
    pass


class NameTaken(BadKeyName):
    """The name is used by keys of the other role (revoked ones included)."""


def create_key(session: Session, name: str, role: str = "client") -> tuple[ApiKey, str]:
    """Store a new key for client ``name``; return it and the whole key (shown once, never stored).

    Raises ``BadKeyName`` for a malformed name or role, ``NameTaken`` when keys of the other role
    (revoked ones included) use the name."""
    if not NAME_PATTERN.match(name):
        raise BadKeyName(f"a key name is 1 to 64 of A-Z a-z 0-9 . _ @ -, starting with a letter or digit: {name!r}")
    if role not in ROLES:
        raise BadKeyName(f"role must be one of {', '.join(ROLES)}, not {role!r}")
    other = session.scalar(select(ApiKey.role).where(ApiKey.name == name, ApiKey.role != role).limit(1))
    if other is not None:
        raise NameTaken(
            f"the name {name!r} is already used by {other} keys; a name belongs to one role (it owns the jobs of "
            f"its keys and signs their webhooks): choose another name for this {role} key"
        )
    key_id, key = new_key()
    # created_at: the database's clock in the INSERT (the model's default), read back after the commit
    row = ApiKey(id=key_id, name=name, role=role, key_hash=digest(key), webhook_secret=new_webhook_secret())
    session.add(row)
    session.commit()
    session.refresh(row)
    return row, key


def verify_key(session: Session, key: str) -> Caller | None:
    """The caller a presented key belongs to; None for a malformed, unknown or revoked key."""
    presented = digest(key)
    key_id = key_id_of(key)
    row = session.get(ApiKey, key_id) if key_id is not None else None
    stored = row.key_hash if row is not None else "0" * 64
    valid = hmac.compare_digest(stored, presented)  # constant time whatever matched
    if row is None or not valid or row.revoked_at is not None:
        return None
    return Caller(key_id=row.id, name=row.name, role=row.role)


def list_keys(session: Session) -> list[ApiKey]:
    return list(session.scalars(select(ApiKey).order_by(ApiKey.created_at, ApiKey.id)))


def revoke(session: Session, name_or_id: str) -> list[ApiKey]:
    """Revoke the key with this id, or else every active key of the client with this name.

    Raises ``NameTaken`` when the name's active keys have both roles (made before names were kept
    to one role): those are revoked by id. ``revoked_at`` is the database's clock (``services.db.clock``),
    each key as refreshed from its row."""
    by_id = session.get(ApiKey, name_or_id)
    if by_id is not None:
        targets = [by_id] if by_id.revoked_at is None else []
    else:
        targets = list(session.scalars(select(ApiKey).where(ApiKey.name == name_or_id, ApiKey.revoked_at.is_(None))))
        if len({k.role for k in targets}) > 1:
            ids = ", ".join(f"{k.id} ({k.role})" for k in targets)
            raise NameTaken(f"the name {name_or_id!r} has both admin and client keys: {ids}; revoke them by id")
    if targets:
        session.execute(update(ApiKey).where(ApiKey.id.in_([k.id for k in targets])).values(revoked_at=db_now()))
        session.commit()
        for key in targets:
            session.refresh(key)
    return targets


def count_keys(session: Session) -> int:
    return int(session.scalar(select(func.count()).select_from(ApiKey)) or 0)


# ------------------------------------------------------------------ webhook secrets


def new_webhook_secret() -> str:
    """A fresh Standard Webhooks secret: ``whsec_`` + base64 of 32 random bytes."""
    return "whsec_" + base64.b64encode(secrets.token_bytes(32)).decode()


def key_for_secret(session: Session, name_or_id: str) -> ApiKey | None:
    """The key with this id, or else the client's most recent active key (None when there is none)."""
    by_id = session.get(ApiKey, name_or_id)
    if by_id is not None:
        return by_id
    latest = select(ApiKey).where(ApiKey.name == name_or_id, ApiKey.revoked_at.is_(None))
    return session.scalars(latest.order_by(*_SIGNER_ORDER).limit(1)).first()


def rotate_webhook_secret(session: Session, key: ApiKey) -> str:
    """Give ``key`` a new webhook secret, commit, and return it."""
    key.webhook_secret = new_webhook_secret()
    session.commit()
    return key.webhook_secret


_SIGNER_ORDER = (case((ApiKey.role == "client", 0), else_=1), ApiKey.created_at.desc(), ApiKey.id.desc())
"""Which key of a name ``spine keys webhook-secret NAME`` shows: a client key first (a name that keys
of both roles share, from before ``NameTaken``, signs with the client's), then the most recent."""


def key_webhook_secret(session: Session, owner: str | None) -> bytes | None:
    """The signing key of ``owner``'s webhooks: the secret of that client's most recent active
    ``client`` key that has one (jobs are owned by client keys' names; an admin key that shares
    the name never signs); None (the service-wide secret then) for no owner or no such key."""
    if owner is None:
        return None
    latest = (
        select(ApiKey.webhook_secret)
        .where(ApiKey.name == owner, ApiKey.role == "client", ApiKey.revoked_at.is_(None),
               ApiKey.webhook_secret.is_not(None))
        .order_by(ApiKey.created_at.desc(), ApiKey.id.desc())
        .limit(1)
    )  # fmt: skip
    secret = session.scalar(latest)
    return decode_secret(secret) if secret else None


def client_revoked(session: Session, owner: str) -> bool:
    """Whether ``owner`` has ``client`` keys and every one of them is revoked: a client whose access was
    taken away, whose jobs' webhooks are then neither signed with a revoked key's secret nor with the
    service-wide one (``services.webhooks.signing.secret_for``)."""
    query = select(func.count(), func.count(ApiKey.revoked_at)).where(ApiKey.name == owner, ApiKey.role == "client")
    total, revoked = session.execute(query).one()
    return bool(total) and total == revoked


# ------------------------------------------------------------------ audit

AuditAction = Literal["create", "read", "list", "cancel", "store"]
"""What a caller did to a job; ``store``: asked for its results to be stored in the PACS again
(``POST /v1/jobs/{id}/dicom-store``)."""

_AUDIT = insert(cast(Table, JobAudit.__table__)).values(at=db_now())
"""The insert of audit rows, ``at`` the database's clock (``services.db.clock``) in the statement: the
rows of one job are in the order of the actions whatever the clocks of the API hosts that write them."""


def audit(
    session: Session, caller: Caller, action: AuditAction, job_ids: Sequence[uuid.UUID], request_id: str | None
) -> None:
    """Add one audit row per job to the session's transaction (one INSERT statement, ``at`` the database's
    clock: ``_AUDIT``; the caller commits)."""
    if not job_ids:
        return
    rows: list[dict[str, Any]] = [
        {"key_id": caller.key_id, "action": action, "job_id": job_id, "request_id": request_id} for job_id in job_ids
    ]
    session.execute(_AUDIT, rows)


def audit_trail(session: Session, job_id: uuid.UUID) -> list[JobAudit]:
    """The audit rows of a job, oldest first."""
    return list(session.scalars(select(JobAudit).where(JobAudit.job_id == job_id).order_by(JobAudit.id)))
