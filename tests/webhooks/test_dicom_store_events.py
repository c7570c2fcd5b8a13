"""The outbox of the webhooks that end a run of STOW-RS attempts (``job.dicom_stored``,
``job.dicom_store_failed``), on real SQLite and PostgreSQL stores, a real Redis broker (and one that
refuses connections), the real ``spine.deliver_webhook`` task and a real HTTP receiver: the event's outbox
row is written in the transaction that records the attempt ending the run, so that a message the broker
refuses, or one never published (the worker stopped after the commit), is published by the reconciler's
sweep with its run; and the message ids of the job's end events are those they always were."""

from __future__ import annotations

import ast
import json
import time
import uuid
from collections.abc import Iterator
from datetime import timedelta
from typing import Any

import pytest
import redis
from sqlalchemy import select, update
from standardwebhooks import Webhook

from services.core.config import Settings
from services.core.jobqueue import DELIVER_WEBHOOK, make_celery
from services.db import deliveries as store
from services.db import dicom_stores
from services.db import jobs as repo
from services.db.engine import session_scope
from services.db.models import Job, WebhookDelivery, utcnow
from services.worker import dicom_tasks, webhook_tasks
from services.worker.tasks import execute_job
from services.worker.webhook_tasks import register_webhook_tasks
from tests.conftest import _purge_queue, spine_payload
from tests.interop_helpers import TEST_WEBHOOK_SECRET, Receiver

BACKENDS = pytest.mark.parametrize("db_settings", ["sqlite", "postgresql"], indirect=True)
REFUSED = "redis://127.0.0.1:1/0"
"""A broker that refuses connections: a publish to it fails after Celery's publish retries (about 0.5 s)."""
SWEEP_AFTER_S = 0.2
"""SPINE_WEBHOOK_SWEEP_AFTER_S of these tests: how long after its event an outbox row is overdue (s)."""


@pytest.fixture
def settings(db_settings: Settings, redis_url: str, receiver: Receiver) -> Iterator[Settings]:
    """``db_settings`` storing results in a PACS nobody listens at (port 9), on a Redis queue of the test's
    own, calling back ``receiver``; nothing of the shared PostgreSQL store's earlier tests is due."""
    queue = f"spine-test-{uuid.uuid4().hex[:8]}"
    made = db_settings.model_copy(update={
        "queue_name": queue, "broker_url": redis_url, "dicomweb_url": "http://127.0.0.1:9/dicom-web",
        "dicomweb_store_results": True, "dicomweb_max_attempts": 1, "webhook_allowed_urls": receiver.url("/hooks/"),
        "webhook_secret": TEST_WEBHOOK_SECRET, "webhook_sweep_after_s": SWEEP_AFTER_S,
    })  # fmt: skip
    with session_scope(made) as session:
        session.execute(update(WebhookDelivery).values(next_attempt_at=None))
    yield made
    _purge_queue(redis_url, queue)


def _succeeded_job(settings: Settings, receiver: Receiver) -> uuid.UUID:
    """A job without study calling back ``receiver``, run in process (its STOW-RS not published: the
    results are not stored by that run), its ``job.succeeded`` delivered: nothing of it is due."""
    payload: dict[str, Any] = {**spine_payload(), "callback_url": receiver.url(f"/hooks/{uuid.uuid4().hex}")}
    with session_scope(settings) as session:
        job, _ = repo.create_job(session, payload)
    assert execute_job(settings.model_copy(update={"dicomweb_store_results": False}), job.id) == "succeeded"
    assert webhook_tasks.deliver_once(settings, job.id, "succeeded", 1) is None
    return job.id


def _rows(settings: Settings, job_id: uuid.UUID, event: str) -> list[WebhookDelivery]:
    with session_scope(settings) as session:
        query = select(WebhookDelivery).where(WebhookDelivery.job_id == job_id, WebhookDelivery.event == event)
        return list(session.scalars(query.order_by(WebhookDelivery.id)))


def _wait_past(moment: Any, seconds: float) -> None:
    while utcnow() < moment + timedelta(seconds=seconds):
        time.sleep(0.02)


def _swept_and_delivered(settings: Settings, job_id: uuid.UUID, receiver: Receiver) -> dict[str, Any]:
    """Once the outbox row of the job's ``job.dicom_store_failed`` is overdue, the sweep publishes it (to
    Redis) with its run, once; the message, run by the real ``spine.deliver_webhook`` task, reaches the
    receiver: its verified body."""
    [outbox] = _rows(settings, job_id, "job.dicom_store_failed")
    _wait_past(outbox.next_attempt_at, SWEEP_AFTER_S + 0.05)
    broker = make_celery(settings)
    assert webhook_tasks.sweep(settings, broker) == 1
    assert webhook_tasks.sweep(settings, broker) == 0  # postponed: published once
    queued = redis.Redis.from_url(settings.celery_broker_url).lrange(settings.webhook_queue, 0, -1)
    messages = [json.loads(raw)["headers"] for raw in queued]
    assert {m["task"] for m in messages} == {DELIVER_WEBHOOK}
    calls = [ast.literal_eval(m["argsrepr"]) for m in messages]  # besides job.succeeded's, delivered in process
    [args] = [a for a in calls if a[1] != "succeeded"]
    assert args == [str(job_id), "dicom_store_failed", 1, 1]  # the event, its first attempt, the run
    register_webhook_tasks(broker, settings)
    broker.tasks[DELIVER_WEBHOOK].apply(args=args)
    got = receiver.received[-1]
    assert got.headers["webhook-id"] == store.message_id(job_id, "dicom_store_failed", 1)
    body: dict[str, Any] = Webhook(TEST_WEBHOOK_SECRET.get_secret_value()).verify(got.body, got.headers)
    assert body["type"] == "job.dicom_store_failed" and body["data"]["id"] == str(job_id)
    [entry] = body["data"]["dicom_stores"]
    assert (entry["attempt"], entry["ok"], entry["problem_type"]) == (1, False, "dicom-no-patient-identity")
    return body


