"""Publishing and delivering a job's webhook when it ends.

``job_ended`` is called where a job reaches a final state (the worker after storing an outcome,
the API after a cancel, the reconciler after failing a lost job); it only publishes a message on
the webhook queue (``<SPINE_QUEUE_NAME>.webhooks``), never raises, and costs nothing for a job
without ``callback_url`` because callers look at the payload first. A message it cannot publish
is recorded as attempt 0, and the reconciler's ``sweep`` publishes it (and any attempt whose
message was lost) again. The ``spine.deliver_webhook``
task POSTs the job, records the attempt in ``webhook_deliveries`` and, unless the receiver answered
2xx (or 410 Gone), publishes the next attempt with exponential backoff (``Retry-After`` honoured),
up to ``SPINE_WEBHOOK_MAX_ATTEMPTS``. The message id is derived from the job and its final
status, so every attempt of a message carries the same ``webhook-id`` and a message that a
receiver already accepted is not sent again.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
import uuid
from collections.abc import Iterable
from datetime import timedelta
from email.utils import parsedate_to_datetime
from typing import Any

import httpx
from celery import Celery
from sqlalchemy import select
from sqlalchemy.orm import Session

from services.core.config import Settings
from services.core.jobqueue import make_celery
from services.core.retry import TRANSIENT
from services.core.status import FINAL_STATUSES
from services.core.webhook_policy import WebhooksDisabled, allow_list, destination_problem
from services.db import deliveries as store
from services.db.engine import session_scope
from services.db.jobs import job_json
from services.db.models import Job, iso_utc, utcnow
from services.webhooks.signing import secret_for, signed_headers

log = logging.getLogger(__name__)

DELIVER = "spine.deliver_webhook"
MAX_RETRY_DELAY_S = 120.0
"""Cap of the delay between attempts (below the Redis visibility timeout, so a scheduled attempt
is never delivered twice)."""
USER_AGENT = "spine-webhooks/1"
_NAMESPACE = uuid.UUID("0b7e3b9e-4f53-5a8e-9c4e-5e1f2a6c9d01")


def message_id(job_id: uuid.UUID | str, status: str) -> str:
    """The Standard Webhooks message id of a job's end: the same on every attempt."""
    return "msg_" + uuid.uuid5(_NAMESPACE, f"{job_id}:{status}").hex


# ------------------------------------------------------------------ publishing

_PUBLISHERS: dict[tuple[str, int], Celery] = {}
_LOCK = threading.Lock()


def _publisher(settings: Settings) -> Celery:
    key = (settings.celery_broker_url, os.getpid())
    with _LOCK:
        if key not in _PUBLISHERS:
            _PUBLISHERS[key] = make_celery(settings)
        return _PUBLISHERS[key]


def publish_attempt(
    settings: Settings, job_id: uuid.UUID | str, status: str, attempt: int, *, countdown: float = 0.0,
    celery: Celery | None = None,
) -> None:  # fmt: skip
    app = celery or _publisher(settings)
    app.send_task(
        DELIVER, args=[str(job_id), status, attempt], countdown=countdown or None, queue=settings.webhook_queue
    )


def job_ended(
    settings: Settings, job_id: uuid.UUID | str, status: str, *, url: str | None = None,
    celery: Celery | None = None,
) -> bool:  # fmt: skip
    """Publish the first delivery of a job's webhook. Never raises; False when publishing failed.

    When it fails and ``url`` (the job's callback_url) is given, an attempt 0 is recorded on the
    job, due now, so that the reconciler's ``sweep`` publishes the message later.
    """
    try:
        publish_attempt(settings, job_id, status, 1, celery=celery)
        return True
    except Exception as exc:
        log.warning("could not publish the webhook of job %s (%s): %s", job_id, status, exc)
        if url:
            _record_unpublished(settings, uuid.UUID(str(job_id)), status, url, exc)
        return False


