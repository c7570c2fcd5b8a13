"""The reconciler's webhook sweep, on real SQLite and PostgreSQL stores and a real broker: a webhook
whose message could not be published when its job ended (a broker that refuses connections) is
recorded as attempt 0 and published again once it is overdue; nothing is published twice, and two
deliveries of one attempt racing each other make one request."""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from datetime import timedelta
from typing import Any

import pytest
from sqlalchemy import func, select, update

from services.core.config import Settings
from services.core.jobqueue import make_celery, queue_depth
from services.db import deliveries as store
from services.db import jobs as repo
from services.db.engine import session_scope
from services.db.models import WebhookDelivery, utcnow
from services.worker import webhook_tasks
from tests.conftest import spine_payload
from tests.interop_helpers import Receiver, cancelled_job_calling

BACKENDS = pytest.mark.parametrize("db_settings", ["sqlite", "postgresql"], indirect=True)
URL = "http://127.0.0.1:9/hooks/sweep"


def settle_earlier_tests(settings: Settings) -> None:
    """The PostgreSQL store is shared by this session's tests: nothing of theirs is due any more."""
    with session_scope(settings) as session:
        session.execute(update(WebhookDelivery).values(next_attempt_at=None))


def cancelled_job_with_callback(settings: Settings) -> uuid.UUID:
    payload: dict[str, Any] = spine_payload()
    payload["callback_url"] = URL
    with session_scope(settings) as session:
        job, _ = repo.create_job(session, payload)
        repo.cancel_job(session, job.id)
    return job.id


def record(settings: Settings, row: dict[str, Any], **values: Any) -> None:
    """Store one finished attempt, as ``deliver_once`` leaves it."""
    with session_scope(settings) as session:
        full = {"status_code": None, "error": None, "duration_ms": None, "next_attempt_at": None, **row, **values}
        assert store.claim(session, **full) is not None


def rows(settings: Settings, job_id: uuid.UUID) -> list[WebhookDelivery]:
    with session_scope(settings) as session:
        query = select(WebhookDelivery).where(WebhookDelivery.job_id == job_id).order_by(WebhookDelivery.id)
        return list(session.scalars(query))


@BACKENDS
def test_an_unpublished_webhook_is_recorded_and_swept_once(db_settings: Settings) -> None:
    settings = db_settings.model_copy(update={"webhook_sweep_after_s": 1.0})
    settle_earlier_tests(settings)
    job_id = cancelled_job_with_callback(settings)
    unreachable = make_celery(settings.model_copy(update={"broker_url": "redis://127.0.0.1:1/0"}))
    assert not store.job_ended(settings, job_id, "cancelled", url=URL, celery=unreachable)
    [row] = rows(settings, job_id)
    assert (row.attempt, row.status_code, row.url, row.event) == (0, None, URL, "job.cancelled")
    assert row.error is not None and row.error.startswith("not published: ")
    assert row.message_id == store.message_id(job_id, "cancelled") and row.next_attempt_at is not None

    broker = make_celery(settings)  # the embedded broker: a real queue, no server needed
    queue = settings.webhook_queue
    not_yet_due = settings.model_copy(update={"webhook_sweep_after_s": 3600.0})
    assert webhook_tasks.sweep(not_yet_due, broker) == 0
    [due] = rows(settings, job_id)
    assert due.next_attempt_at == row.next_attempt_at
    wait_past(due.next_attempt_at, 1.05)  # due: published again; then not before 1 s more, however slow this machine
    assert webhook_tasks.sweep(settings, broker) == 1
    assert queue_depth(broker, queue) == 1
    assert webhook_tasks.sweep(settings, broker) == 0  # postponed: published once
    [postponed] = rows(settings, job_id)
    assert postponed.next_attempt_at is not None and postponed.next_attempt_at > row.next_attempt_at  # type: ignore[operator]


REFUSED = "redis://127.0.0.1:1/0"
"""A broker that refuses connections: a publish to it fails after Celery's publish retries (about 0.5 s)."""


