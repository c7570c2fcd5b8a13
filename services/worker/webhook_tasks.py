"""The worker's side of webhooks: the ``spine.deliver_webhook`` task and the reconciler's sweep.

The task POSTs the job (``services.webhooks.delivery``), records the attempt in
``webhook_deliveries`` and, unless the receiver answered 2xx (or 410 Gone), publishes the next attempt
with exponential backoff (``Retry-After`` honoured), up to ``SPINE_WEBHOOK_MAX_ATTEMPTS``. The first
attempt is published by ``services.db.deliveries.job_ended`` as the job ends, after its outbox row
(attempt 0) is written; so is the first attempt of the event that ends a run of STOW-RS attempts
(``job.dicom_stored``, ``job.dicom_store_failed``: ``services.worker.dicom_tasks``), whose message also
carries the run (the number of its first STOW-RS attempt, part of its message id).

Time limits: the task's soft limit is its attempt's deadline (``SPINE_WEBHOOK_TIMEOUT_S``, which
bounds the claim and the request) plus ``SPINE_WEBHOOK_TASK_MARGIN_S`` (writing the outcome, retried
in place, and publishing the next attempt), its hard limit ``HARD_LIMIT_GRACE_S`` later. A task cut
off leaves its attempt's row in flight (or only the outbox row), which the sweep publishes again.

Every due time (``next_attempt_at``) is written and compared on the database's clock
(``services.db.clock``): the worker that writes it and the reconciler that sweeps may run on hosts
whose clocks differ by more than ``SPINE_WEBHOOK_SWEEP_AFTER_S``. So is an attempt's ``attempted_at``
(the claim's), which is only shown: ordered with the job's times whatever this worker's clock.

A retry's message carries a countdown, which Celery turns into an absolute ETA on the publishing
worker's clock and the consuming worker compares with its own: a consumer whose clock is ahead of the
publisher's receives the retry early, by the difference. So a message with an ETA is made only once its
attempt is due on the database's clock (``retry_wait_s``); one that came early is published again with
the time left as its countdown, counted by the worker that found it early. A consumer whose clock is
behind holds the message late by the difference; beyond ``SPINE_WEBHOOK_SWEEP_AFTER_S`` the sweep
publishes the attempt again, and the claim of its row lets only one of the two make the request.
"""

from __future__ import annotations

import logging
import time
import uuid
from datetime import datetime, timedelta
from typing import Any

from celery import Celery, Task

from services.core.config import Settings
from services.core.jobqueue import DELIVER_WEBHOOK, HARD_LIMIT_GRACE_S, publish_webhook
from services.core.retry import TRANSIENT, write_retry
from services.core.webhook_policy import WebhooksDisabled, allow_list, destination_problem
from services.db import deliveries, dicom_stores
from services.db.clock import db_now, db_now_plus_s
from services.db.engine import session_scope
from services.db.models import WebhookDelivery
from services.webhooks.delivery import post, retry_delay, webhook_body
from services.webhooks.signing import secret_for, signed_headers

log = logging.getLogger(__name__)


