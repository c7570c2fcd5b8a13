"""``job_audit.action`` takes ``store``: a request to store a job's results in the PACS again.

``POST /v1/jobs/{id}/dicom-store`` is audited as ``cancel`` is, one row in the caller's name; its action
is ``store`` (the PACS's Store transaction, STOW-RS), which the check constraint ``ck_job_audit_action``
did not allow. The constraint is made again with it; on SQLite, which cannot alter a constraint, by
Alembic's batch mode (the table copied; its two indexes are made again). No row changes going up.

Going down, the ``store`` rows are deleted: the older constraint cannot hold them, and the older release
has no such request to audit.

Revision ID: 0014_audit_store
Revises: 0013_idempotency_client
Create Date: 2026-12-05
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0014_audit_store"
down_revision: str | None = "0013_idempotency_client"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

CONSTRAINT = "ck_job_audit_ck_job_audit_action"
"""The constraint's name as 0003 made it (its name went through the naming convention once more)."""
BEFORE = "action IN ('create', 'read', 'list', 'cancel')"
AFTER = "action IN ('create', 'read', 'list', 'cancel', 'store')"


def _audit_table(condition: str) -> sa.Table:
    """``job_audit`` as 0003 made it, checked by ``condition``: what SQLite's batch mode copies (read from
    here, not reflected; a plain MetaData, so the names stay as written)."""
    return sa.Table(
        "job_audit",
        sa.MetaData(),
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), autoincrement=True, nullable=False),
        sa.Column("at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("key_id", sa.String(16), nullable=False),
        sa.Column("action", sa.String(8), nullable=False),
        sa.Column("job_id", sa.Uuid(), nullable=False),
        sa.Column("request_id", sa.String(64), nullable=True),
        sa.PrimaryKeyConstraint("id", name="pk_job_audit"),
        sa.CheckConstraint(condition, name=CONSTRAINT),
        sa.Index("ix_job_audit_job_id_at", "job_id", "at"),
        sa.Index("ix_job_audit_key_id_at", "key_id", "at"),
    )


def _check(before: str, after: str) -> None:
    with op.batch_alter_table("job_audit", copy_from=_audit_table(before)) as batch:
        batch.drop_constraint(op.f(CONSTRAINT), type_="check")  # op.f: the name as is, not the convention's
        batch.create_check_constraint(op.f(CONSTRAINT), after)


def upgrade() -> None:
    _check(BEFORE, AFTER)


def downgrade() -> None:
    op.execute("DELETE FROM job_audit WHERE action = 'store'")
    _check(AFTER, BEFORE)
