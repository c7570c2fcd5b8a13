"""The /metrics window of finished jobs (``SPINE_METRICS_WINDOW_S``) ends at the database's clock, not at
the API replica's own: an API host whose clock is an hour off reported the jobs just finished as none
(its clock ahead: the window lay after them) or counted jobs finished up to an hour before the window
(its clock behind).

Real pieces: the database (SQLite, and a PostgreSQL database of the test's own), the engine that runs
the job, and the embedded broker. The fault is injected in this test process only: the API's metrics
module's Python clock (``utcnow``, which it read for the window) is moved an hour from the host's; the
job's own times are written by a worker on the host's clock."""

from __future__ import annotations

from datetime import timedelta

import pytest
from prometheus_client.core import Metric

from services.api import metrics
from services.core.config import Settings
from services.core.jobqueue import make_celery
from services.db import jobs
from services.db.engine import session_scope
from services.db.models import Job
from services.worker.tasks import execute_job
from tests.conftest import spine_payload
from tests.faults import SkewedClock

SKEW = timedelta(hours=1)
"""How far the API's clock is from the host's: twelve times the window (SPINE_METRICS_WINDOW_S, 300 s)."""


@pytest.fixture
def settings(fresh_db_settings: Settings) -> Settings:
    return fresh_db_settings


def _finished_recent(settings: Settings) -> float:
    """``spine_jobs_finished_recent`` as one scrape of the API's collector reports it."""
    collected: list[Metric] = list(metrics.JobStateCollector(settings, make_celery(settings)).collect())
    (family,) = [m for m in collected if m.name == "spine_jobs_finished_recent"]
    return float(family.samples[0].value)


@pytest.mark.parametrize("offset", [SKEW, -SKEW], ids=["api-ahead", "api-behind"])
def test_the_metrics_window_is_on_the_databases_clock(
    settings: Settings, monkeypatch: pytest.MonkeyPatch, offset: timedelta
) -> None:
    """One job finished just now (inside the window) and one whose end is moved to 30 min ago (outside
    it, inside the skew): the scrape counts the first only, whatever the API's own clock says."""
    finished = []
    for _ in range(2):
        with session_scope(settings) as session:
            job, _ = jobs.create_job(session, spine_payload())
        assert execute_job(settings, job.id) == "succeeded"
        finished.append(job.id)
    with session_scope(settings) as session:
        old = session.get(Job, finished[1])
        assert old is not None and old.finished_at is not None and old.started_at is not None
        old.created_at -= SKEW / 2
        old.started_at -= SKEW / 2
        old.finished_at -= SKEW / 2
    clock = SkewedClock()
    clock.offset = offset
    monkeypatch.setattr(metrics, "utcnow", clock, raising=False)  # the API's clock, where the module reads one
    assert _finished_recent(settings) == 1
