"""PostgreSQL: compress the jobs' results with LZ4 instead of pglz.

A result is about 17 kB of JSON, always stored out of line and compressed (TOAST). With pglz,
PostgreSQL's default, storing one took about 0.42 ms of the server's CPU; with LZ4 0.04 ms, at the
same size (2,000 results: 840 against 74 ms, 16 against 17 MB; docs/performance.md). LZ4 exists
from PostgreSQL 14 on when the server was built with it (PostgreSQL documentation, ALTER TABLE
"SET COMPRESSION" and the setting ``default_toast_compression``, whose allowed values list the
methods the server has); elsewhere, and on SQLite, this revision changes nothing. Results stored
before keep their compression until they are written again.

Revision ID: 0009_result_lz4
Revises: 0008_webhook_attempt_unique
Create Date: 2026-12-01
"""

from collections.abc import Sequence

from alembic import op
from sqlalchemy import text

revision: str = "0009_result_lz4"
down_revision: str | None = "0008_webhook_attempt_unique"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def _server_has_lz4() -> bool:
    bind = op.get_bind()
    if bind.dialect.name != "postgresql":
        return False
    found = bind.execute(
        text(
            "SELECT 1 FROM pg_catalog.pg_settings "
            "WHERE name = 'default_toast_compression' AND 'lz4' = ANY(enumvals)"
        )
    ).first()
    return found is not None


def upgrade() -> None:
    if _server_has_lz4():
        op.execute("ALTER TABLE jobs ALTER COLUMN result SET COMPRESSION lz4")


def downgrade() -> None:
    if _server_has_lz4():
        op.execute("ALTER TABLE jobs ALTER COLUMN result SET COMPRESSION default")
