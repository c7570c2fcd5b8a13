"""A job whose outcome the database refuses for good (here a trigger on ``job_measures`` of the real
SQLite or PostgreSQL database, as a constraint or a faulty trigger would) fails at once with a
``result-not-stored`` problem naming the refusal in words: one run, no traceback, one error line with the
job id, and its webhook's ``job.failed`` outbox row written with the failure."""

from __future__ import annotations

import logging
import uuid
from collections.abc import Iterator
from typing import Any

import pytest
from sqlalchemy import func, select, text

from services.core.config import Settings
from services.core.problems import PROBLEM_BASE
from services.db import deliveries
from services.db.engine import get_engine, session_scope
from services.db.jobs import create_job
from services.db.models import Job, JobMeasures, WebhookDelivery
from services.worker.tasks import execute_job
from tests.conftest import spine_payload

BACKENDS = pytest.mark.parametrize("db_settings", ["sqlite", "postgresql"], indirect=True)
REFUSAL = "measures refused by a test trigger"


@pytest.fixture
def refused_job(db_settings: Settings) -> Iterator[uuid.UUID]:
    """A queued job (with a callback_url) whose ``job_measures`` row the database refuses (SQLSTATE
    23514 check_violation on PostgreSQL, RAISE(ABORT) on SQLite); the trigger is dropped after."""
    payload: dict[str, Any] = spine_payload()
    payload["callback_url"] = "http://127.0.0.1:9/hooks/refused"
    with session_scope(db_settings) as session:
        job, _ = create_job(session, payload)
    name = f"refuse_measures_{uuid.uuid4().hex[:8]}"
    engine = get_engine(db_settings)
    with engine.begin() as connection:
        if engine.dialect.name == "postgresql":  # the database is the session's: only this job's row is refused
            connection.execute(text(
                f"CREATE FUNCTION {name}() RETURNS trigger AS $$ BEGIN IF NEW.job_id = '{job.id}' THEN "
                f"RAISE EXCEPTION '{REFUSAL}' USING ERRCODE = 'check_violation'; END IF; RETURN NEW; END $$ "
                "LANGUAGE plpgsql"))  # fmt: skip
            connection.execute(text(f"CREATE TRIGGER {name} BEFORE INSERT ON job_measures FOR EACH ROW "
                                    f"EXECUTE FUNCTION {name}()"))  # fmt: skip
        else:
            connection.execute(text(f"CREATE TRIGGER {name} BEFORE INSERT ON job_measures "
                                    f"BEGIN SELECT RAISE(ABORT, '{REFUSAL}'); END"))  # fmt: skip
    yield job.id
    with engine.begin() as connection:
        connection.execute(text(f"DROP TRIGGER {name}" + (" ON job_measures" if engine.dialect.name == "postgresql"
                                                          else "")))  # fmt: skip
        if engine.dialect.name == "postgresql":
            connection.execute(text(f"DROP FUNCTION {name}()"))


@BACKENDS
def test_a_result_the_database_refuses_fails_the_job_at_once(
    db_settings: Settings, refused_job: uuid.UUID, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.INFO):
        assert execute_job(db_settings, refused_job) == "failed"
    with session_scope(db_settings) as session:
        job = session.get(Job, refused_job)
        assert job is not None
        measures = session.scalar(select(func.count()).where(JobMeasures.job_id == refused_job))
        outbox = session.scalars(select(WebhookDelivery).where(WebhookDelivery.job_id == refused_job)).all()
    assert (job.status, job.attempts, job.result, job.lease_expires_at, measures) == ("failed", 1, None, None, 0)
    assert job.error is not None and job.error["type"] == PROBLEM_BASE + "result-not-stored"
    assert job.error["status"] == 500 and job.error["instance"] == f"/v1/jobs/{refused_job}"
    detail = job.error["detail"]
    assert "the database refused to store the job's outcome (a constraint of the database failed" in detail
    assert REFUSAL in detail and "not run again" in detail
    if db_settings.sqlalchemy_url.startswith("postgresql"):
        assert "check_violation" in detail
    assert [(r.attempt, r.event, r.error) for r in outbox] == [(0, "job.failed", None)]
    assert outbox[0].message_id == deliveries.message_id(refused_job, "failed")

    errors = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(errors) == 1 and str(refused_job) in errors[0].getMessage(), [r.getMessage() for r in errors]
    assert errors[0].exc_info is None and "result-not-stored" in errors[0].getMessage()
    assert execute_job(db_settings, refused_job) == "skipped"  # a second delivery runs nothing
