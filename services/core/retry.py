"""The queue's retry policy: which faults are transient, and how the worker's write of an outcome is retried.

A fault of an unreachable database or broker is transient: the Celery task that met it is
retried with backoff (``autoretry_for=TRANSIENT``), and the worker's final write of a fit's
outcome is retried in place (``write_retry``: 0.5 s doubling up to 10 s, 6 tries, ~30 s in all)
so that a fit is not thrown away by a database restart of a few seconds. A statement the database
refuses for what it holds (a constraint, a trigger, a value it cannot store) fails the same way on
every try: it is not transient (``refused_by_database``), and ``storage_refusal`` says why in words.
"""

from __future__ import annotations

import re

from kombu.exceptions import OperationalError as BrokerError
from sqlalchemy.exc import DataError, IntegrityError, InterfaceError, OperationalError, ProgrammingError, StatementError
from tenacity import retry, retry_if_exception_type, stop_after_attempt, wait_exponential

TRANSIENT = (OperationalError, InterfaceError, BrokerError, ConnectionError, TimeoutError)
"""Faults of an unreachable database or broker: the task is retried with backoff."""

write_retry = retry(
    retry=retry_if_exception_type(TRANSIENT),
    wait=wait_exponential(multiplier=0.5, max=10),
    stop=stop_after_attempt(6),
    reraise=True,
)
"""Decorator: retry a database write on a transient fault (0.5, 1, 2, 4, 8 s between the 6 tries)."""


def schema_not_migrated(exc: BaseException) -> bool:
    """Whether a database error says that a table or column the code needs is missing: a database
    never migrated, or migrated to an older revision than the code's (``spine migrate`` mends it)."""
    if not isinstance(exc, (ProgrammingError, OperationalError)):
        return False
    orig = getattr(exc, "orig", None)
    if getattr(orig, "sqlstate", None) in ("42P01", "42703"):  # PostgreSQL: undefined table, undefined column
        return True
    text = str(orig).lower()
    return "no such table" in text or "no such column" in text  # SQLite


def refused_by_database(exc: BaseException) -> bool:
    """Whether a database error is a refusal that trying again cannot mend: a statement that failed
    (SQLAlchemy's ``StatementError``: a constraint or trigger, a value the column cannot hold, a
    statement the schema does not fit) and is not ``TRANSIENT`` (a connection lost, a timeout)."""
    return isinstance(exc, StatementError) and not isinstance(exc, TRANSIENT)


_REFUSALS = ((IntegrityError, "a constraint of the database failed"), (DataError, "a value the database cannot hold"),
             (ProgrammingError, "a statement the database's schema does not accept"))  # fmt: skip


def storage_refusal(exc: StatementError) -> str:
    """Why the database refused a statement, in words: the kind of refusal, PostgreSQL's condition name
    (PostgreSQL 15 documentation, Appendix A, e.g. ``check_violation``) and its primary message, or
    SQLite's message; never the statement's parameters nor PostgreSQL's DETAIL, which may quote the
    values of the row."""
    kind = next((words for cls, words in _REFUSALS if isinstance(exc, cls)), "the database refused the statement")
    orig = exc.orig
    diag = getattr(orig, "diag", None)
    text = str(orig).strip()
    message = getattr(diag, "message_primary", None) or (text.splitlines()[0] if text else type(orig).__name__)
    if getattr(orig, "sqlstate", None):  # psycopg: the class is the condition, e.g. CheckViolation
        condition = re.sub(r"(?<!^)(?=[A-Z])", "_", type(orig).__name__).lower()
        return f"{kind}: {condition}, {message}"
    return f"{kind}: {message}"
