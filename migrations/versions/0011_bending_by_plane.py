"""``vertebra_strains``: the two bending columns are named by anatomical plane, as the result's
fields (``VertebraResult.sagittal_bending_deg`` and ``frontal_bending_deg`` in openapi.yaml), not by
the film that shows them: ``pa_bending_deg`` (u1·Δs, bending about d1, in the sagittal plane)
becomes ``sagittal_bending_deg`` and ``lateral_bending_deg`` (u2·Δs, about d2, in the frontal
plane) becomes ``frontal_bending_deg``. The values stay.

``ALTER TABLE … RENAME COLUMN`` on both backends (PostgreSQL 15 docs, ALTER TABLE; SQLite from
3.25, "ALTER TABLE", 2. ALTER TABLE RENAME COLUMN); no index names either column.

Revision ID: 0011_bending_by_plane
Revises: 0010_jobs_partial_indexes
Create Date: 2026-12-02
"""

from collections.abc import Sequence

from alembic import op

revision: str = "0011_bending_by_plane"
down_revision: str | None = "0010_jobs_partial_indexes"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

RENAMES = (("pa_bending_deg", "sagittal_bending_deg"), ("lateral_bending_deg", "frontal_bending_deg"))
"""(by view, by plane) of each column."""


def _rename(old: str, new: str) -> None:
    op.execute(f"ALTER TABLE vertebra_strains RENAME COLUMN {old} TO {new}")


def upgrade() -> None:
    for by_view, by_plane in RENAMES:
        _rename(by_view, by_plane)


def downgrade() -> None:
    for by_view, by_plane in RENAMES:
        _rename(by_plane, by_view)
