"""No webhook is lost to a broker restart or to a delivery task stuck on its database, with the real
service: the API in process and a real ``spine worker`` (Celery, reconciler embedded) on a PostgreSQL
database of the test's own and Redis, delivering to a real receiver.

- A job's first webhook message waits in the test's own redis-server (no worker yet) when that
  server is killed and started again (``--save ""``: the message is gone). The webhook's outbox row,
  written before the message was published, makes the reconciler publish it again: the receiver
  gets it once.
- A delivery task whose claim waits on a lock the test holds (no statement timeout, so that only
  the task's time limit can end it) is ended by its time limit (SPINE_WEBHOOK_TIMEOUT_S +
  SPINE_WEBHOOK_TASK_MARGIN_S, then 5 s to the hard limit), and the webhook is delivered once the
  lock is gone, once: by the task's own retry when the soft limit ended it, by the sweep when the hard
  limit killed it."""

from __future__ import annotations

import re
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import redis
from sqlalchemy import select, text

from services.core.jobqueue import HARD_LIMIT_GRACE_S
from services.db.deliveries import message_id
from services.db.engine import get_engine, session_scope
from services.db.models import WebhookDelivery
from tests.conftest import Service, service_env, spawned_service, spine_payload, start_own_redis
from tests.interop_helpers import TEST_WEBHOOK_SECRET, Receiver, wait_until

pytestmark = pytest.mark.integration

SWEEP_AFTER_S = 1.0


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    r = Receiver()
    yield r
    r.close()


def webhook_env(receiver: Receiver, **extra: str) -> dict[str, str]:
    return {"SPINE_WEBHOOK_ALLOWED_URLS": receiver.url("/hooks/"),
            "SPINE_WEBHOOK_SECRET": TEST_WEBHOOK_SECRET.get_secret_value(),
            "SPINE_WEBHOOK_SWEEP_AFTER_S": str(SWEEP_AFTER_S), **extra}  # fmt: skip


def submit_and_cancel(service: Service, url: str) -> str:
    job = service.submit({**spine_payload(), "callback_url": url})
    response = service.client.post(f"/v1/jobs/{job['id']}/cancel")
    assert response.status_code == 200 and response.json()["status"] == "cancelled", response.text
    return str(job["id"])


def deliveries(service: Service, job_id: str) -> list[dict[str, Any]]:
    listed: list[dict[str, Any]] = service.job(job_id)["deliveries"]
    return listed


def test_a_first_webhook_message_lost_in_a_broker_restart_is_delivered_once(
    tmp_path: Path, fresh_postgres_url: str, receiver: Receiver
) -> None:
    own = start_own_redis(tmp_path / "redis")
    env = service_env(tmp_path, DATABASE_URL=fresh_postgres_url, CELERY_BROKER_URL=own.url, **webhook_env(receiver))
    service = Service("outbox", env, tmp_path)  # its worker is started after the restart
    try:
        path = f"/hooks/{uuid.uuid4().hex}"
        job_id = submit_and_cancel(service, receiver.url(path))
        waiting = redis.Redis.from_url(own.url).llen(service.settings.webhook_queue)
        assert waiting == 1  # attempt 1's message, not consumed: no worker runs
        own.stop()  # SIGKILL: the message is gone with the server
        own.start()
        assert redis.Redis.from_url(own.url).llen(service.settings.webhook_queue) == 0
        service.start_worker()
        # the sweep runs every SPINE_RECONCILE_INTERVAL_S (1 s) and publishes the attempt SWEEP_AFTER_S past the
        # cancel, which is already past; 20 s covers Celery beat's first run and the delivery on a loaded machine
        wait_until(lambda: receiver.at(path), 20, "the lost webhook to be delivered")
        wait_until(lambda: any(d["status_code"] for d in deliveries(service, job_id)), 10,
                   "the delivery's answer to be recorded")  # fmt: skip
        listed = deliveries(service, job_id)
        assert [(d["attempt"], d["status_code"]) for d in listed] == [(1, 204)]
        outbox_row = (WebhookDelivery.attempt == 0, WebhookDelivery.job_id == uuid.UUID(job_id))
        with session_scope(service.settings) as session:  # the outbox row says why attempt 1 came late
            outbox = session.scalar(select(WebhookDelivery.error).where(*outbox_row))
        assert outbox is not None and outbox.startswith("no attempt within 1 s of the job's end")
        [got] = receiver.at(path)
        assert got.headers["webhook-id"] == message_id(job_id, "cancelled") and got.json()["type"] == "job.cancelled"
    finally:
        service.stop_worker()
        own.stop()