def sweep(settings: Settings, celery: Celery, window: timedelta = timedelta(days=1)) -> int:
    """Publish again every attempt that was due ``SPINE_WEBHOOK_SWEEP_AFTER_S`` ago and never came.

    Such an attempt's message was not published (the outbox row, attempt 0, says "not published":
    the broker was down when the job ended) or was lost with a broker (the outbox row of a message
    whose attempt 1 never came, or a retry that never came), or its worker stopped during the request
    (the row of an attempt in flight is due at the attempt's deadline, ``SPINE_WEBHOOK_TIMEOUT_S``
    after it started, which ``services.webhooks.delivery.post`` holds: an attempt still within it is
    never swept). Each one found is published and its row's due time moved
    ``SPINE_WEBHOOK_SWEEP_AFTER_S`` ahead, so it is published again only if this one is lost too (the
    claim of the attempt sets it back to when the attempt came: ``deliveries.settle_earlier``). A row
    of the last attempt (``SPINE_WEBHOOK_MAX_ATTEMPTS``) publishes nothing: its due time is cleared.
    Looks back ``window``. Every time is the database's clock's (``services.db.clock``), as the rows'
    due times are written. Returns how many were published.
    """
    after_s = settings.webhook_sweep_after_s
    with session_scope(settings) as session:
        rows = deliveries.overdue(
            session, due_before=db_now_plus_s(-after_s), due_after=db_now_plus_s(-window.total_seconds())
        )
        published = 0
        for row in rows:
            lost = _in_flight(row)
            if row.attempt >= settings.webhook_max_attempts:
                final = {"error": f"{_LOST}; no attempt left"} if lost else {}
                deliveries.finish(session, row.id, next_attempt_at=None, **final)
                continue
            status = row.event.removeprefix("job.")
            run = None
            if status in deliveries.RUN_EVENTS:  # the run is in the message id: found among the job's runs
                run = dicom_stores.run_of_message(session, row.job_id, status, row.message_id)
                if run is None:
                    log.error("webhook sweep: message %s (%s) of job %s matches none of its STOW-RS runs: dropped",
                              row.message_id, row.event, row.job_id)  # fmt: skip
                    deliveries.finish(session, row.id, next_attempt_at=None)
                    continue
            try:
                publish_webhook(settings, row.job_id, status, row.attempt + 1, run=run, celery=celery)
            except Exception as exc:
                log.warning("webhook sweep: could not publish for job %s: %s", row.job_id, exc)
                break
            if lost:
                deliveries.finish(session, row.id, error=_LOST)
            elif row.attempt == deliveries.OUTBOX_ATTEMPT and row.error is None:
                since = "the job's end" if run is None else "the end of its STOW-RS run"
                deliveries.note(session, row.id, _NEVER_CAME.format(after=settings.webhook_sweep_after_s, since=since))
            deliveries.postpone(session, row.id, db_now_plus_s(after_s))
            published += 1
    if published:
        log.info("webhook sweep: published %d overdue webhook attempts", published)
    return published


_LOST = "no outcome recorded: the worker stopped during the attempt"
_NEVER_CAME = ("no attempt within {after:g} s of {since} (SPINE_WEBHOOK_SWEEP_AFTER_S): its message was lost "
               "or is still waiting; the reconciler published it again")  # fmt: skip


def _in_flight(row: WebhookDelivery) -> bool:
    """A claimed attempt whose outcome was never written (its worker stopped mid-request)."""
    return bool(row.attempt > 0 and row.status_code is None and row.error is None and row.duration_ms is None)


def deliver_once(
    settings: Settings, job_id: uuid.UUID, status: str, attempt: int, run: int | None = None
) -> float | None:
    """Make attempt ``attempt`` of the job's webhook (of its end, ``status`` its final status; or, with
    ``run``, of event ``job.<status>`` of that run of STOW-RS attempts); return the delay before the next
    one, or None.

    An attempt beyond ``SPINE_WEBHOOK_MAX_ATTEMPTS`` (or below 1) is dropped before anything is
    recorded or sent. The next attempt is due ``delay`` after this one ended (its row's
    ``next_attempt_at``, on the database's clock), when the caller publishes it with that countdown.

    The attempt's row is claimed before the request (``deliveries.claim``): a second delivery of the
    same attempt finds it and does nothing. Until the outcome is written, the row's
    ``next_attempt_at`` is the request's deadline (``SPINE_WEBHOOK_TIMEOUT_S`` after the claim, on the
    database's clock: never before the deadline ``post`` holds, counted on this process's monotonic clock
    from before the claim), so a worker that dies mid-request leaves a row the reconciler's ``sweep``
    picks up. The row's ``attempted_at`` is the database's clock of the claim (``db_now()`` in the insert,
    the clock of its deadline), returned by it.
    """
    if not 1 <= attempt <= settings.webhook_max_attempts:
        log.warning("dropping attempt %d of the webhook of job %s (%s): SPINE_WEBHOOK_MAX_ATTEMPTS is %d",
                    attempt, job_id, status, settings.webhook_max_attempts)  # fmt: skip
        return None
    mid = deliveries.message_id(job_id, status, run)
    started = time.monotonic()  # the request's deadline is counted from here: a duration on this process's clock
    with session_scope(settings) as session:
        job = deliveries.delivery_job(session, job_id)
        if job is None or deliveries.delivered(session, mid):
            return None
        url = job.callback_url
        claimed = deliveries.claim(
            session, job_id=job_id, message_id=mid, event=f"job.{status}", attempt=attempt, url=url,
            attempted_at=db_now(), next_attempt_at=db_now_plus_s(settings.webhook_timeout_s),
        )  # fmt: skip
        if claimed is None:  # published twice (a repeated cancel, a sweep, a redelivery)
            return None
        row_id = claimed.id
        deliveries.settle_earlier(session, mid, attempt, claimed.attempted_at)
        body = _body(job, status, run)
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
    spent = time.monotonic() - started  # the deadline claimed above holds for the request too
    # the signature's timestamp stays this process's clock: never stored, the receiver checks it against its own
    sent = post(url, body, signed_headers(key, mid, int(time.time()), body), settings.webhook_timeout_s, spent_s=spent)
    if sent.accepted:
        _finish(settings, row_id, status_code=sent.status_code, duration_ms=sent.duration_ms)
        return None
    if sent.status_code == 410 or attempt >= settings.webhook_max_attempts:
        final = "the receiver says the resource is gone" if sent.status_code == 410 else "no attempt left"
        _finish(settings, row_id, status_code=sent.status_code, duration_ms=sent.duration_ms,
                error=f"{sent.error}; {final}")  # fmt: skip
        return None
    delay = retry_delay(settings, attempt, sent.retry_after, sent.date)  # counted from the attempt's end
    _finish(settings, row_id, status_code=sent.status_code, duration_ms=sent.duration_ms, error=sent.error,
            next_attempt_at=db_now_plus_s(delay))  # fmt: skip
    return delay


