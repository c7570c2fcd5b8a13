"""API keys, the audit trail of job access, and an index of each owner's queued jobs.

Revision ID: 0003_keys
Revises: 0002_webhook_deliveries
Create Date: 2026-11-22
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003_keys"
down_revision: str | None = "0002_webhook_deliveries"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

TS = sa.DateTime(timezone=True)


def upgrade() -> None:
    op.create_table(
        "api_keys",
        sa.Column("id", sa.String(16), nullable=False),
        sa.Column("name", sa.String(64), nullable=False),
        sa.Column("role", sa.String(8), nullable=False),
        sa.Column("key_hash", sa.String(64), nullable=False),
        sa.Column("created_at", TS, nullable=False),
        sa.Column("revoked_at", TS, nullable=True),
        sa.PrimaryKeyConstraint("id", name="pk_api_keys"),
        sa.CheckConstraint("role IN ('admin', 'client')", name="ck_api_keys_role"),
    )
    op.create_index("ix_api_keys_name", "api_keys", ["name"])
    op.create_table(
        "job_audit",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), autoincrement=True, nullable=False),
        sa.Column("at", TS, nullable=False),
        sa.Column("key_id", sa.String(16), nullable=False),
        sa.Column("action", sa.String(8), nullable=False),
        sa.Column("job_id", sa.Uuid(), nullable=False),
        sa.Column("request_id", sa.String(64), nullable=True),
        sa.PrimaryKeyConstraint("id", name="pk_job_audit"),
        sa.CheckConstraint("action IN ('create', 'read', 'list', 'cancel')", name="ck_job_audit_action"),
    )
    op.create_index("ix_job_audit_job_id_at", "job_audit", ["job_id", "at"])
    op.create_index("ix_job_audit_key_id_at", "job_audit", ["key_id", "at"])
    # The per-client cap on queued jobs counts these: a small partial index, queued jobs only.
    op.create_index(
        "ix_jobs_owner_queued",
        "jobs",
        ["owner"],
        postgresql_where=sa.text("status = 'queued'"),
        sqlite_where=sa.text("status = 'queued'"),
    )


def downgrade() -> None:
    op.drop_index("ix_jobs_owner_queued", table_name="jobs")
    op.drop_index("ix_job_audit_key_id_at", table_name="job_audit")
    op.drop_index("ix_job_audit_job_id_at", table_name="job_audit")
    op.drop_table("job_audit")
    op.drop_index("ix_api_keys_name", table_name="api_keys")
    op.drop_table("api_keys")