STUCK_SOFT_LIMIT_S = 5.0
"""The stuck delivery's soft limit (SPINE_WEBHOOK_TIMEOUT_S 1 s + SPINE_WEBHOOK_TASK_MARGIN_S 4 s). Every
delivery that claims while the test holds the lock waits on it too, and ends as the stuck one does if
its own limit passes before the test lets go: the pool checks the limits once a second and the test
polls the log, so a limit only a second or two longer than the stuck one's start makes a second
attempt whenever the machine delays either by that much (seen with three test processes on two
cores). The task's own retry starts once the stuck one is ended, a full limit before its own."""
STUCK_SWEEP_AFTER_S = STUCK_SOFT_LIMIT_S + 3.0
"""The sweep of the outbox row waits past the stuck delivery's end and the test's rollback, so that it
never claims while the lock is held."""


def test_a_delivery_stuck_on_its_database_is_ended_by_its_time_limit_and_delivered_once(
    tmp_path: Path, fresh_postgres_url: str, redis_url: str, receiver: Receiver
) -> None:
    env = webhook_env(receiver, SPINE_WEBHOOK_TIMEOUT_S="1", SPINE_WEBHOOK_TASK_MARGIN_S=str(STUCK_SOFT_LIMIT_S - 1),
                      SPINE_DB_STATEMENT_TIMEOUT_S="0")  # fmt: skip
    env["SPINE_WEBHOOK_SWEEP_AFTER_S"] = str(STUCK_SWEEP_AFTER_S)
    hard_limit_s = STUCK_SOFT_LIMIT_S + HARD_LIMIT_GRACE_S
    with spawned_service("stuck", tmp_path, postgres_url=fresh_postgres_url, redis_url=redis_url, **env) as service:
        path = f"/hooks/{uuid.uuid4().hex}"
        job = service.submit({**spine_payload(), "callback_url": receiver.url(path)})
        holder = get_engine(service.settings).connect()
        try:  # attempt 1's row inserted, not committed: the worker's claim of it waits for this transaction
            row = {"job": uuid.UUID(job["id"]), "mid": message_id(job["id"], "cancelled"), "url": receiver.url(path)}
            holder.execute(text("INSERT INTO webhook_deliveries (job_id, message_id, event, attempt, url, "
                                "attempted_at) VALUES (:job, :mid, 'job.cancelled', 1, :url, now())"), row)  # fmt: skip
            started = time.monotonic()
            assert service.client.post(f"/v1/jobs/{job['id']}/cancel").status_code == 200
            # the soft limit after the task started, the hard one HARD_LIMIT_GRACE_S later; 4 s for the pool's
            # check and the log
            limit = re.compile(r"(Soft|Hard) time limit \([\d.]+s\) exceeded for spine\.deliver_webhook")
            wait_until(lambda: limit.search(service.worker_log()), hard_limit_s + 4, "the delivery's time limit")
            stopped_after = time.monotonic() - started
            assert receiver.at(path) == []  # nothing is delivered while its claim waits
        finally:
            holder.rollback()
            holder.close()
        # retried at once when the soft limit ended it; else the outbox row (due at the cancel) is swept
        # STUCK_SWEEP_AFTER_S later, at a reconcile pass every 1 s
        wait_until(lambda: receiver.at(path), STUCK_SWEEP_AFTER_S + 5, "the webhook to be delivered")
        # the attempt's row is listed from its claim, its status once the receiver's answer is written
        wait_until(lambda: any(d["status_code"] for d in deliveries(service, job["id"])), 10,
                   "the delivery's answer to be recorded")  # fmt: skip
        listed = deliveries(service, job["id"])
        assert [(d["attempt"], d["status_code"]) for d in listed] == [(1, 204)]
        assert len(receiver.at(path)) == 1 and stopped_after < hard_limit_s + 4
