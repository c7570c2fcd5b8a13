"""A client's read of a job by id: another client's job is not even loaded, so the answer (404, as for an
unknown id) costs the same and its time does not tell that the job exists (docs/security.md)."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from typing import Any

import pytest
from sqlalchemy import event

from services.core.config import Settings
from services.db import jobs as repo
from services.db.engine import session_scope
from services.db.models import Job
from tests.conftest import spine_payload

BACKENDS = pytest.mark.parametrize("db_settings", ["sqlite", "postgresql"], indirect=True)


@pytest.fixture()
def loaded() -> Iterator[list[uuid.UUID]]:
    """The ids of the Job rows the ORM builds objects from while the test runs."""
    ids: list[uuid.UUID] = []

    def on_load(job: Job, _context: Any) -> None:
        ids.append(job.id)

    event.listen(Job, "load", on_load)
    yield ids
    event.remove(Job, "load", on_load)


@BACKENDS
def test_another_clients_job_is_not_loaded(db_settings: Settings, loaded: list[uuid.UUID]) -> None:
    with session_scope(db_settings) as session:
        job, _ = repo.create_job(session, spine_payload(), owner="clinic-a")
        job_id = job.id
    with session_scope(db_settings) as session:
        with pytest.raises(repo.JobNotFound):
            repo.get_job(session, job_id, owner="clinic-b")
        assert loaded == []
        assert repo.get_job(session, job_id, owner="clinic-a").id == job_id
        assert repo.get_job(session, job_id).id == job_id  # the operator's read, without an owner
