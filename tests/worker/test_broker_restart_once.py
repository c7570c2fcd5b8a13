"""A broker restart is taken by one reconciler: every pool process of every worker that looked at the
broker before it restarted sees the new run id on its next pass, and each of them used to publish every
queued job again (N processes, N messages a job; the claims skipped the extra ones). Of those that see
it, the one whose claim on the broker succeeds (``jobqueue.claim_broker_restart``) publishes them; the
others publish no queued job in that pass (``tasks.broker_restart``, ``tasks.reconcile_once``).

Real pieces: a redis-server of the test's own, restarted (SIGKILL, no persistence: its messages are
gone), and a PostgreSQL database of the test's own. The two processes are two memories of the broker's
run id (each pool process holds its own, ``tasks._LAST_RUN_ID``).
"""

from __future__ import annotations

import logging

import pytest
import redis

from services.core.config import Settings
from services.core.jobqueue import claim_broker_restart, make_celery, queue_depth
from services.db import runs
from services.db.engine import session_scope
from services.worker import tasks
from services.worker.tasks import BrokerRestart, broker_restart, reconcile_once, register_tasks
from tests.conftest import queued_job
from tools.loadbench import OwnRedis


@pytest.fixture
def settings(own_broker_settings: Settings) -> Settings:
    return own_broker_settings


def test_of_the_processes_that_see_a_restart_one_takes_it(settings: Settings, own_redis: OwnRedis) -> None:
    app = make_celery(settings)
    queue = settings.queue_name
    first: dict[str, str] = {}
    second: dict[str, str] = {}
    assert broker_restart(app, queue, first) is BrokerRestart.NONE  # the first look: the run id
    assert broker_restart(app, queue, second) is BrokerRestart.NONE
    before = dict(first)
    own_redis.stop()
    own_redis.start()
    assert broker_restart(app, queue, first) is BrokerRestart.OURS
    assert broker_restart(app, queue, second) is BrokerRestart.TAKEN
    assert broker_restart(app, queue, first) is BrokerRestart.NONE  # the next pass: the same run
    assert broker_restart(app, queue, second) is BrokerRestart.NONE
    # another service's queue on the same broker lost its messages too: its own reconciler takes it
    assert broker_restart(app, f"{queue}-other", dict(before)) is BrokerRestart.OURS


def test_after_a_restart_two_reconcilers_publish_each_queued_job_once(
    settings: Settings, own_redis: OwnRedis, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    app = make_celery(settings)
    register_tasks(app, settings)
    reconcile_once(settings, app)  # this process's first look at the broker
    url = str(app.conf.broker_url)
    old_run = tasks._LAST_RUN_ID[url]
    ids = [queued_job(settings) for _ in range(3)]
    with session_scope(settings) as session:
        runs.publish(session, app, ids)
    assert queue_depth(app, settings.queue_name) == 3
    own_redis.stop()
    own_redis.start()
    assert queue_depth(app, settings.queue_name) == 0
    ours = reconcile_once(settings, app)
    assert sorted(ours.requeue) == sorted(ids) and queue_depth(app, settings.queue_name) == 3
    monkeypatch.setitem(tasks._LAST_RUN_ID, url, old_run)  # a second pool process, which looked before too
    with caplog.at_level(logging.INFO, logger="services.worker.tasks"):
        taken = reconcile_once(settings, app)
    assert taken.requeue == [] and queue_depth(app, settings.queue_name) == 3
    assert "another reconciler publishes the queued jobs again" in caplog.text  # what an operator reads


def test_a_broker_that_refuses_the_claim_still_has_every_queued_job_published_again(
    settings: Settings, own_redis: OwnRedis
) -> None:
    """A broker user whose ACL refuses SET (Redis ACL, ``-set``) cannot claim the restart: the reconciler
    publishes every queued job anyway (a duplicate is harmless, a lost message is not), as before claims."""

    def refuse_set() -> None:  # a restart forgets the ACL (no configuration file): given again after it
        with redis.Redis.from_url(own_redis.url) as admin:
            admin.execute_command("ACL", "SETUSER", "noset", "on", ">pw", "~*", "&*", "+@all", "-set")

    refuse_set()
    limited = settings.model_copy(update={"broker_url": own_redis.url.replace("redis://", "redis://noset:pw@")})
    app = make_celery(limited)
    seen: dict[str, str] = {}
    assert broker_restart(app, limited.queue_name, seen) is BrokerRestart.NONE
    own_redis.stop()
    own_redis.start()
    refuse_set()
    with pytest.raises(redis.exceptions.NoPermissionError):
        claim_broker_restart(app, limited.queue_name, "any")
    assert broker_restart(app, limited.queue_name, seen) is BrokerRestart.OURS
