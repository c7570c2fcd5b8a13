"""A Redis restart found by a reconciler process that never looked at the broker before it: a pool process
that had run no pass yet, or a worker its supervisor started again after the restart (seen: Celery's
worker stopped on the lost connection). Its pass publishes at once the queued jobs whose messages went to
the broker's previous run (they waited longer than the broker has been up), not ``SPINE_QUEUED_TIMEOUT_S``
later. Real PostgreSQL, a real redis-server of the test's own (killed and started again), the pass in a
process of its own, and a real Celery worker running the job afterwards."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from celery.contrib.testing.worker import start_worker

from services.core.config import Settings
from services.core.jobqueue import enqueue, make_celery, queue_depth
from services.db.engine import session_scope
from services.db.migrate import upgrade
from services.db.models import Job
from services.worker.tasks import register_tasks
from tests.conftest import queued_job, start_own_redis
from tests.faults import wait_until
from tools.loadbench import OwnRedis

CHECKOUT = Path(__file__).resolve().parents[2]
PASS = """
import json, sys
from services.core.config import Settings
from services.core.jobqueue import make_celery
from services.worker.tasks import reconcile_once
settings = Settings()
outcome = reconcile_once(settings, make_celery(settings))
print(json.dumps([str(job_id) for job_id in outcome.requeue]))
"""
"""One reconciler pass in a new process (none of its memory), its requeued job ids printed as JSON."""


@pytest.fixture
def own_redis(tmp_path: Path) -> Iterator[OwnRedis]:
    own = start_own_redis(tmp_path / "redis")
    yield own
    own.stop()


def _status(settings: Settings, job_id: uuid.UUID) -> str:
    with session_scope(settings) as session:
        job = session.get(Job, job_id)
        assert job is not None
        return job.status


def test_a_pass_that_never_saw_the_broker_before_its_restart_publishes_the_lost_jobs_at_once(
    tmp_path: Path, fresh_postgres_url: str, own_redis: OwnRedis
) -> None:
    queue = f"test-unseen-{uuid.uuid4().hex[:8]}"
    env = {"DATABASE_URL": fresh_postgres_url, "CELERY_BROKER_URL": own_redis.url, "SPINE_QUEUE_NAME": queue,
           "SPINE_DATA_DIR": str(tmp_path / "data"), "SPINE_QUEUED_TIMEOUT_S": "3600"}  # fmt: skip
    settings = Settings(DATABASE_URL=fresh_postgres_url, CELERY_BROKER_URL=own_redis.url, queue_name=queue,
                        data_dir=tmp_path / "data", queued_timeout_s=3600)  # fmt: skip
    upgrade(settings, quiet=True)
    app = make_celery(settings)
    job_id = queued_job(settings)
    assert enqueue(app, [job_id]) == 1 and queue_depth(app, queue) == 1  # published, enqueued_at now
    time.sleep(1.5)  # it waits longer than the restarted broker will have been up plus 1 s (tasks.UPTIME_MARGIN_S)
    own_redis.stop()  # SIGKILL, then a new run: the message is gone
    own_redis.start()
    assert queue_depth(app, queue) == 0

    done = subprocess.run([sys.executable, "-c", PASS], env={**os.environ, **env}, cwd=CHECKOUT,
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads(done.stdout.strip().splitlines()[-1]) == [str(job_id)], done.stderr[-3000:]
    assert "the broker restarted" in done.stderr
    assert queue_depth(app, queue) == 1  # published again at once, the queued timeout an hour away

    register_tasks(app, settings)
    with start_worker(app, perform_ping_check=False, queues=[queue], shutdown_timeout=30.0):
        wait_until(lambda: _status(settings, job_id) == "succeeded", 20, "the job's run")
