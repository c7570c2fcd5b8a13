"""The database server's clock, for every time the database stores: job leases and the due times the
reconciler looks for, a job's created, started and finished times, the times of its webhook and STOW-RS
attempts, API keys' and the audit trail's times.

A time written by one process on one host and compared by another (the reconciler, the API) means the
same instant to both only when both take "now" from one clock. The processes' own clocks may differ
by more than the margins these times hold: a lease (``SPINE_LEASE_S``, 10 s), the queued timeout
(``SPINE_QUEUED_TIMEOUT_S``, 10 s), the webhook and STOW-RS sweeps' delays
(``SPINE_WEBHOOK_SWEEP_AFTER_S``, ``SPINE_DICOMWEB_SWEEP_AFTER_S``, 300 s). A writer whose clock is
behind writes a time already past for the comparer (a live run taken back, a message waiting in the
broker published again), a writer ahead or a comparer behind finds a lost one late. So each of these
times is written and compared in SQL with the database's clock:

- ``jobs.lease_expires_at`` (``services.db.runs``: claim, renewal, the reconciler's test);
- ``jobs.enqueued_at`` (``services.db.jobs``' inserts; ``services.db.runs``: the reconciler's queued
  timeout and re-enqueue, ``release_claim``);
- ``webhook_deliveries.next_attempt_at`` (``services.db.deliveries``; the worker's
  ``services.worker.webhook_tasks``: an attempt's deadline, its retry, the sweep);
- ``jobs.dicom_store_due_at`` (``services.db.dicom_stores``; ``services.worker.dicom_tasks``).

A job's shown times are written with it too, so that they are ordered and their differences are
durations whatever the clocks of the processes that write them (the API, a worker, the reconciler):

- ``jobs.created_at`` (``services.db.jobs``' inserts, returned to the API's answer; the model's default);
- ``jobs.started_at`` (``services.db.runs``: the claim);
- ``jobs.finished_at`` (``services.db.runs``: the finish and the reconciler's failure, whose webhook
  outbox row's ``attempted_at`` is that same value; ``services.db.jobs``: the cancel).

So are the other times stored, only shown or ordered, so that they are ordered with the job's and with
one another whatever the clocks of the processes that write them:

- ``webhook_deliveries.attempted_at`` (``services.worker.webhook_tasks.deliver_once``: the claim,
  returned by it; ``services.db.deliveries``: the outbox row the API writes after a cancel takes the
  job's stored ``finished_at``, a message the broker refused the time it was marked);
- ``jobs.dicom_stores[].attempted_at`` and ``next_attempt_at`` (``services.db.dicom_stores``: read with
  the job the attempt stores, or when attempt 0 is recorded; the next attempt that plus its delay);
- ``api_keys.created_at`` (the most recent key of a client signs its webhooks) and ``revoked_at``
  (``services.db.keys``);
- ``job_audit.at`` (``services.db.keys.audit``: the rows of one job in the order of the actions).

A process's own clock (``services.db.timestamps.utcnow``) is left for what that process alone compares
or shows and never stores (e.g. a ``Retry-After`` date; a webhook's signature timestamp, which its
receiver compares with its own clock); a duration it measures itself is a monotonic clock's
(``time.monotonic``).

The database's clock is:

- PostgreSQL: ``statement_timestamp()``, the start of the current statement (PostgreSQL 15
  documentation, §9.9.5 "Current Date/Time"; ``now()`` would be the start of the transaction);
- SQLite: ``strftime('%Y-%m-%d %H:%M:%f', 'now')``, UTC to the millisecond, constant within one
  statement (SQLite documentation, "Date And Time Functions", §2 and §3), written with three more
  digits so that it has the form SQLAlchemy stores for a ``DateTime`` (``YYYY-MM-DD HH:MM:SS.ffffff``)
  and compares with stored values as text. The embedded SQLite is one host's file, so this is that
  host's clock, read by the database library.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import Float, bindparam
from sqlalchemy.ext.compiler import compiles
from sqlalchemy.sql.elements import BindParameter
from sqlalchemy.sql.functions import FunctionElement

from services.db.timestamps import UTCDateTime

_SQLITE_NOW = "strftime('%Y-%m-%d %H:%M:%f', 'now'{modifier}) || '000'"


class db_now(FunctionElement[datetime]):  # noqa: N801 (an SQL function, named as SQLAlchemy's are)
    """The database server's current time (UTC), read when the statement runs."""

    type = UTCDateTime()
    name = "db_now"
    inherit_cache = True


class db_now_plus(FunctionElement[datetime]):  # noqa: N801
    """The database server's current time plus a number of seconds (a bound ``float``), e.g. the end
    of a lease: ``db_now_plus(bindparam("lease_s"))``."""

    type = UTCDateTime()
    name = "db_now_plus"
    inherit_cache = True

    def __init__(self, seconds: BindParameter[float]):
        super().__init__(seconds)


def seconds_param(name: str) -> BindParameter[float]:
    """A bound number of seconds, for ``db_now_plus``, given when the statement is executed."""
    return bindparam(name, type_=Float())


def seconds_until(due: datetime | None, now: datetime) -> float:
    """Seconds from ``now`` to ``due``, both read on the database's clock in one statement, at least 0;
    0 without a due time (nothing to wait for)."""
    return 0.0 if due is None else max(0.0, (due - now).total_seconds())


def db_now_plus_s(seconds: float) -> db_now_plus:
    """The database server's current time plus ``seconds`` (negative: minus), the number bound with
    the statement (a parameter of its own: several in one statement do not clash)."""
    return db_now_plus(bindparam("seconds", seconds, type_=Float(), unique=True))


def _only_argument(element: db_now_plus, compiler: Any, **kw: Any) -> str:
    return str(compiler.process(next(iter(element.clauses)), **kw))


@compiles(db_now, "postgresql")
def _now_postgresql(element: db_now, compiler: Any, **kw: Any) -> str:
    return "statement_timestamp()"


@compiles(db_now_plus, "postgresql")
def _plus_postgresql(element: db_now_plus, compiler: Any, **kw: Any) -> str:
    return f"(statement_timestamp() + make_interval(secs => {_only_argument(element, compiler, **kw)}))"


@compiles(db_now, "sqlite")
def _now_sqlite(element: db_now, compiler: Any, **kw: Any) -> str:
    return f"({_SQLITE_NOW.format(modifier='')})"


@compiles(db_now_plus, "sqlite")
def _plus_sqlite(element: db_now_plus, compiler: Any, **kw: Any) -> str:
    # the modifier "+NNN.NNN seconds" (SQLite "Date And Time Functions", §3)
    modifier = f", printf('%+.3f seconds', {_only_argument(element, compiler, **kw)})"
    return f"({_SQLITE_NOW.format(modifier=modifier)})"
