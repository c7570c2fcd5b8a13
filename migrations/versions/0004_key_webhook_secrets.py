"""A per-key Standard Webhooks signing secret on API keys (``api_keys.webhook_secret``).

Revision ID: 0004_key_webhook_secrets
Revises: 0003_keys
Create Date: 2026-11-29
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004_key_webhook_secrets"
down_revision: str | None = "0003_keys"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # Nullable: keys made before this revision have none (their clients' webhooks keep the
    # service-wide SPINE_WEBHOOK_SECRET until `spine keys rotate-webhook-secret`).
    with op.batch_alter_table("api_keys") as batch:
        batch.add_column(sa.Column("webhook_secret", sa.String(64), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("api_keys") as batch:
        batch.drop_column("webhook_secret")
