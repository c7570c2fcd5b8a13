"""SQLAlchemy 2 models of the service: every table, in one metadata (``Base.metadata``), which
``migrations/env.py`` compares with the database. The Alembic migrations in ``migrations/`` create
them, and tests/db/test_migrations.py checks that the migrated schema equals these models.

Tables: ``jobs``, ``job_measures``, ``vertebra_strains`` (results), ``api_keys``, ``job_audit``
(keys and audit trail), ``webhook_deliveries`` (one row per webhook delivery attempt).

``jobs`` is the source of truth for job state. A succeeded job's clinical measures go to
``job_measures`` (one row per job) and its per-vertebra strains to ``vertebra_strains``, so
that they can be queried with SQL; the full result stays as JSON on the job.
"""

from __future__ import annotations

import uuid
from datetime import UTC, datetime
from typing import Annotated, Any

from pydantic import PlainSerializer, WithJsonSchema
from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    CheckConstraint,
    Float,
    ForeignKey,
    Index,
    Integer,
    MetaData,
    String,
    Text,
    Uuid,
    func,
    text,
)
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

from services.core.status import JobStatus
from services.db.clock import db_now
from services.db.timestamps import UTCDateTime
from services.db.timestamps import utcnow as utcnow  # re-exported: the process's own clock

NAMING_CONVENTION = {
    "ix": "ix_%(table_name)s_%(column_0_N_name)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

JSONDocument = JSON().with_variant(JSONB(), "postgresql")


def iso_utc(value: datetime) -> str:
    """A timestamp as every job view writes it (job, lists, deliveries, webhook bodies): UTC, always
    with microseconds, ``Z`` for the zone, e.g. ``2026-12-01T16:42:47.123456Z`` (RFC 3339)."""
    return value.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


UtcTimestamp = Annotated[
    datetime,
    PlainSerializer(iso_utc, return_type=str, when_used="json"),
    WithJsonSchema({"type": "string", "format": "date-time"}),
]
"""A datetime member of a response model, written to JSON as ``iso_utc`` writes it (pydantic's own
form drops a zero fraction); its schema stays a plain ``date-time``."""


def _where_not_null(column: str) -> dict[str, Any]:
    """The keyword arguments of a partial ``Index`` over the rows whose ``column`` is not NULL, on
    PostgreSQL and on SQLite."""
    predicate = f"{column} IS NOT NULL"
    return {"postgresql_where": text(predicate), "sqlite_where": text(predicate)}


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)


