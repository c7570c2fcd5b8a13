"""The worker's tasks: run one job through the engine, and reconcile stranded jobs.

run_job(job_id): queued → running with a conditional UPDATE (a second delivery, or a cancelled
job, does nothing), runs ``spine_engine.register(payload)`` and stores the result (with its
measures) or a problem, only if the run still owns the job. Faults of the database or broker are
retried with backoff; engine errors fail the job at once.
"""

from __future__ import annotations

import logging
import time
import uuid
from datetime import timedelta
from typing import Any

from celery import Celery, Task
from celery.exceptions import SoftTimeLimitExceeded
from kombu.exceptions import OperationalError as BrokerError
from sqlalchemy.exc import InterfaceError, OperationalError
from sqlalchemy.orm import Session
from tenacity import retry, retry_if_exception_type, stop_after_attempt, wait_exponential

import spine_engine
from services.db import jobs as jobs_repo
from services.db.engine import session_scope, worker_session
from services.db.models import JobStatus
from services.jobqueue import RECONCILE, RUN_JOB, publish, queue_depth
from services.problems import problem, validation_problem
from services.settings import Settings
from services.webhooks import delivery as webhooks
from spine_engine.errors import FitFailed, InvalidInput

log = logging.getLogger(__name__)

TRANSIENT = (OperationalError, InterfaceError, BrokerError, ConnectionError, TimeoutError)
"""Faults of an unreachable database or broker: the task is retried with backoff."""

_store_retry = retry(
    retry=retry_if_exception_type(TRANSIENT),
    wait=wait_exponential(multiplier=0.5, max=10),
    stop=stop_after_attempt(6),
    reraise=True,
)


def _engine_version() -> str:
    return str(getattr(spine_engine, "__version__", "unknown"))


def run_engine(payload: dict[str, Any], instance: str) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """Run the registration; return (result, None) or (None, problem)."""
    try:
        from spine_engine import register  # the engine's public entry point

        return register(payload), None
    except InvalidInput as exc:
        return None, validation_problem(exc.errors, instance=instance)
    except FitFailed as exc:
        return None, problem("fit-failed", exc.reason, instance=instance, iterations=exc.iterations)
    except SoftTimeLimitExceeded:
        return None, problem("fit-timeout", "the fit did not finish within its time limit", instance=instance)
    except Exception as exc:
        log.exception("engine error on %s", instance)
        return None, problem("engine-error", f"{type(exc).__name__}: {exc}", instance=instance)


def execute_job(settings: Settings, job_id: uuid.UUID) -> str:
    """Claim, run and finish one job; return what happened (for logs and tests)."""
    with worker_session(settings, durable=False) as session:
        claim = jobs_repo.claim_job(session, job_id, _engine_version())
    if claim is None:
        return "skipped"
    instance = f"/v1/jobs/{job_id}"
    result, error = run_engine(claim.payload, instance)
    engine_version = (result or {}).get("engine", {}).get("version") if result else None

    @_store_retry
    def store() -> bool:
        with worker_session(settings) as session:
            return jobs_repo.finish_job(session, claim, result=result, error=error, engine_version=engine_version)

    stored = store()
    if not stored:
        return "superseded"
    status = "succeeded" if error is None else "failed"
    url = claim.payload.get("callback_url")
    if url:  # only then: a message on the webhook queue
        webhooks.job_ended(settings, job_id, status, url=url)
    return status


def _messages_cover_queued_jobs(session: Session, app: Celery, settings: Settings) -> bool:
    """True when the broker holds at least one message per queued job.

    Then no queued job lost its message, however long the backlog, and re-publishing the stale
    ones would only add duplicates for the workers to skip.
    """
    try:
        depth = queue_depth(app, settings.queue_name)
    except Exception:
        return False
    return depth > 0 and depth >= jobs_repo.count_by_status(session)[JobStatus.queued.value]


def reconcile_once(settings: Settings, app: Celery) -> jobs_repo.Reconciliation:
    """One pass of the reconciler: re-enqueue stranded jobs, fail those out of attempts."""
    lost = problem(
        "worker-lost",
        f"the job was still running {settings.fit_time_limit_s:g} s after it started, "
        f"{settings.max_attempts} times; its worker stopped or lost it",
    )
    queued_timeout = timedelta(seconds=settings.queued_timeout_s)
    with session_scope(settings) as session:
        if _messages_cover_queued_jobs(session, app, settings):
            queued_timeout = timedelta(days=36500)  # nothing lost: leave a long backlog alone
        outcome = jobs_repo.reconcile(
            session,
            queued_timeout=queued_timeout,
            running_timeout=timedelta(seconds=settings.fit_time_limit_s + settings.running_grace_s),
            max_attempts=settings.max_attempts,
            lost_problem=lost,
        )
    if outcome.requeue:
        with session_scope(settings) as session:
            publish(session, app, outcome.requeue)
    if outcome.failed:
        with session_scope(settings) as session:
            webhooks.jobs_ended(session, settings, outcome.failed, app)
    if outcome.requeue or outcome.failed:
        log.info("reconciler: re-enqueued %d jobs, failed %d", len(outcome.requeue), len(outcome.failed))
    webhooks.sweep(settings, app)
    return outcome


def register_tasks(app: Celery, settings: Settings) -> None:
    """Define the tasks on ``app`` (the time limits come from ``settings``)."""

    @app.task(
        name=RUN_JOB,
        bind=True,
        acks_late=True,
        ignore_result=True,
        soft_time_limit=settings.fit_time_limit_s,
        time_limit=settings.fit_time_limit_s + 15,
        autoretry_for=TRANSIENT,
        retry_backoff=True,
        retry_backoff_max=60,
        retry_jitter=True,
        max_retries=10,
    )
    def run_job(self: Task, job_id: str) -> None:
        started = time.perf_counter()
        try:
            parsed = uuid.UUID(job_id)
        except ValueError:
            log.error("dropping a message with a malformed job id %r", job_id)
            return
        outcome = execute_job(settings, parsed)
        log.info("job %s %s in %.1f ms", job_id, outcome, (time.perf_counter() - started) * 1000)

    @app.task(name=RECONCILE, ignore_result=True, autoretry_for=TRANSIENT, max_retries=0)
    def reconcile() -> None:
        reconcile_once(settings, app)