def _body(job: deliveries.DeliveryJob, status: str, run: int | None) -> bytes:
    """The body of event ``job.<status>``: for the job's end (``run`` None), the job as ``GET /v1/jobs``
    lists it, timed at the job's end; for the end of run ``run`` of STOW-RS attempts, the same with the
    job's ``dicom_stores`` as ``GET /v1/jobs/{id}`` shows them up to the attempt that ended the run
    (``dicom_stores.run_stores``: a later run does not change the message), timed at that attempt's
    ``attempted_at``."""
    if run is None:
        return webhook_body(job.data, status, job.finished_at)
    stores = dicom_stores.run_stores(job.dicom_stores, run)
    at = datetime.fromisoformat(stores[-1]["attempted_at"]) if stores else job.finished_at
    return webhook_body({**job.data, "dicom_stores": stores}, status, at)


def retry_wait_s(settings: Settings, job_id: uuid.UUID, status: str, attempt: int, run: int | None = None) -> float:
    """Seconds until attempt ``attempt`` of the job's webhook is due on the database's clock (the attempt
    before it wrote that time: ``deliver_once``); 0 when it is due."""
    with session_scope(settings) as session:
        return deliveries.wait_s(session, deliveries.message_id(job_id, status, run), attempt)


@write_retry
def _finish(settings: Settings, row_id: int, **values: Any) -> None:
    """Write the attempt's outcome on its row, retried in place on a transient fault (``write_retry``):
    the request was made, and a row left in flight would be swept and the receiver called again."""
    with session_scope(settings) as session:
        deliveries.finish(session, row_id, **{"status_code": None, "error": None, "duration_ms": None,
                                              "next_attempt_at": None, **values})  # fmt: skip


def register_webhook_tasks(app: Celery, settings: Settings) -> None:
    """Define ``spine.deliver_webhook`` on the worker's Celery app, signing with per-key secrets."""

    soft_limit = settings.webhook_timeout_s + settings.webhook_task_margin_s

    @app.task(name=DELIVER_WEBHOOK, bind=True, shared=False, ignore_result=True, acks_late=True,
              autoretry_for=TRANSIENT, retry_backoff=True, retry_backoff_max=60, max_retries=10,
              soft_time_limit=soft_limit, time_limit=soft_limit + HARD_LIMIT_GRACE_S)  # fmt: skip
    def deliver_webhook(task: Task, job_id: str, status: str, attempt: int, run: int | None = None) -> None:
        try:
            parsed = uuid.UUID(job_id)
        except ValueError:
            log.error("dropping a webhook message with a malformed job id %r", job_id)
            return
        if (run is None) == (status in deliveries.RUN_EVENTS):
            log.error("dropping a webhook message of job %s: event job.%s with run %r", parsed, status, run)
            return
        if task.request.eta is not None:  # a retry: its ETA is on its publisher's clock, compared with ours
            wait = retry_wait_s(settings, parsed, status, attempt, run)
            if wait > 0:
                log.info("webhook of job %s attempt %d came %.3f s before it is due on the database's clock "
                         "(this worker's clock and its publisher's differ): published again for then",
                         parsed, attempt, wait)  # fmt: skip
                publish_webhook(settings, parsed, status, attempt, run=run, countdown=wait, celery=app)
                return
        delay = deliver_once(settings, parsed, status, attempt, run)
        if delay is not None:
            publish_webhook(settings, parsed, status, attempt + 1, run=run, countdown=delay, celery=app)