def _record_unpublished(settings: Settings, job_id: uuid.UUID, status: str, url: str, exc: Exception) -> None:
    now = utcnow()
    row = {"job_id": job_id, "message_id": message_id(job_id, status), "event": f"job.{status}", "attempt": 0,
           "url": url, "attempted_at": now}  # fmt: skip
    error = f"not published: {type(exc).__name__}; the reconciler publishes it again"
    try:
        with session_scope(settings) as session:  # a second failure for the same message finds the first row
            store.claim(session, **row, status_code=None, error=error, duration_ms=None, next_attempt_at=now)
    except Exception as db_exc:  # the database is down too: nothing left to remember it by
        log.error("webhook of job %s (%s) lost: neither published nor recorded: %s", job_id, status, db_exc)


def jobs_ended(session: Session, settings: Settings, job_ids: Iterable[uuid.UUID], celery: Celery) -> int:
    """``job_ended`` for those of ``job_ids`` that have a callback_url (the reconciler's failures)."""
    ids = list(job_ids)
    if not ids:
        return 0
    sent = 0
    for job_id, status, url in session.execute(select(Job.id, Job.status, Job.callback_url).where(Job.id.in_(ids))):
        if url and status in FINAL_STATUSES:
            sent += job_ended(settings, job_id, str(status), url=url, celery=celery)
    return sent


def sweep(settings: Settings, celery: Celery, window: timedelta = timedelta(days=1)) -> int:
    """Publish again every attempt that was due ``SPINE_WEBHOOK_SWEEP_AFTER_S`` ago and never came.

    Such an attempt's message was not published (attempt 0: the broker was down when the job
    ended) or was lost with a broker. Each one found is published and its row's due time moved
    ``SPINE_WEBHOOK_SWEEP_AFTER_S`` ahead, so it is published again only if this one is lost too.
    Looks back ``window``. Returns how many were published.
    """
    after = timedelta(seconds=settings.webhook_sweep_after_s)
    now = utcnow()
    with session_scope(settings) as session:
        rows = store.overdue(session, due_before=now - after, due_after=now - window)
        published = 0
        for row in rows:
            status = row.event.removeprefix("job.")
            try:
                publish_attempt(settings, row.job_id, status, row.attempt + 1, celery=celery)
            except Exception as exc:
                log.warning("webhook sweep: could not publish for job %s: %s", row.job_id, exc)
                break
            store.postpone(session, row.id, now + after)
            published += 1
    if published:
        log.info("webhook sweep: published %d overdue webhook attempts", published)
    return published


# ------------------------------------------------------------------ delivering

_CLIENTS: dict[tuple[float, int], httpx.Client] = {}


def _client(timeout: float) -> httpx.Client:
    key = (timeout, os.getpid())
    with _LOCK:
        if key not in _CLIENTS:
            # No redirects (a 3xx could point anywhere), no proxies or .netrc from the environment.
            _CLIENTS[key] = httpx.Client(
                timeout=timeout, follow_redirects=False, trust_env=False, headers={"user-agent": USER_AGENT}
            )
        return _CLIENTS[key]


def webhook_body(job: Job, status: str) -> bytes:
    """The JSON a receiver gets: ``{"type": "job.<status>", "timestamp", "data": <the job>}``."""
    finished = job.finished_at or utcnow()
    body = {"type": f"job.{status}", "timestamp": iso_utc(finished), "data": job_json(job)}
    return json.dumps(body, separators=(",", ":"), ensure_ascii=False).encode()


def retry_delay(settings: Settings, attempt: int, retry_after: str | None = None) -> float:
    """Delay before attempt ``attempt + 1``: base·2^(attempt−1), or the receiver's Retry-After if longer."""
    delay = settings.webhook_retry_base_s * 2 ** (attempt - 1)
    wanted = _retry_after_s(retry_after)
    if wanted is not None:
        delay = max(delay, wanted)
    return min(delay, MAX_RETRY_DELAY_S)


def _retry_after_s(value: str | None) -> float | None:
    if not value:
        return None
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        return max(0.0, (parsedate_to_datetime(value) - utcnow()).total_seconds())
    except (TypeError, ValueError):
        return None


