"""The outcome of a webhook attempt is written even when the database drops the worker's connection while
the receiver answers (a PostgreSQL restart or failover at that moment): the write is retried in place,
so the attempt is recorded as answered, not left in flight for the sweep to send again (a duplicate
delivery with a log saying the worker stopped). Real PostgreSQL (a database of the test's own, whose
connections the receiver terminates with ``pg_terminate_backend``) and a real HTTP receiver."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import psycopg
import pytest
from sqlalchemy import select

from services.core.config import Settings
from services.db.engine import session_scope
from services.db.migrate import upgrade
from services.db.models import WebhookDelivery
from services.worker import webhook_tasks
from tests.interop_helpers import Receiver, cancelled_job_calling


@pytest.fixture
def dropping_receiver(fresh_postgres_url: str) -> Iterator[Receiver]:
    """A receiver that, before answering 204, terminates every other connection to the test's database:
    the worker's pooled connection is dead when it writes the attempt's outcome."""
    receiver = Receiver()
    handler = receiver.server.RequestHandlerClass
    answer = handler.do_POST  # type: ignore[attr-defined]
    admin_url = fresh_postgres_url.replace("postgresql+psycopg://", "postgresql://", 1)

    def drop_then_answer(self: Any) -> None:
        with psycopg.connect(admin_url, autocommit=True) as admin:
            admin.execute("SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                          "WHERE datname = current_database() AND pid <> pg_backend_pid()")  # fmt: skip
        answer(self)

    handler.do_POST = drop_then_answer  # type: ignore[attr-defined]
    yield receiver
    receiver.close()


def test_an_answered_attempt_is_recorded_after_the_database_dropped_the_connection(
    tmp_path: Path, fresh_postgres_url: str, dropping_receiver: Receiver
) -> None:
    settings = Settings(data_dir=tmp_path, DATABASE_URL=fresh_postgres_url)
    upgrade(settings, quiet=True)
    settings, job_id = cancelled_job_calling(settings, dropping_receiver.url(f"/hooks/{uuid.uuid4().hex}"))
    assert webhook_tasks.deliver_once(settings, job_id, "cancelled", 1) is None  # no next attempt, no error
    assert [r.answered for r in dropping_receiver.received] == [204]
    with session_scope(settings) as session:
        rows = session.scalars(select(WebhookDelivery).where(WebhookDelivery.job_id == job_id)).all()
        [row] = rows
        assert (row.attempt, row.status_code, row.error, row.next_attempt_at) == (1, 204, None, None)
        assert row.duration_ms is not None  # the outcome, not a row left in flight
