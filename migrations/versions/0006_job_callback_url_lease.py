"""Jobs get ``callback_url`` as a column (read from the payload once, at admission) and
``lease_expires_at``, the running job's worker lease (renewed while it runs; an expired lease hands
the job back to the reconciler).

Revision ID: 0006_job_callback_url_lease
Revises: 0005_webhook_sweep_index
Create Date: 2026-12-01
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006_job_callback_url_lease"
down_revision: str | None = "0005_webhook_sweep_index"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # Plain ADD/DROP COLUMN (SQLite 3.35+ has both): a batch copy of the table would lose the
    # expression index uq_jobs_owner_idempotency_key, which SQLite cannot reflect.
    op.add_column("jobs", sa.Column("callback_url", sa.String(2048), nullable=True))
    op.add_column("jobs", sa.Column("lease_expires_at", sa.DateTime(timezone=True), nullable=True))
    # Jobs stored before this revision: their callback_url is in the payload.
    if op.get_bind().dialect.name == "postgresql":
        op.execute("UPDATE jobs SET callback_url = payload->>'callback_url' WHERE payload ? 'callback_url'")
    else:
        op.execute(
            "UPDATE jobs SET callback_url = json_extract(payload, '$.callback_url') "
            "WHERE json_extract(payload, '$.callback_url') IS NOT NULL"
        )
    # The reconciler looks for running jobs whose lease expired.
    op.create_index(
        "ix_jobs_running_lease",
        "jobs",
        ["lease_expires_at"],
        postgresql_where=sa.text("status = 'running'"),
        sqlite_where=sa.text("status = 'running'"),
    )


def downgrade() -> None:
    op.drop_index("ix_jobs_running_lease", table_name="jobs")
    for name in ("lease_expires_at", "callback_url"):
        op.execute(f"ALTER TABLE jobs DROP COLUMN {name}")
