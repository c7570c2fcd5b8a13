"""The queue's retry policy: which faults are transient, and how the worker's write of an outcome is retried.

A fault of an unreachable database or broker is transient: the Celery task that met it is
retried with backoff (``autoretry_for=TRANSIENT``), and the worker's final write of a fit's
outcome is retried in place (``write_retry``: 0.5 s doubling up to 10 s, 6 tries, ~30 s in all)
so that a fit is not thrown away by a database restart of a few seconds.
"""

from __future__ import annotations

from kombu.exceptions import OperationalError as BrokerError
from sqlalchemy.exc import InterfaceError, OperationalError, ProgrammingError
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
