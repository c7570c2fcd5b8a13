"""``jobs.idempotency_client``: Idempotency-Keys are per client, admin clients included.

Keys were unique per owner, and an admin key's jobs have no owner (every admin sees them), so every
admin client shared one namespace: an admin reusing a key another admin had sent got a 409 naming the
other's job, or with the same body that job replayed. docs/security.md says "Idempotency keys are per
client", a client being its API keys' name. The column holds that name for every job stored with a key
(NULL without one), and the unique index becomes ``(coalesce(owner, ''), coalesce(idempotency_client,
''), idempotency_key, coalesce(idempotency_kind, ''))``, partial as before.

The keys stored before this revision are given their client so that a request retried across the
upgrade replays its job, never makes a second one:

- a job with an owner: the owner (a client key's name);
- an admin's job (no owner): the name of the key that created it, from the audit trail (its first
  ``create`` row, ``job_audit``, joined to ``api_keys``);
- an admin's job that the audit trail does not name (none found): NULL, and every admin key still
  replays it, as before (``services.db.jobs``).

Going down, where two admin clients stored one key (and kind) after this revision, the older index
allows one: the job stored first keeps its key, the others lose it (they are no longer replayed by the
older release, and no job is lost).

Revision ID: 0013_idempotency_client
Revises: 0012_idempotency_kind
Create Date: 2026-12-05
"""

from collections.abc import Sequence
from typing import Any

import sqlalchemy as sa
from alembic import op

revision: str = "0013_idempotency_client"
down_revision: str | None = "0012_idempotency_kind"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

IDEMPOTENCY = "uq_jobs_owner_idempotency_key"
PARTIAL: dict[str, Any] = {
    "postgresql_where": sa.text("idempotency_key IS NOT NULL"),
    "sqlite_where": sa.text("idempotency_key IS NOT NULL"),
}
OWNER = sa.text("coalesce(owner, '')")
KIND = sa.text("coalesce(idempotency_kind, '')")

CLIENT_OF_OWNER = "UPDATE jobs SET idempotency_client = owner WHERE idempotency_key IS NOT NULL AND owner IS NOT NULL"
CLIENT_OF_ADMIN = (
    "UPDATE jobs SET idempotency_client = (SELECT k.name FROM job_audit AS a JOIN api_keys AS k ON k.id = a.key_id "
    "WHERE a.job_id = jobs.id AND a.action = 'create' ORDER BY a.at, a.id LIMIT 1) "
    "WHERE idempotency_key IS NOT NULL AND owner IS NULL"
)
"""An admin's keyed job: the name of the key of its first ``create`` audit row (NULL when there is none)."""
SHARED_KEYS_DOWN = (
    "UPDATE jobs SET idempotency_key = NULL WHERE owner IS NULL AND idempotency_key IS NOT NULL AND EXISTS ("
    "SELECT 1 FROM jobs AS s WHERE s.owner IS NULL AND s.idempotency_key = jobs.idempotency_key "
    "AND coalesce(s.idempotency_kind, '') = coalesce(jobs.idempotency_kind, '') "
    "AND (s.created_at < jobs.created_at OR (s.created_at = jobs.created_at AND s.id < jobs.id)))"
)
"""The admins' keys the older index cannot hold: every one but the first stored of each key and kind."""


def _index(*columns: sa.TextClause | str) -> None:
    op.drop_index(IDEMPOTENCY, table_name="jobs")
    op.create_index(IDEMPOTENCY, "jobs", list(columns), unique=True, **PARTIAL)


def upgrade() -> None:
    # Plain ADD/DROP COLUMN (SQLite 3.35+ has both): a batch copy of the table would lose the
    # expression index uq_jobs_owner_idempotency_key, which SQLite cannot reflect.
    op.add_column("jobs", sa.Column("idempotency_client", sa.String(64), nullable=True))
    op.execute(CLIENT_OF_OWNER)
    op.execute(CLIENT_OF_ADMIN)
    _index(OWNER, sa.text("coalesce(idempotency_client, '')"), "idempotency_key", KIND)


def downgrade() -> None:
    op.execute(SHARED_KEYS_DOWN)
    _index(OWNER, "idempotency_key", KIND)
    op.execute("ALTER TABLE jobs DROP COLUMN idempotency_client")