@BACKENDS
def test_a_run_event_the_broker_refuses_is_published_by_the_sweep(settings: Settings, receiver: Receiver) -> None:
    """The STOW-RS attempt of a job without study ends its run (not storable): its ``job.dicom_store_failed``
    outbox row is written with the attempt (due at once, its time the attempt's); the broker refuses the
    message, which the job then lists as attempt 0 "not published"; the sweep publishes it, the receiver
    gets it once, and the job lists the accepted attempt after it."""
    job_id = _succeeded_job(settings, receiver)
    refusing = settings.model_copy(update={"broker_url": REFUSED})
    outcome = dicom_tasks.store_once(refusing, job_id, 1)
    assert (outcome.ok, outcome.problem_type, outcome.next_attempt_at) == (False, "dicom-no-patient-identity", None)
    [outbox] = _rows(settings, job_id, "job.dicom_store_failed")
    assert (outbox.attempt, outbox.message_id) == (0, store.message_id(job_id, "dicom_store_failed", 1))
    assert outbox.error is not None and outbox.error.startswith("not published: "), outbox.error
    with session_scope(settings) as session:
        [stored] = session.scalar(select(Job.dicom_stores).where(Job.id == job_id)) or []
        listed = [(d.event, d.attempt, d.status_code) for d in store.deliveries(session, job_id)]
    assert listed == [("job.succeeded", 1, 204), ("job.dicom_store_failed", 0, None)]

    body = _swept_and_delivered(settings, job_id, receiver)
    assert body["data"]["dicom_stores"] == [stored]
    with session_scope(settings) as session:
        listed = [(d.event, d.attempt, d.status_code) for d in store.deliveries(session, job_id)]
    assert listed == [
        ("job.succeeded", 1, 204), ("job.dicom_store_failed", 0, None), ("job.dicom_store_failed", 1, 204)]  # fmt: skip
    assert len(receiver.received) == 2  # job.succeeded, job.dicom_store_failed: once each


@pytest.mark.parametrize("db_settings", ["postgresql"], indirect=True)
def test_a_run_event_recorded_with_its_attempt_survives_a_worker_that_stops_before_publishing(
    settings: Settings, receiver: Receiver
) -> None:
    """Recording the attempt that ends the run and its event's outbox row is one transaction: rolled back
    (the worker stopped before the commit), neither is there, and the attempt is made again; committed,
    with the worker stopped before it published the message, the sweep publishes it ("no attempt within
    … of the end of its STOW-RS run") and the receiver gets it."""
    job_id = _succeeded_job(settings, receiver)
    with session_scope(settings) as session:
        source = dicom_stores.store_source(session, job_id)
    assert source is not None
    failed = dicom_stores.DicomStoreAttempt(attempt=1, attempted_at=source.read_at, ok=False,
                                            problem_type="dicom-no-patient-identity",
                                            error="the job has no study")  # fmt: skip
    sweep_after = timedelta(seconds=settings.dicomweb_sweep_after_s)
    with pytest.raises(RuntimeError), session_scope(settings) as session:
        assert dicom_stores.record(session, job_id, failed, sweep_after) is not None
        raise RuntimeError("the worker stops before the commit")
    assert _rows(settings, job_id, "job.dicom_store_failed") == []
    with session_scope(settings) as session:
        assert session.scalar(select(Job.dicom_stores).where(Job.id == job_id)) in (None, [])

    with session_scope(settings) as session:  # committed; then the worker stops: nothing published
        end = dicom_stores.record(session, job_id, failed, sweep_after)
        url = session.scalar(select(Job.callback_url).where(Job.id == job_id))
    assert end == dicom_stores.RunEnd("dicom_store_failed", 1, str(url))
    [outbox] = _rows(settings, job_id, "job.dicom_store_failed")
    assert (outbox.attempt, outbox.error, outbox.attempted_at) == (0, None, source.read_at)
    _swept_and_delivered(settings, job_id, receiver)
    outbox, accepted = _rows(settings, job_id, "job.dicom_store_failed")
    assert outbox.error is not None and outbox.error.startswith(
        f"no attempt within {SWEEP_AFTER_S:g} s of the end of its STOW-RS run"), outbox.error  # fmt: skip
    assert (accepted.attempt, accepted.status_code) == (1, 204)


def test_the_job_end_events_keep_their_message_ids() -> None:
    """Receivers drop duplicates by ``webhook-id``: a job's end events keep the ids the service always gave
    them (computed by the function before the run events, for this fixed job id), and no run event's id is
    one of them."""
    job_id = "3f2b9c4e-8d1a-4e6b-9a7c-0d5e2f1b6a83"
    assert {status: store.message_id(job_id, status) for status in ("succeeded", "failed", "cancelled")} == {
        "succeeded": "msg_c3a2e33fc8205007b496453d9be7ecf2",
        "failed": "msg_b4ee6e30e45152e5b997346d35bfc8bb",
        "cancelled": "msg_c6715eecefba5b4b9175588b9229ade8",
    }
    assert store.message_id(uuid.UUID(job_id), "succeeded") == "msg_c3a2e33fc8205007b496453d9be7ecf2"
    runs = {store.message_id(job_id, event, run) for event in store.RUN_EVENTS for run in (1, 2, 6)}
    assert len(runs) == 6 and not runs & {store.message_id(job_id, s) for s in ("succeeded", "failed", "cancelled")}
