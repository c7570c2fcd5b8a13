"""The UTC timestamp column type of every table (``UTCDateTime``) and the process's own clock
(``utcnow``), apart from ``services.db.models`` so that ``services.db.clock`` (the database's clock,
typed ``UTCDateTime``) and the models (whose job times default to that clock) import it without a
cycle. ``services.db.models`` re-exports both names."""

from __future__ import annotations

from datetime import UTC, datetime

from sqlalchemy import DateTime
from sqlalchemy.engine import Dialect
from sqlalchemy.types import TypeDecorator


class UTCDateTime(TypeDecorator[datetime]):
    """A timezone-aware UTC timestamp on every backend (SQLite stores it naive, in UTC)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("naive datetime given to a UTC column")
        value = value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


def utcnow() -> datetime:
    """This process's own clock (UTC): for the times only this process compares or shows, never for
    a time the database stores (``services.db.clock.db_now``)."""
    return datetime.now(UTC)
