"""An index on ``webhook_deliveries.next_attempt_at`` for the reconciler's webhook sweep.

Revision ID: 0005_webhook_sweep_index
Revises: 0004_key_webhook_secrets
Create Date: 2026-11-23
"""

from collections.abc import Sequence

from alembic import op

revision: str = "0005_webhook_sweep_index"
down_revision: str | None = "0004_key_webhook_secrets"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_index("ix_webhook_deliveries_next_attempt_at", "webhook_deliveries", ["next_attempt_at"])


def downgrade() -> None:
    op.drop_index("ix_webhook_deliveries_next_attempt_at", table_name="webhook_deliveries")
