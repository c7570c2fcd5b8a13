"""Six indexes of ``jobs`` become partial, over the rows whose column is not NULL: ``finished_at``,
the three DICOM list filters (``study_instance_uid``, ``accession_number``, ``patient_id`` with the
owner), ``dicom_store_due_at`` and the unique ``(coalesce(owner, ''), idempotency_key)``.

Each job's row is written three times (the API's insert, the worker's claim and finish), and the
claim and the finish change ``status``, an indexed column, so neither is a HOT update: PostgreSQL
adds an entry for the new row version to every index of the table whose predicate it satisfies
(PostgreSQL 15 docs, 73.7 Heap-Only Tuples (HOT); 67.4.2 Bottom-up Index Deletion). A job of the
load bench (no study, no Idempotency-Key) wrote 11 + 11 + 10 index entries, NULL keys included;
with these predicates 5 + 5 + 5 (the primary key, the three list indexes, and the one partial index
whose predicate the row version meets: queued, running with its lease, finished).

Every query that uses one of these indexes compares its column with a strict operator (``=``,
``<``, ``>=``, ``IN``), which implies ``IS NOT NULL``, so the planner still uses it (PostgreSQL 15
docs, 11.8 Partial Indexes; SQLite's "Partial Indexes", 2.2 Queries Using Partial Indexes). The
unique index keeps its meaning: NULL keys never conflicted.

The indexes are dropped and created again in the migration's transaction, which blocks writes to
``jobs`` while they build (one scan of the table each).

Revision ID: 0010_jobs_partial_indexes
Revises: 0009_result_lz4
Create Date: 2026-12-02
"""

from collections.abc import Sequence
from typing import Any

import sqlalchemy as sa
from alembic import op

revision: str = "0010_jobs_partial_indexes"
down_revision: str | None = "0009_result_lz4"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

INDEXES: dict[str, tuple[list[str], str]] = {
    "ix_jobs_finished_at": (["finished_at"], "finished_at"),
    "ix_jobs_owner_study_instance_uid": (["owner", "study_instance_uid", "created_at"], "study_instance_uid"),
    "ix_jobs_owner_accession_number": (["owner", "accession_number", "created_at"], "accession_number"),
    "ix_jobs_owner_patient_id": (["owner", "patient_id", "created_at"], "patient_id"),
    "ix_jobs_dicom_store_due_at": (["dicom_store_due_at"], "dicom_store_due_at"),
}
"""name -> (columns, the column whose NULLs the partial index leaves out)"""

IDEMPOTENCY = "uq_jobs_owner_idempotency_key"


def _where(column: str, partial: bool) -> dict[str, Any]:
    if not partial:
        return {}
    return {"postgresql_where": sa.text(f"{column} IS NOT NULL"), "sqlite_where": sa.text(f"{column} IS NOT NULL")}


def _create(partial: bool) -> None:
    for name, (columns, column) in INDEXES.items():
        op.create_index(name, "jobs", columns, **_where(column, partial))
    expressions = [sa.text("coalesce(owner, '')"), "idempotency_key"]
    op.create_index(IDEMPOTENCY, "jobs", expressions, unique=True, **_where("idempotency_key", partial))


def _drop() -> None:
    for name in (*INDEXES, IDEMPOTENCY):
        op.drop_index(name, table_name="jobs")


def upgrade() -> None:
    _drop()
    _create(partial=True)


def downgrade() -> None:
    _drop()
    _create(partial=False)
