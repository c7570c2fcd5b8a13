"""A job failed by an unexpected exception of the engine: what its client reads (``GET /v1/jobs/{id}``,
the job stored in the real PostgreSQL or SQLite database by the worker's ``execute_job``) says what
happened and names the job, never the exception's type nor message (here a file path of the server);
the worker logs the exception with its traceback and the job id, for the operator.

The engine's bug is stood in for by ``register_model`` raising (no payload makes today's engine raise
outside its own errors): the database, the worker's run and the API are the real ones."""

from __future__ import annotations

import logging
import uuid
from collections.abc import Iterator
from typing import Any, NoReturn

import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from services.core.config import Settings
from services.core.problems import PROBLEM_BASE
from services.db.engine import session_scope
from services.db.jobs import create_job
from services.worker import tasks
from tests.conftest import make_key, spine_payload

INTERNAL_PATH = "/srv/spine/internal/priors/frontal_v7.json"
"""A server path that the exception's message holds and the client must not read."""


def _engine_bug(*_args: Any, **_kwargs: Any) -> NoReturn:
    raise FileNotFoundError(2, "No such file or directory", INTERNAL_PATH)


@pytest.fixture
def admin(db_settings: Settings) -> Iterator[TestClient]:
    with TestClient(create_app(db_settings)) as client:
        client.headers["Authorization"] = f"Bearer {make_key(db_settings, f'ops-{uuid.uuid4().hex[:8]}', 'admin')}"
        yield client


@pytest.mark.parametrize("db_settings", ["postgresql", "sqlite"], indirect=True)
def test_an_engine_error_shows_the_client_no_internals_and_logs_the_traceback(
    db_settings: Settings, admin: TestClient, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    with session_scope(db_settings) as session:
        job, _ = create_job(session, spine_payload())
    monkeypatch.setattr(tasks, "register_model", _engine_bug)
    with caplog.at_level(logging.INFO, logger="services.worker.tasks"):
        assert tasks.execute_job(db_settings, job.id) == "failed"

    read = admin.get(f"/v1/jobs/{job.id}")
    assert read.status_code == 200, read.text
    error = read.json()["error"]
    assert error["type"] == PROBLEM_BASE + "engine-error" and error["status"] == 500
    assert error["instance"] == f"/v1/jobs/{job.id}"
    assert str(job.id) in error["detail"] and "operator" in error["detail"]
    shown = read.text + admin.get("/v1/jobs").text
    for internal in (INTERNAL_PATH, "FileNotFoundError", "No such file", "Errno"):
        assert internal not in shown, internal

    logged = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(logged) == 1, [r.getMessage() for r in logged]
    assert str(job.id) in logged[0].getMessage() and "engine-error" in logged[0].getMessage()
    assert logged[0].exc_info is not None and logged[0].exc_info[0] is FileNotFoundError  # the traceback, worker side
    assert INTERNAL_PATH in caplog.text