def deliver_once(settings: Settings, job_id: uuid.UUID, status: str, attempt: int) -> float | None:
    """Make attempt ``attempt`` of the job's webhook; return the delay before the next one, or None.

    The attempt's row is claimed before the request (``store.claim``): a second delivery of the
    same attempt finds it and does nothing. Until the outcome is written, the row's
    ``next_attempt_at`` is the request's deadline (``SPINE_WEBHOOK_TIMEOUT_S`` after it started),
    so a worker that dies mid-request leaves a row the reconciler's ``sweep`` picks up.
    """
    mid = message_id(job_id, status)
    attempted_at = utcnow()
    with session_scope(settings) as session:
        job = session.get(Job, job_id)
        url = job.callback_url if job is not None else None
        if job is None or not url or store.delivered(session, mid):
            return None
        row_id = store.claim(
            session, job_id=job_id, message_id=mid, event=f"job.{status}", attempt=attempt, url=url,
            attempted_at=attempted_at, next_attempt_at=attempted_at + timedelta(seconds=settings.webhook_timeout_s),
        )  # fmt: skip
        if row_id is None:  # published twice (a repeated cancel, a sweep, a redelivery)
            return None
        body = webhook_body(job, status)
        key = secret_for(session, job.owner, settings)
    try:
        refused = destination_problem(url, allow_list(settings.webhook_allowed_urls))
    except WebhooksDisabled as exc:
        refused = str(exc)
    if refused is None and key is None:
        refused = "no webhook signing secret is configured"
    if refused is not None:  # the operator changed the settings since the job was submitted
        _finish(settings, row_id, error=f"not sent: {refused}")
        return None
    assert key is not None
    headers = signed_headers(key, mid, int(time.time()), body)
    started = time.perf_counter()
    status_code: int | None = None
    retry_after: str | None = None
    error: str | None = None
    try:
        with _client(settings.webhook_timeout_s).stream("POST", url, content=body, headers=headers) as response:
            status_code = response.status_code
            retry_after = response.headers.get("retry-after")
    except httpx.HTTPError as exc:
        error = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    duration_ms = (time.perf_counter() - started) * 1000
    if status_code is not None and 200 <= status_code < 300:
        _finish(settings, row_id, status_code=status_code, duration_ms=duration_ms)
        return None
    if status_code is not None:
        error = f"HTTP {status_code}" + (" (redirects are not followed)" if 300 <= status_code < 400 else "")
    if status_code == 410 or attempt >= settings.webhook_max_attempts:
        final = "the receiver says the resource is gone" if status_code == 410 else "no attempt left"
        _finish(settings, row_id, status_code=status_code, duration_ms=duration_ms, error=f"{error}; {final}")
        return None
    delay = retry_delay(settings, attempt, retry_after)
    _finish(settings, row_id, status_code=status_code, duration_ms=duration_ms, error=error,
            next_attempt_at=attempted_at + timedelta(seconds=delay))  # fmt: skip
    return delay


def _finish(settings: Settings, row_id: int, **values: Any) -> None:
    with session_scope(settings) as session:
        store.finish(session, row_id, **{"status_code": None, "error": None, "duration_ms": None,
                                         "next_attempt_at": None, **values})  # fmt: skip


def register_webhook_tasks(app: Celery, settings: Settings) -> None:
    """Define ``spine.deliver_webhook`` on the worker's Celery app, signing with per-key secrets."""
    @app.task(name=DELIVER, ignore_result=True, acks_late=True, autoretry_for=TRANSIENT, retry_backoff=True,
              retry_backoff_max=60, max_retries=10)  # fmt: skip
    def deliver_webhook(job_id: str, status: str, attempt: int) -> None:
        try:
            parsed = uuid.UUID(job_id)
        except ValueError:
            log.error("dropping a webhook message with a malformed job id %r", job_id)
            return
        delay = deliver_once(settings, parsed, status, attempt)
        if delay is not None:
            publish_attempt(settings, parsed, status, attempt + 1, countdown=delay, celery=app)
