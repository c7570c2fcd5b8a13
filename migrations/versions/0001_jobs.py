"""Jobs, their clinical measures and per-vertebra strains.

Revision ID: 0001
Revises:
Create Date: 2026-11-22
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects.postgresql import JSONB

revision: str = "0001"
down_revision: str | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

JSONDocument = sa.JSON().with_variant(JSONB(), "postgresql")
TS = sa.DateTime(timezone=True)


def upgrade() -> None:
    op.create_table(
        "jobs",
        sa.Column("id", sa.Uuid(), nullable=False),
        sa.Column("owner", sa.String(64), nullable=True),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("created_at", TS, nullable=False),
        sa.Column("enqueued_at", TS, nullable=True),
        sa.Column("started_at", TS, nullable=True),
        sa.Column("finished_at", TS, nullable=True),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("payload", JSONDocument, nullable=False),
        sa.Column("result", JSONDocument, nullable=True),
        sa.Column("error", JSONDocument, nullable=True),
        sa.Column("engine_version", sa.String(64), nullable=True),
        sa.Column("idempotency_key", sa.String(255), nullable=True),
        sa.Column("request_hash", sa.String(64), nullable=True),
        sa.PrimaryKeyConstraint("id", name="pk_jobs"),
        sa.CheckConstraint(
            "status IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')", name="ck_jobs_status"
        ),
    )
    op.create_index("ix_jobs_created_at_id", "jobs", ["created_at", "id"])
    op.create_index("ix_jobs_status_created_at_id", "jobs", ["status", "created_at", "id"])
    op.create_index("ix_jobs_owner_created_at_id", "jobs", ["owner", "created_at", "id"])
    op.create_index("ix_jobs_finished_at", "jobs", ["finished_at"])
    op.create_index(
        "uq_jobs_owner_idempotency_key",
        "jobs",
        [sa.text("coalesce(owner, '')"), "idempotency_key"],
        unique=True,
    )
    op.create_table(
        "job_measures",
        sa.Column("job_id", sa.Uuid(), nullable=False),
        sa.Column("major_cobb_deg", sa.Float(), nullable=True),
        sa.Column("major_curve_upper", sa.String(3), nullable=True),
        sa.Column("major_curve_lower", sa.String(3), nullable=True),
        sa.Column("major_curve_apex", sa.String(3), nullable=True),
        sa.Column("major_convexity", sa.String(5), nullable=True),
        sa.Column("major_apex_axial_rotation_deg", sa.Float(), nullable=True),
        sa.Column("major_plane_of_max_curvature_deg", sa.Float(), nullable=True),
        sa.Column("curve_count", sa.Integer(), nullable=False),
        sa.Column("thoracic_kyphosis_t4_t12_deg", sa.Float(), nullable=False),
        sa.Column("thoracic_kyphosis_t5_t12_deg", sa.Float(), nullable=False),
        sa.Column("lumbar_lordosis_l1_l5_deg", sa.Float(), nullable=False),
        sa.Column("mean_registration_error_mm", sa.Float(), nullable=False),
        sa.Column("converged", sa.Boolean(), nullable=False),
        sa.ForeignKeyConstraint(["job_id"], ["jobs.id"], name="fk_job_measures_job_id_jobs", ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("job_id", name="pk_job_measures"),
    )
    op.create_index("ix_job_measures_major_cobb_deg", "job_measures", ["major_cobb_deg"])
    op.create_table(
        "vertebra_strains",
        sa.Column("job_id", sa.Uuid(), nullable=False),
        sa.Column("level", sa.String(3), nullable=False),
        sa.Column("u1", sa.Float(), nullable=True),
        sa.Column("u2", sa.Float(), nullable=True),
        sa.Column("u3", sa.Float(), nullable=True),
        sa.Column("v1", sa.Float(), nullable=True),
        sa.Column("v2", sa.Float(), nullable=True),
        sa.Column("v3", sa.Float(), nullable=True),
        sa.Column("pa_bending_deg", sa.Float(), nullable=True),
        sa.Column("lateral_bending_deg", sa.Float(), nullable=True),
        sa.Column("twist_deg", sa.Float(), nullable=True),
        sa.Column("axial_rotation_deg", sa.Float(), nullable=False),
        sa.ForeignKeyConstraint(["job_id"], ["jobs.id"], name="fk_vertebra_strains_job_id_jobs", ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("job_id", "level", name="pk_vertebra_strains"),
    )
    op.create_index("ix_vertebra_strains_level_twist_deg", "vertebra_strains", ["level", "twist_deg"])


def downgrade() -> None:
    op.drop_index("ix_vertebra_strains_level_twist_deg", table_name="vertebra_strains")
    op.drop_table("vertebra_strains")
    op.drop_index("ix_job_measures_major_cobb_deg", table_name="job_measures")
    op.drop_table("job_measures")
    op.drop_index("uq_jobs_owner_idempotency_key", table_name="jobs")
    op.drop_index("ix_jobs_finished_at", table_name="jobs")
    op.drop_index("ix_jobs_owner_created_at_id", table_name="jobs")
    op.drop_index("ix_jobs_status_created_at_id", table_name="jobs")
    op.drop_index("ix_jobs_created_at_id", table_name="jobs")
    op.drop_table("jobs")
