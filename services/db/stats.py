"""Counts and durations of jobs, for /metrics, the reconciler and the per-client cap on queued jobs
(``count_queued_for_insert``: the count under a lock that holds until the inserting transaction ends)."""

from __future__ import annotations

import hashlib
from datetime import datetime

from sqlalchemy import (
    ColumnElement,
    func,
    literal_column,
    select,
)
from sqlalchemy.orm import Session

from services.core.status import JobStatus
from services.db.engine import sqlite_write_lock
from services.db.models import Job


def count_by_status(session: Session) -> dict[str, int]:
    counts = {s.value: 0 for s in JobStatus}
    for status, n in session.execute(select(Job.status, func.count()).group_by(Job.status)):
        counts[status] = n
    return counts


def recent_durations(
    session: Session, since: datetime | ColumnElement[datetime], limit: int = 20_000
) -> list[tuple[float, float]]:
    """(fit seconds, end-to-end seconds) of jobs that succeeded or failed since ``since`` (a time, or an
    SQL expression of one: ``services.db.clock.db_now_plus_s(-seconds)``, the database's clock)."""
    rows = session.execute(
        select(Job.created_at, Job.started_at, Job.finished_at)
        .where(
            Job.finished_at >= since,
            Job.status.in_([JobStatus.succeeded.value, JobStatus.failed.value]),
            Job.started_at.is_not(None),
        )
        .order_by(Job.finished_at.desc())
        .limit(limit)
    ).all()
    return [
        ((finished - started).total_seconds(), (finished - created).total_seconds())
        for created, started, finished in rows
        if started is not None and finished is not None
    ]


_QUEUED = Job.status == literal_column(f"'{JobStatus.queued.value}'")
"""status = 'queued' written as a literal, so that the partial index on queued jobs can serve."""


def count_all_queued(session: Session) -> int:
    """Queued jobs of every owner. The reconciler's broker check runs it every pass: it reads the
    status index's queued entries, not the whole table as ``count_by_status`` does (a sequential scan
    that grows with every job ever stored: 88 ms at 67,000 jobs on this project's VM)."""
    return int(session.scalar(select(func.count()).select_from(Job).where(_QUEUED)) or 0)


def count_queued(session: Session, owner: str, limit: int) -> int:
    """Queued jobs of ``owner``, counted up to ``limit``."""
    ids = select(Job.id).where(Job.owner == owner, _QUEUED).limit(limit)
    return int(session.scalar(select(func.count()).select_from(ids.subquery())) or 0)


SUBMISSION_LOCK_SPACE = 0x5350_4E45
"""The first key of the two-key PostgreSQL advisory locks that serialise one owner's submissions (the
second is ``owner_lock_key(owner)``). Two-key and one-key advisory locks do not overlap (PostgreSQL 15 docs,
9.27.10 Advisory Lock Functions), and no other lock of the service uses this first key."""


def owner_lock_key(owner: str) -> int:
    """The second key of ``owner``'s submission lock: the first 4 bytes of the SHA-256 of its UTF-8 name,
    as a signed 32-bit integer (the type of the lock's keys)."""
    return int.from_bytes(hashlib.sha256(owner.encode()).digest()[:4], "big", signed=True)


def lock_submissions(session: Session, owner: str) -> None:
    """Serialise ``owner``'s submissions until the session's transaction ends (commit or rollback): a
    second transaction that calls this for the same owner waits here until the first has inserted its
    jobs and committed, so a count made after this call sees every job the other stored.

    PostgreSQL: ``pg_advisory_xact_lock(SUBMISSION_LOCK_SPACE, owner_lock_key(owner))``, a transaction-level
    advisory lock, released by the server at the transaction's end (PostgreSQL 15 docs, 9.27.10). Two
    owners whose names hash alike only wait for each other. The count must be a statement after this one:
    under READ COMMITTED each statement sees what was committed before it began (PostgreSQL 15 docs,
    13.2.1), and this one may have begun before the lock's last holder committed.

    SQLite (the embedded mode): SQLite has one writer at a time; ``BEGIN IMMEDIATE`` takes the database's
    write lock now instead of at the first write ("BEGIN TRANSACTION", sqlite.org/lang_transaction.html),
    so the count and the insert that follow it run with no other writer in between (another API process
    or thread waits on the lock, up to the connection's busy timeout). Python's sqlite3 driver opens a
    transaction only before an INSERT, UPDATE or DELETE (its legacy transaction control, Python 3.11
    docs, sqlite3, "Transaction control"): a transaction already open here has written, so it already
    holds the write lock.
    """
    connection = session.connection()
    dialect = connection.dialect.name
    if dialect == "postgresql":
        connection.execute(select(func.pg_advisory_xact_lock(SUBMISSION_LOCK_SPACE, owner_lock_key(owner))))
    elif dialect == "sqlite":
        sqlite_write_lock(session)
    else:  # no lock known for it: a cap that could be passed is refused rather than kept silently
        raise NotImplementedError(f"no submission lock for the {dialect} database")


def count_queued_for_insert(session: Session, owner: str, limit: int) -> int:
    """``count_queued`` under ``lock_submissions``: the queued jobs of ``owner`` (up to ``limit``) as no
    concurrent submission of the owner can change them before this transaction inserts and commits."""
    lock_submissions(session, owner)
    return count_queued(session, owner, limit)
