"""``jobs.idempotency_kind``: a single submission's Idempotency-Key and a batch entry's are kept apart.

A batch sent with key ``K`` stores payload ``i`` under ``K#i``; a single POST stores its key as sent.
Both were in one namespace, so a single POST keyed ``abc#0`` was answered with entry 0 of the batch
keyed ``abc`` (and the other way round). The draft's Idempotency-Key is an sf-string
(draft-ietf-httpapi-idempotency-key-header-06, §2.1 "Syntax"; RFC 8941 §3.3.3: printable ASCII,
``#`` included), so a client's key with a ``#`` is a valid one and is not refused (a client that used
one would also lose the replays of what it stored); the kind of request is stored beside the key:

- NULL: a single submission's key (and every job without a key);
- ``batch``: entry ``i`` of a batch's key ``K``, stored as ``K#i``;
- ``either``: a key with a ``#`` stored before this revision, by a single POST or as a batch entry
  (the row does not say which). It keeps answering both, as it did, so every request stored before
  this revision replays as before; only new requests are kept apart.

The unique index becomes ``(coalesce(owner, ''), idempotency_key, coalesce(idempotency_kind, ''))``,
partial as before. Going down, a batch entry whose ``K#i`` a single key of the same owner also holds
loses its key (the older index allows one of them): that entry is no longer replayed by the older
release, and no job is lost.

Revision ID: 0012_idempotency_kind
Revises: 0011_bending_by_plane
Create Date: 2026-12-05
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0012_idempotency_kind"
down_revision: str | None = "0011_bending_by_plane"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

IDEMPOTENCY = "uq_jobs_owner_idempotency_key"
PARTIAL = {
    "postgresql_where": sa.text("idempotency_key IS NOT NULL"),
    "sqlite_where": sa.text("idempotency_key IS NOT NULL"),
}
jobs = sa.table("jobs", sa.column("idempotency_key", sa.String), sa.column("idempotency_kind", sa.String))


def _index(*kind: sa.TextClause) -> None:
    op.drop_index(IDEMPOTENCY, table_name="jobs")
    columns = [sa.text("coalesce(owner, '')"), "idempotency_key", *kind]
    op.create_index(IDEMPOTENCY, "jobs", columns, unique=True, **PARTIAL)


def upgrade() -> None:
    # Plain ADD/DROP COLUMN (SQLite 3.35+ has both): a batch copy of the table would lose the
    # expression index uq_jobs_owner_idempotency_key, which SQLite cannot reflect.
    op.add_column("jobs", sa.Column("idempotency_kind", sa.String(6), nullable=True))
    op.execute(jobs.update().where(jobs.c.idempotency_key.contains("#")).values(idempotency_kind="either"))
    _index(sa.text("coalesce(idempotency_kind, '')"))


def downgrade() -> None:
    op.execute(
        "UPDATE jobs SET idempotency_key = NULL WHERE idempotency_kind = 'batch' AND EXISTS ("
        "SELECT 1 FROM jobs AS s WHERE s.idempotency_kind IS NULL AND s.idempotency_key = jobs.idempotency_key "
        "AND coalesce(s.owner, '') = coalesce(jobs.owner, ''))"
    )
    _index()
    op.execute("ALTER TABLE jobs DROP COLUMN idempotency_kind")