class Job(Base):
    __tablename__ = "jobs"

    id: Mapped[uuid.UUID] = mapped_column(Uuid, primary_key=True, default=uuid.uuid4)
    owner: Mapped[str | None] = mapped_column(String(64), nullable=True)
    status: Mapped[str] = mapped_column(String(16), nullable=False, default=JobStatus.queued.value)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, nullable=False, default=db_now())
    """When the job was stored, on the database's clock (``services.db.clock.db_now``), as ``started_at``
    (the claim) and ``finished_at`` (the finish, the cancel, the reconciler's failure) are: so the three
    are ordered and their differences are durations whatever the writing processes' clocks. The
    default is an SQL expression evaluated in the INSERT (no server default: no migration)."""
    enqueued_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    attempts: Mapped[int] = mapped_column(Integer, nullable=False, default=0)
    payload: Mapped[dict[str, Any]] = mapped_column(JSONDocument, nullable=False)
    result: Mapped[dict[str, Any] | None] = mapped_column(JSONDocument, nullable=True)
    error: Mapped[dict[str, Any] | None] = mapped_column(JSONDocument, nullable=True)
    engine_version: Mapped[str | None] = mapped_column(String(64), nullable=True)
    idempotency_key: Mapped[str | None] = mapped_column(String(255), nullable=True)
    idempotency_kind: Mapped[str | None] = mapped_column(String(6), nullable=True)
    """Which request's key ``idempotency_key`` is (migration 0012): NULL a single submission's (or no key),
    ``batch`` entry i of a batch's key K (stored as ``K#i``), ``either`` a key with a ``#`` stored before
    0012, when the two shared one namespace (``services.db.jobs``: it answers both, as it did)."""
    idempotency_client: Mapped[str | None] = mapped_column(String(64), nullable=True)
    """The client (its API keys' name) whose ``idempotency_key`` it is (migration 0013), NULL without a key:
    the key's scope, apart from ``owner``, which an admin key's jobs do not have (admins see every job,
    but each admin client has its own keys). NULL with a key: stored before 0013 by an admin key that the
    audit trail does not name; every admin key still replays it (``services.db.jobs``)."""
    request_hash: Mapped[str | None] = mapped_column(String(64), nullable=True)
    callback_url: Mapped[str | None] = mapped_column(String(2048), nullable=True)
    lease_expires_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    """While running: when the worker's lease on the job ends unless renewed (``SPINE_LEASE_S``)."""
    # DICOM (services/dicom): the study's identifiers for the list filters, from the payload's study at
    # admission and from the image header once read; what the DICOM layer read; STOW-RS attempts.
    study_instance_uid: Mapped[str | None] = mapped_column(String(64), nullable=True)
    accession_number: Mapped[str | None] = mapped_column(String(16), nullable=True)
    patient_id: Mapped[str | None] = mapped_column(String(64), nullable=True)
    dicom: Mapped[dict[str, Any] | None] = mapped_column(JSONDocument, nullable=True)
    """``DicomProvenance`` as JSON: per view, the attributes read and where from; conflicts."""
    dicom_stores: Mapped[list[dict[str, Any]] | None] = mapped_column(JSONDocument, nullable=True)
    """One entry per STOW-RS attempt of the job's SR and figure: attempt, time, outcome."""
    dicom_store_due_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    """While the results are not stored: when the reconciler publishes the next STOW-RS attempt if no
    message did (a lost or unpublished message); null once stored or out of attempts."""

    __table_args__ = (
        CheckConstraint(f"status IN ({', '.join(repr(s.value) for s in JobStatus)})", name="status"),
        Index("ix_jobs_created_at_id", "created_at", "id"),
        Index("ix_jobs_status_created_at_id", "status", "created_at", "id"),
        Index("ix_jobs_owner_created_at_id", "owner", "created_at", "id"),
        # Partial indexes (migration 0010): a row version whose column is NULL gets no entry, so the
        # API's insert and the worker's claim skip them (the claim and the finish change status, so
        # they are not HOT updates and add an entry to every index whose predicate the new version
        # meets: PostgreSQL 15 docs, 73.7 Heap-Only Tuples). Every query that uses one compares its
        # column with a strict operator (=, <, >=), which implies IS NOT NULL: the planner still uses
        # it (PostgreSQL 15 docs, 11.8 Partial Indexes; SQLite, Partial Indexes 2.2).
        Index("ix_jobs_finished_at", "finished_at", **_where_not_null("finished_at")),
        # The per-client cap on queued jobs counts these (services/api/access.py): queued jobs only.
        Index("ix_jobs_owner_queued", "owner", postgresql_where=text("status = 'queued'"),
              sqlite_where=text("status = 'queued'")),
        # GET /v1/jobs?study_instance_uid=|accession_number=|patient_id= within an owner, newest first.
        Index("ix_jobs_owner_study_instance_uid", "owner", "study_instance_uid", "created_at",
              **_where_not_null("study_instance_uid")),
        Index("ix_jobs_owner_accession_number", "owner", "accession_number", "created_at",
              **_where_not_null("accession_number")),
        Index("ix_jobs_owner_patient_id", "owner", "patient_id", "created_at", **_where_not_null("patient_id")),
        Index("ix_jobs_dicom_store_due_at", "dicom_store_due_at", **_where_not_null("dicom_store_due_at")),
        # The reconciler's search for running jobs whose lease expired (services/db/runs.py).
        Index("ix_jobs_running_lease", "lease_expires_at", postgresql_where=text("status = 'running'"),
              sqlite_where=text("status = 'running'")),
        # Unique per owner, client and kind (a single key and a batch entry's K#i are apart, migration 0012;
        # two admin clients' keys, both of owner NULL, are apart, 0013); jobs without a key have no entry
        # (NULLs never conflict in a unique index).
        Index(
            "uq_jobs_owner_idempotency_key",
            func.coalesce(owner, ""),  # type: ignore[arg-type]
            func.coalesce(idempotency_client, ""),  # type: ignore[arg-type]
            idempotency_key,  # type: ignore[arg-type]
            func.coalesce(idempotency_kind, ""),  # type: ignore[arg-type]
            unique=True,
            **_where_not_null("idempotency_key"),
        ),
    )  # fmt: skip


class JobMeasures(Base):
    """The clinical measures of a succeeded job, one row per job, for SQL queries."""

    __tablename__ = "job_measures"

    job_id: Mapped[uuid.UUID] = mapped_column(Uuid, ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True)
    major_cobb_deg: Mapped[float | None] = mapped_column(Float, nullable=True)
    major_curve_upper: Mapped[str | None] = mapped_column(String(3), nullable=True)
    major_curve_lower: Mapped[str | None] = mapped_column(String(3), nullable=True)
    major_curve_apex: Mapped[str | None] = mapped_column(String(3), nullable=True)
    major_convexity: Mapped[str | None] = mapped_column(String(5), nullable=True)
    major_apex_axial_rotation_deg: Mapped[float | None] = mapped_column(Float, nullable=True)
    major_plane_of_max_curvature_deg: Mapped[float | None] = mapped_column(Float, nullable=True)
    curve_count: Mapped[int] = mapped_column(Integer, nullable=False)
    thoracic_kyphosis_t4_t12_deg: Mapped[float] = mapped_column(Float, nullable=False)
    thoracic_kyphosis_t5_t12_deg: Mapped[float] = mapped_column(Float, nullable=False)
    lumbar_lordosis_l1_l5_deg: Mapped[float] = mapped_column(Float, nullable=False)
    mean_registration_error_mm: Mapped[float] = mapped_column(Float, nullable=False)
    converged: Mapped[bool] = mapped_column(Boolean, nullable=False)

    __table_args__ = (Index("ix_job_measures_major_cobb_deg", "major_cobb_deg"),)


