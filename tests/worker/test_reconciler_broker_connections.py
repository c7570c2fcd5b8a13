"""The reconciler looks at the broker on a connection of the app's pool (``jobqueue.broker_connection``):
every pass (every ``SPINE_RECONCILE_INTERVAL_S`` in each worker) asks Redis for the broker's run id and the
queue's depth, and each look used to open a connection of its own, three new TCP connections a pass.

Real pieces: a redis-server of the test's own, whose ``total_connections_received`` (``INFO stats``)
counts every connection made to it, and a PostgreSQL database of the test's own.
"""

from __future__ import annotations

import pytest

from services.core.config import Settings
from services.core.jobqueue import make_celery, queue_depth
from services.db import runs
from services.db.engine import session_scope
from services.worker.tasks import reconcile_once, register_tasks
from tests.conftest import queued_job
from tools.celerycost import connections_received
from tools.loadbench import OwnRedis

PASSES = 5


@pytest.fixture
def settings(own_broker_settings: Settings) -> Settings:
    return own_broker_settings


def test_reconciler_passes_open_no_new_broker_connection(settings: Settings, own_redis: OwnRedis) -> None:
    app = make_celery(settings)
    register_tasks(app, settings)
    reconcile_once(settings, app)  # the first pass opens the pool's connection
    before = connections_received(own_redis.url)
    for _ in range(PASSES):
        reconcile_once(settings, app)
    # the only new one is this test's second look (before: 3 a pass, 15 here)
    assert connections_received(own_redis.url) - before == 1


def test_a_pooled_connection_reads_the_broker_again_after_a_restart(settings: Settings, own_redis: OwnRedis) -> None:
    """The pool's socket dies with the server; the next look opens it again and reads the new run."""
    app = make_celery(settings)
    register_tasks(app, settings)
    reconcile_once(settings, app)
    own_redis.stop()
    own_redis.start()
    ids = [queued_job(settings) for _ in range(2)]
    with session_scope(settings) as session:
        runs.publish(session, app, ids)
    assert queue_depth(app, settings.queue_name) == 2
    outcome = reconcile_once(settings, app)  # the run id changed: every queued job is published again
    assert sorted(outcome.requeue) == sorted(ids)
    assert queue_depth(app, settings.queue_name) == 4