@BACKENDS
def test_a_refusal_recorded_after_the_sweep_published_the_message_is_shown(
    db_settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The broker refuses the publish of a cancelled job's webhook, but only after its outbox row (written
    first, due at once) has become overdue and the reconciler's sweep has published the message again
    (``SPINE_WEBHOOK_SWEEP_AFTER_S`` shorter than the publish's retries). The job still shows the refusal
    (attempt 0 "not published"), and the row keeps the due time the sweep gave it (the refusal does not
    make it due again at once)."""
    settings = db_settings.model_copy(update={"webhook_sweep_after_s": 0.2})
    settle_earlier_tests(settings)
    job_id = cancelled_job_with_callback(settings)
    broker = make_celery(settings)  # the embedded broker: the sweep's publish is taken
    refused = make_celery(settings.model_copy(update={"broker_url": REFUSED}))
    publish = store.publish_webhook
    swept: list[WebhookDelivery] = []

    def sweep_then_refuse(*args: Any, **kwargs: Any) -> None:  # the order under test; the refusal is real
        [row] = rows(settings, job_id)
        assert row.error is None and row.next_attempt_at is not None
        wait_past(row.next_attempt_at, 0.25)
        assert webhook_tasks.sweep(settings, broker) == 1
        swept.extend(rows(settings, job_id))
        publish(*args, **kwargs)

    monkeypatch.setattr(store, "publish_webhook", sweep_then_refuse)
    assert not store.job_ended(settings, job_id, "cancelled", url=URL, celery=refused)
    assert queue_depth(broker, settings.webhook_queue) == 1
    [row] = rows(settings, job_id)
    assert row.error is not None and row.error.startswith("not published: "), row.error
    with session_scope(settings) as session:
        assert [(d.attempt, d.status_code) for d in store.deliveries(session, job_id)] == [(0, None)]
    assert row.next_attempt_at == swept[0].next_attempt_at  # the sweep's: SWEEP_AFTER_S after it published


@BACKENDS
def test_a_refusal_recorded_while_the_sweep_publishes_the_message_is_kept(
    db_settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The sweep read the overdue outbox row (no error yet) and publishes the message when the refusal of
    the job's own publish is recorded: the sweep's note ("no attempt within …") does not replace it."""
    settings = db_settings.model_copy(update={"webhook_sweep_after_s": 0.2})
    settle_earlier_tests(settings)
    job_id = cancelled_job_with_callback(settings)
    with session_scope(settings) as session:  # what job_ended writes before it publishes
        store.record_due(session, job_id, "cancelled", URL, utcnow())
    [row] = rows(settings, job_id)
    assert row.next_attempt_at is not None
    wait_past(row.next_attempt_at, 0.25)
    broker = make_celery(settings)
    refused = make_celery(settings.model_copy(update={"broker_url": REFUSED}))
    publish = webhook_tasks.publish_webhook

    def publish_while_refused(*args: Any, **kwargs: Any) -> None:  # the order under test; the refusal is real
        publish(*args, **kwargs)
        assert not store.job_ended(settings, job_id, "cancelled", url=URL, celery=refused)

    monkeypatch.setattr(webhook_tasks, "publish_webhook", publish_while_refused)
    assert webhook_tasks.sweep(settings, broker) == 1
    [row] = rows(settings, job_id)
    assert row.error is not None and row.error.startswith("not published: "), row.error
    with session_scope(settings) as session:
        assert [(d.attempt, d.status_code) for d in store.deliveries(session, job_id)] == [(0, None)]


@BACKENDS
def test_a_message_whose_next_attempt_came_is_not_swept(db_settings: Settings) -> None:
    settings = db_settings.model_copy(update={"webhook_sweep_after_s": 0.05})
    settle_earlier_tests(settings)
    job_id = cancelled_job_with_callback(settings)
    mid = store.message_id(job_id, "cancelled")
    now = utcnow()
    base = {"job_id": job_id, "message_id": mid, "event": "job.cancelled", "url": URL, "attempted_at": now,
            "status_code": None, "duration_ms": None}  # fmt: skip
    record(settings, {**base, "attempt": 1}, error="HTTP 500", next_attempt_at=now)
    record(settings, {**base, "attempt": 2}, error="HTTP 503", next_attempt_at=now)
    old = cancelled_job_with_callback(settings)  # due two days ago: outside the sweep's window
    record(settings, {**base, "job_id": old, "message_id": store.message_id(old, "cancelled"),
                                "attempt": 1}, error="HTTP 500", next_attempt_at=now - timedelta(days=2))  # fmt: skip
    wait_past(now, 0.1)
    broker = make_celery(settings)
    assert webhook_tasks.sweep(settings, broker) == 1  # attempt 2's retry never came; attempt 1's did
    assert queue_depth(broker, settings.webhook_queue) == 1
    with session_scope(settings) as session:  # attempt 3 accepted: nothing is overdue any more
        session.execute(update(WebhookDelivery).where(WebhookDelivery.attempt == 2).values(next_attempt_at=now))
    record(settings, {**base, "attempt": 3, "status_code": 204})
    assert webhook_tasks.sweep(settings, broker) == 0


@BACKENDS
def test_a_repeated_attempt_is_dropped_before_any_request(db_settings: Settings) -> None:
    job_id = cancelled_job_with_callback(db_settings)
    mid = store.message_id(job_id, "cancelled")
    record(db_settings, {"job_id": job_id, "message_id": mid, "event": "job.cancelled", "attempt": 2,
                                   "url": URL, "attempted_at": utcnow()}, error="HTTP 500")  # fmt: skip
    assert webhook_tasks.deliver_once(db_settings, job_id, "cancelled", 2) is None
    with session_scope(db_settings) as session:
        mine = select(func.count()).select_from(WebhookDelivery).where(WebhookDelivery.job_id == job_id)
        count = session.scalar(mine)
    assert count == 1  # no second row: not even a refusal was recorded


def wait_past(moment: Any, seconds: float) -> None:
    import time

    while utcnow() < moment + timedelta(seconds=seconds):
        time.sleep(0.02)


@pytest.fixture()
def slow_receiver() -> Iterator[Receiver]:
    """A receiver that holds each request 0.3 s, so that two deliveries of one attempt overlap."""
    receiver = Receiver()
    handler = receiver.server.RequestHandlerClass
    answer = handler.do_POST  # type: ignore[attr-defined]

    def slow(self: Any) -> None:
        time.sleep(0.3)
        answer(self)

    handler.do_POST = slow  # type: ignore[attr-defined]
    yield receiver
    receiver.close()


@BACKENDS
def test_two_deliveries_of_one_attempt_make_one_request(db_settings: Settings, slow_receiver: Receiver) -> None:
    """Attempt 2 of a message run twice at once (its retry and a sweep): a check-then-insert would
    let both through and the receiver get it twice; the claim is an insert under a unique index, so
    exactly one of the racing deliveries makes the request."""
    settings, job_id = cancelled_job_calling(db_settings, slow_receiver.url(f"/hooks/{uuid.uuid4().hex}"))
    start = threading.Barrier(2)

    def deliver(_: int) -> float | None:
        start.wait()
        return webhook_tasks.deliver_once(settings, job_id, "cancelled", 2)

    with ThreadPoolExecutor(2) as pool:
        assert list(pool.map(deliver, range(2))) == [None, None]
    assert [r.answered for r in slow_receiver.received] == [204]
    [row] = rows(settings, job_id)
    assert (row.attempt, row.status_code, row.error, row.next_attempt_at) == (2, 204, None, None)


# ------------------------------------------------------------------ the maximum and attempts in flight


@BACKENDS
def test_the_sweep_never_publishes_past_the_last_attempt(db_settings: Settings) -> None:
    """A row of the last attempt whose worker stopped mid-request (in flight, past its deadline) is
    closed, not followed by one attempt more; one below the maximum is followed by the next."""
    settings = db_settings.model_copy(update={"webhook_sweep_after_s": 0.05, "webhook_max_attempts": 3})
    settle_earlier_tests(settings)
    now = utcnow()
    last, below = cancelled_job_with_callback(settings), cancelled_job_with_callback(settings)
    for job_id, attempt in ((last, 3), (below, 2)):  # claimed, never finished: what a dead worker leaves
        record(settings, {"job_id": job_id, "message_id": store.message_id(job_id, "cancelled"),
                          "event": "job.cancelled", "attempt": attempt, "url": URL, "attempted_at": now},
               next_attempt_at=now)  # fmt: skip
    wait_past(now, 0.1)
    broker = make_celery(settings)
    assert webhook_tasks.sweep(settings, broker) == 1
    assert queue_depth(broker, settings.webhook_queue) == 1
    [closed] = rows(settings, last)
    assert closed.next_attempt_at is None and closed.error is not None and "no attempt left" in closed.error
    [swept] = rows(settings, below)
    assert swept.error is not None and swept.error.startswith("no outcome recorded")
    with session_scope(settings) as session:  # however late the next sweep runs, only `below` is ever due again
        due = store.overdue(session, due_before=utcnow() + timedelta(days=1), due_after=now - timedelta(days=1))
    assert [row.job_id for row in due if row.job_id in (last, below)] == [below]


@BACKENDS
def test_an_attempt_in_flight_within_its_deadline_is_not_swept(db_settings: Settings) -> None:
    settings = db_settings.model_copy(update={"webhook_sweep_after_s": 0.05, "webhook_timeout_s": 30.0})
    settle_earlier_tests(settings)
    job_id = cancelled_job_with_callback(settings)
    now = utcnow()
    record(settings, {"job_id": job_id, "message_id": store.message_id(job_id, "cancelled"), "event": "job.cancelled",
                      "attempt": 1, "url": URL, "attempted_at": now},
           next_attempt_at=now + timedelta(seconds=30))  # fmt: skip
    wait_past(now, 0.1)
    assert webhook_tasks.sweep(settings, make_celery(settings)) == 0


@BACKENDS
def test_an_attempt_past_the_maximum_is_dropped_before_any_request(db_settings: Settings) -> None:
    receiver = Receiver()
    try:
        url = receiver.url(f"/hooks/{uuid.uuid4().hex}")
        settings, job_id = cancelled_job_calling(db_settings, url, webhook_max_attempts=3)
        assert webhook_tasks.deliver_once(settings, job_id, "cancelled", 4) is None
        assert webhook_tasks.deliver_once(settings, job_id, "cancelled", 0) is None
        assert receiver.received == [] and rows(settings, job_id) == []
    finally:
        receiver.close()


@BACKENDS
def test_the_next_attempt_is_due_after_this_one_ended(db_settings: Settings, slow_receiver: Receiver) -> None:
    url = slow_receiver.url(f"/hooks/{uuid.uuid4().hex}")
    slow_receiver.plan[url.removeprefix(slow_receiver.url(""))] = [500]
    settings, job_id = cancelled_job_calling(db_settings, url, webhook_retry_base_s=1.0)
    assert webhook_tasks.deliver_once(settings, job_id, "cancelled", 1) == 1.0
    [row] = rows(settings, job_id)
    assert row.status_code == 500 and row.next_attempt_at is not None
    assert row.next_attempt_at - row.attempted_at >= timedelta(seconds=1.0 + 0.3)  # the receiver held it 0.3 s