class VertebraStrain(Base):
    """Pose angles and Cosserat strains of one vertebra of a succeeded job (u rad/mm, v 1); the bending
    angles u1·Δs and u2·Δs (degrees) named by plane, as ``VertebraResult``'s."""

    __tablename__ = "vertebra_strains"

    job_id: Mapped[uuid.UUID] = mapped_column(Uuid, ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True)
    level: Mapped[str] = mapped_column(String(3), primary_key=True)
    u1: Mapped[float | None] = mapped_column(Float, nullable=True)
    u2: Mapped[float | None] = mapped_column(Float, nullable=True)
    u3: Mapped[float | None] = mapped_column(Float, nullable=True)
    v1: Mapped[float | None] = mapped_column(Float, nullable=True)
    v2: Mapped[float | None] = mapped_column(Float, nullable=True)
    v3: Mapped[float | None] = mapped_column(Float, nullable=True)
    sagittal_bending_deg: Mapped[float | None] = mapped_column(Float, nullable=True)
    frontal_bending_deg: Mapped[float | None] = mapped_column(Float, nullable=True)
    twist_deg: Mapped[float | None] = mapped_column(Float, nullable=True)
    axial_rotation_deg: Mapped[float] = mapped_column(Float, nullable=False)

    __table_args__ = (Index("ix_vertebra_strains_level_twist_deg", "level", "twist_deg"),)


class ApiKey(Base):
    __tablename__ = "api_keys"

    id: Mapped[str] = mapped_column(String(16), primary_key=True)
    name: Mapped[str] = mapped_column(String(64), nullable=False)
    role: Mapped[str] = mapped_column(String(8), nullable=False)
    key_hash: Mapped[str] = mapped_column(String(64), nullable=False)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, nullable=False, default=db_now())
    """When the key was made, on the database's clock (``services.db.clock``): a client's most recent key
    signs its webhooks (``services.db.keys.key_webhook_secret``), so keys made on hosts whose clocks
    differ are ordered as they were made."""
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    """When the key was revoked, on the database's clock (``services.db.keys.revoke``); NULL: active."""
    webhook_secret: Mapped[str | None] = mapped_column(String(64), nullable=True)

    __table_args__ = (
        CheckConstraint("role IN ('admin', 'client')", name="role"),
        Index("ix_api_keys_name", "name"),
    )


class JobAudit(Base):
    """Who (key id) created, read, listed, cancelled or had stored in the PACS again which job, when, in which
    request."""

    __tablename__ = "job_audit"

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer(), "sqlite"), primary_key=True,
                                    autoincrement=True)  # fmt: skip
    at: Mapped[datetime] = mapped_column(UTCDateTime, nullable=False)
    """When, on the database's clock (``services.db.keys.audit``): the rows of one job are in the order of
    the actions whichever API host's clock wrote them."""
    key_id: Mapped[str] = mapped_column(String(16), nullable=False)
    action: Mapped[str] = mapped_column(String(8), nullable=False)
    job_id: Mapped[uuid.UUID] = mapped_column(Uuid, nullable=False)
    request_id: Mapped[str | None] = mapped_column(String(64), nullable=True)

    __table_args__ = (
        # 'store': a request to store the job's results in the PACS again (migration 0014)
        CheckConstraint("action IN ('create', 'read', 'list', 'cancel', 'store')", name="action"),
        Index("ix_job_audit_job_id_at", "job_id", "at"),
        Index("ix_job_audit_key_id_at", "key_id", "at"),
    )


class WebhookDelivery(Base):
    """One attempt to deliver one webhook message of a job."""

    __tablename__ = "webhook_deliveries"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[uuid.UUID] = mapped_column(Uuid, ForeignKey("jobs.id", ondelete="CASCADE"), nullable=False)
    message_id: Mapped[str] = mapped_column(String(64), nullable=False)
    event: Mapped[str] = mapped_column(String(32), nullable=False)
    attempt: Mapped[int] = mapped_column(Integer, nullable=False)
    url: Mapped[str] = mapped_column(String(2048), nullable=False)
    attempted_at: Mapped[datetime] = mapped_column(UTCDateTime, nullable=False)
    """When the attempt was claimed, on the database's clock (``services.worker.webhook_tasks.deliver_once``);
    the outbox row's (attempt 0): the job's ``finished_at``, or when the broker refused the message."""
    status_code: Mapped[int | None] = mapped_column(Integer, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    duration_ms: Mapped[float | None] = mapped_column(Float, nullable=True)
    next_attempt_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)

    __table_args__ = (
        Index("ix_webhook_deliveries_job_id_id", "job_id", "id"),
        Index("uq_webhook_deliveries_message_id_attempt", "message_id", "attempt", unique=True),
        Index("ix_webhook_deliveries_next_attempt_at", "next_attempt_at"),
    )
