"""One row per attempt of a webhook message: a unique index on (message_id, attempt).

A worker claims an attempt by inserting its row before it makes the request; the index makes a
second delivery of the same attempt (a message published twice) fail to claim it, where the
earlier check-then-insert let both through. It replaces ``ix_webhook_deliveries_message_id``,
whose column it leads with. Duplicate attempts stored before this revision are removed first,
keeping the earliest row of each.

Revision ID: 0008_webhook_attempt_unique
Revises: 0007_job_dicom
Create Date: 2026-12-01
"""

from collections.abc import Sequence

from alembic import op

revision: str = "0008_webhook_attempt_unique"
down_revision: str | None = "0007_job_dicom"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.execute(
        "DELETE FROM webhook_deliveries WHERE id NOT IN "
        "(SELECT MIN(id) FROM webhook_deliveries GROUP BY message_id, attempt)"
    )
    op.drop_index("ix_webhook_deliveries_message_id", table_name="webhook_deliveries")
    op.create_index(
        "uq_webhook_deliveries_message_id_attempt", "webhook_deliveries", ["message_id", "attempt"], unique=True
    )


def downgrade() -> None:
    op.drop_index("uq_webhook_deliveries_message_id_attempt", table_name="webhook_deliveries")
    op.create_index("ix_webhook_deliveries_message_id", "webhook_deliveries", ["message_id"])
