"""Jobs get their DICOM study's identifiers as indexed columns (the list filters
``?study_instance_uid=``, ``?accession_number=``, ``?patient_id=`` within an owner), what the DICOM
layer read (``dicom``), the STOW-RS attempts of their results (``dicom_stores``) and when the
reconciler publishes a STOW-RS attempt no message carried (``dicom_store_due_at``).

Revision ID: 0007_job_dicom
Revises: 0006_job_callback_url_lease
Create Date: 2026-12-01
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects.postgresql import JSONB

revision: str = "0007_job_dicom"
down_revision: str | None = "0006_job_callback_url_lease"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

JSON_DOCUMENT = sa.JSON().with_variant(JSONB(), "postgresql")
COLUMNS = {"study_instance_uid": 64, "accession_number": 16, "patient_id": 64}


def upgrade() -> None:
    # Plain ADD COLUMN, as 0006: a batch copy would lose the expression index SQLite cannot reflect.
    for name, length in COLUMNS.items():
        op.add_column("jobs", sa.Column(name, sa.String(length), nullable=True))
    op.add_column("jobs", sa.Column("dicom", JSON_DOCUMENT, nullable=True))
    op.add_column("jobs", sa.Column("dicom_stores", JSON_DOCUMENT, nullable=True))
    op.add_column("jobs", sa.Column("dicom_store_due_at", sa.DateTime(timezone=True), nullable=True))
    op.create_index("ix_jobs_dicom_store_due_at", "jobs", ["dicom_store_due_at"])
    # Jobs stored before this revision: their study is in the payload.
    for name in COLUMNS:
        if op.get_bind().dialect.name == "postgresql":
            op.execute(f"UPDATE jobs SET {name} = payload->'study'->>'{name}' WHERE payload->'study' ? '{name}'")
        else:
            op.execute(
                f"UPDATE jobs SET {name} = json_extract(payload, '$.study.{name}') "
                f"WHERE json_extract(payload, '$.study.{name}') IS NOT NULL"
            )
        op.create_index(f"ix_jobs_owner_{name}", "jobs", ["owner", name, "created_at"])


def downgrade() -> None:
    op.drop_index("ix_jobs_dicom_store_due_at", table_name="jobs")
    for name in COLUMNS:
        op.drop_index(f"ix_jobs_owner_{name}", table_name="jobs")
    for name in (*COLUMNS, "dicom", "dicom_stores", "dicom_store_due_at"):
        op.execute(f"ALTER TABLE jobs DROP COLUMN {name}")
