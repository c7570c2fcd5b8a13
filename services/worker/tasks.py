"""The worker's tasks: run one job through the engine, and reconcile stranded jobs.

run_job(job_id): queued → running with a conditional UPDATE (a second delivery, or a cancelled
job, does nothing; a message that came before its job is due, on the database's clock, is published
again for the time left), runs ``spine_engine.register(payload)`` and stores the result (with its
measures) or a problem, only if the run still owns the job. Faults of the database or broker are
retried with backoff; engine errors fail the job at once.

Leases: a running job's lease is renewed while the fit runs, so that a job whose worker died
(kill -9, a lost machine) is found by the reconciler within ``SPINE_LEASE_S`` plus one reconcile
interval, not after the fit time limit. One thread per worker process (``LeaseKeeper``) renews,
every third of the lease, the leases of the runs that have been going for more than a third of it:
a 5 ms fit ends long before and costs nothing beyond the lease set by its claim. A run whose job
was cancelled or taken back meanwhile is not renewed (the update is fenced by attempt) and will
store nothing.
"""

from __future__ import annotations

import enum
import logging
import os
import threading
import time
import uuid
from datetime import timedelta
from typing import Any

from celery import Celery, Task
from celery.exceptions import SoftTimeLimitExceeded
from sqlalchemy.exc import StatementError
from sqlalchemy.orm import Session

import spine_engine
from services.core.config import DicomwebConfig, Settings
from services.core.jobqueue import (
    HARD_LIMIT_GRACE_S,
    RECONCILE,
    RUN_JOB,
    broker_run_id,
    claim_broker_restart,
    queue_depth,
)
from services.core.problems import problem, validation_problem
from services.core.retry import TRANSIENT, refused_by_database, storage_refusal, write_retry
from services.db import deliveries, runs, stats
from services.db.engine import session_scope, worker_connection
from services.db.job_forms import apply_reads, engine_payload
from services.dicom.dicomweb import Pacs
from services.dicom.errors import PacsUnavailable
from services.dicom.reference import resolve_by_reference, views_to_fetch
from services.worker import dicom_tasks, webhook_tasks
from spine_client.dicom.errors import DicomError, PatientConflict
from spine_engine.errors import FitFailed, InvalidInput
from spine_engine.models import RegistrationResult
from spine_engine.reconstruction import register_model
from spine_engine.validation import validate_payload

log = logging.getLogger(__name__)


def _engine_version() -> str:
    return str(getattr(spine_engine, "__version__", "unknown"))


class RunSpacing:
    """Whether a periodic run goes ahead: not when this process started one less than ``min_gap_s`` ago,
    on its own monotonic clock. The reconciler's runs that queued while they could not start (the
    database down, the pool busy) then end at once instead of all running and holding every pool
    process. No other clock is compared: Celery's ``expires`` is an instant on beat's clock that the
    consuming worker compares with its own, so a worker whose clock ran ahead of beat's host by more
    than the interval would drop every run."""

    def __init__(self, min_gap_s: float):
        self.min_gap_s = min_gap_s
        self.last: float | None = None

    def due(self, now: float | None = None) -> bool:
        """Whether a run starting at ``now`` (``time.monotonic()``, s) goes ahead; if so it is the last."""
        now = time.monotonic() if now is None else now
        if self.last is not None and now - self.last < self.min_gap_s:
            return False
        self.last = now
        return True


def run_engine(
    payload: dict[str, Any], instance: str, job_id: uuid.UUID
) -> tuple[RegistrationResult | None, dict[str, Any] | None]:
    """Run the registration; return (result, None) or (None, problem).

    An unexpected exception of the engine (a bug, not the payload's fault) is logged here with its
    traceback, on the worker's side only: the client reads the problem, whose detail says what happened
    and names the job for the operator, never the exception's type or message (a path, an internal
    name, a number of another computation)."""
    try:
        return register_model(validate_payload(payload)), None
    except InvalidInput as exc:
        return None, validation_problem(exc.errors, instance=instance)
    except FitFailed as exc:
        return None, problem("fit-failed", exc.reason, instance=instance, iterations=exc.iterations)
    except SoftTimeLimitExceeded:
        return None, problem("fit-timeout", "the fit did not finish within its time limit", instance=instance)
    except Exception:
        log.exception("job %s: the engine raised an unexpected error; the job fails (engine-error)", job_id)
        detail = (
            f"the engine stopped on an unexpected error while fitting job {job_id}, an error of the service, "
            "not of the payload; the service's operator finds it in the worker's log under this job id"
        )
        return None, problem("engine-error", detail, instance=instance)


class LeaseKeeper:
    """Renews the leases of this process's running claims (a daemon thread, started on first use)."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self.lease = timedelta(seconds=settings.lease_s)
        self.period_s = settings.lease_s / 3
        self._lock = threading.Lock()
        self._claims: dict[uuid.UUID, tuple[runs.Claim, float]] = {}
        self._thread: threading.Thread | None = None
        self._pid = 0

    def hold(self, claim: runs.Claim) -> None:
        """Keep ``claim``'s lease alive until ``release``."""
        with self._lock:
            self._claims[claim.job_id] = (claim, time.monotonic())
            if self._thread is None or self._pid != os.getpid():  # first use, or a forked child
                self._pid = os.getpid()
                self._thread = threading.Thread(target=self._run, name="spine-lease-keeper", daemon=True)
                self._thread.start()

    def release(self, claim: runs.Claim) -> None:
        with self._lock:
            self._claims.pop(claim.job_id, None)

    def due(self, now: float) -> list[runs.Claim]:
        """Claims held for more than a third of the lease (their lease needs renewing)."""
        with self._lock:
            return [c for c, since in self._claims.values() if now - since >= self.period_s]

    def renew_once(self) -> int:
        due = self.due(time.monotonic())
        if not due:
            return 0
        with worker_connection(self.settings) as session:
            kept = runs.renew_leases(session, due, self.lease)
        lost = {c.job_id for c in due} - {c.job_id for c in kept}
        for job_id in lost:
            log.warning("job %s: lease not renewed (cancelled or taken back); its outcome will not be stored", job_id)
        return len(kept)

    def _run(self) -> None:
        while True:
            time.sleep(self.period_s)
            try:
                self.renew_once()
            except Exception as exc:  # the database is away: the next period tries again
                log.warning("could not renew job leases: %s", exc)


_KEEPERS: dict[str, LeaseKeeper] = {}


def lease_keeper(settings: Settings) -> LeaseKeeper:
    """The process's lease keeper for the database of ``settings``."""
    keeper = _KEEPERS.get(settings.sqlalchemy_url)
    if keeper is None:
        keeper = _KEEPERS[settings.sqlalchemy_url] = LeaseKeeper(settings)
    return keeper


class RunLater(Exception):
    """The run cannot proceed now (the PACS is unavailable): the job went back to queued, due again
    ``countdown`` (s) later on the database's clock (``runs.release_claim``)."""

    def __init__(self, countdown: float):
        super().__init__(countdown)
        self.countdown = countdown


class NotDue(RunLater):
    """The message came before its job is due (``countdown`` s left on the database's clock): a released
    run's message whose ETA, on its publisher's clock, the consuming worker read on its own. Nothing was
    claimed, no attempt spent; the message is to be published again for the time left."""


def resolve_dicom(settings: Settings, claim: runs.Claim, instance: str) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """The payload to run: with SPINE_DICOMWEB_URL, the headers of the images the study names by UID
    fill what the payload lacks (``services.dicom.reference``), recorded on the job. Returns
    (payload, None) or (payload, problem). A PACS that is unavailable hands the job back to the queue
    (``RunLater``) until its attempts (SPINE_MAX_ATTEMPTS) are spent, then fails it
    (``dicomweb-unavailable``); a missing instance or an unusable header fails it at once, and so do
    films that are not of the payload's patient and study, or of one patient (``dicom-patient-conflict``),
    however the job was read."""
    config = settings.dicomweb
    payload = apply_reads(claim.payload, claim.dicom)  # the client's reads of its files, or an earlier run's
    if config is None or (claim.dicom is not None and not views_to_fetch(payload)):
        return engine_payload(payload), None
    if not views_to_fetch(payload):  # read only for the SR's reference: a PACS problem does not fail the job
        try:
            return engine_payload(_reference_reads(settings, config, claim, payload)), None
        except PatientConflict as exc:
            return payload, problem(exc.problem, str(exc), instance=instance, **exc.problem_fields)
    try:
        with Pacs(config) as pacs:
            resolved, provenance = resolve_by_reference(payload, pacs)
    except PacsUnavailable as exc:
        if claim.attempt < settings.max_attempts:
            delay = dicom_tasks.retry_delay_s(settings, claim.attempt)
            with worker_connection(settings) as session:
                runs.release_claim(session, claim, delay)  # due again delay s from now, the database's clock
            raise RunLater(delay) from None
        detail = f"{exc}; {claim.attempt} attempts (SPINE_MAX_ATTEMPTS)"
        return payload, problem("dicomweb-unavailable", detail, instance=instance, attempts=claim.attempt)
    except DicomError as exc:
        return payload, problem(exc.problem, str(exc), instance=instance, **exc.problem_fields)
    if provenance is not None:
        with worker_connection(settings) as session:
            runs.record_dicom(session, claim, provenance.model_dump(mode="json"), resolved.get("study") or {})
    return engine_payload(resolved), None


def _reference_reads(
    settings: Settings, config: DicomwebConfig, claim: runs.Claim, payload: dict[str, Any]
) -> dict[str, Any]:
    """The payload with the headers of the images its study names, read although it gives all it needs
    (``resolve_by_reference(all_named=True)``) and recorded on the job; unchanged when the PACS cannot
    give them (logged). Raises ``PatientConflict`` when the films are not of the payload's patient and
    study, or of one patient: the job needs nothing from them, but its results would go into the film's
    study under another patient."""
    if not views_to_fetch(payload, all_named=True):
        return payload
    try:
        with Pacs(config) as pacs:
            resolved, provenance = resolve_by_reference(payload, pacs, all_named=True)
    except PatientConflict:
        raise
    except DicomError as exc:
        log.warning("job %s: the images its study names were not read (%s); it runs without them", claim.job_id, exc)
        return payload
    if provenance is not None:
        with worker_connection(settings) as session:
            runs.record_dicom(session, claim, provenance.model_dump(mode="json"), resolved.get("study") or {})
    return resolved


@write_retry
def _save_outcome(
    settings: Settings,
    claim: runs.Claim,
    result: RegistrationResult | None,
    error: dict[str, Any] | None,
    engine_version: str | None,
) -> bool:
    """The run's outcome written to the jobs table (``runs.finish_job``), retried in place on a transient fault."""
    with worker_connection(settings) as connection:
        return runs.finish_job(connection, claim, result=result, error=error, engine_version=engine_version)


def _store_outcome(
    settings: Settings,
    claim: runs.Claim,
    result: RegistrationResult | None,
    error: dict[str, Any] | None,
    instance: str,
) -> tuple[bool, dict[str, Any] | None]:
    """Store the run's outcome; return (stored, the problem stored). A database that refuses it for
    good (a constraint, a trigger, a value it cannot hold: ``refused_by_database``) fails the job at
    once with ``result-not-stored`` instead: no traceback, one log line, and no fit run again."""
    engine_version = result.engine.version if result is not None else None
    try:
        return _save_outcome(settings, claim, result, error, engine_version), error
    except StatementError as exc:
        if not refused_by_database(exc):
            raise
        reason = storage_refusal(exc)
    log.error("job %s: the database refused to store its outcome (%s); the job fails (result-not-stored)",
              claim.job_id, reason)  # fmt: skip
    refused = result_not_stored(f"the database refused to store the job's outcome ({reason}); the fit is not "
                                "run again: the service's operator must look at the database", instance)  # fmt: skip
    try:
        return _save_outcome(settings, claim, None, refused, engine_version), refused
    except StatementError as exc:
        if not refused_by_database(exc):
            raise
        log.error("job %s: the database refused its failure too (%s); it stays running until its lease expires",
                  claim.job_id, storage_refusal(exc))  # fmt: skip
        return False, refused


def result_not_stored(detail: str, instance: str) -> dict[str, Any]:
    """The ``result-not-stored`` problem (status 500) of a job whose outcome the database refused."""
    return problem("result-not-stored", detail, instance=instance)


def _claim_when_due(settings: Settings, job_id: uuid.UUID) -> runs.Claim | None:
    """The job's claim (``runs.claim_job``: queued and due on the database's clock), or None when it is
    not queued; raises ``NotDue`` with the seconds left when it is queued but not due. The common case
    is one statement; the due time is read only when the claim took nothing."""
    lease = timedelta(seconds=settings.lease_s)
    with worker_connection(settings, durable=False) as session:
        for _ in range(2):  # a second claim only when the job became due between the two statements
            claim = runs.claim_job(session, job_id, _engine_version(), lease)
            if claim is not None:
                return claim
            wait = runs.due_in_s(session, job_id)
            if wait is None:
                return None
            if wait > 0:
                raise NotDue(wait)
    return None


def execute_job(settings: Settings, job_id: uuid.UUID) -> str:
    """Claim (with a lease), run and finish one job; return what happened (for logs and tests).
    Raises ``RunLater`` when the job went back to the queue (the PACS is unavailable), ``NotDue`` when
    the job is not due yet on the database's clock (a released run's message that came early): then
    nothing is claimed and no attempt spent.

    The lease is held until the outcome is stored: its write may be retried for ~30 s
    (``write_retry``), longer than a lease, and a job taken back meanwhile would be fitted again."""
    claim = _claim_when_due(settings, job_id)
    if claim is None:
        return "skipped"
    instance = f"/v1/jobs/{job_id}"
    keeper = lease_keeper(settings)
    keeper.hold(claim)
    try:
        payload, error = resolve_dicom(settings, claim, instance)
        result = None
        if error is None:
            result, error = run_engine(payload, instance, job_id)
        saved, error = _store_outcome(settings, claim, result, error, instance)
    finally:
        keeper.release(claim)
    if not saved:
        return "superseded"
    status = "succeeded" if error is None else "failed"
    url = claim.callback_url
    if url:  # only then: a message on the webhook queue (its outbox row was written with the outcome)
        deliveries.job_ended(settings, job_id, status, url=url, recorded=True)
    if status == "succeeded" and settings.stores_dicom_results:
        dicom_tasks.job_succeeded(settings, job_id)  # STOW-RS of the SR and figure
    return status


_LAST_RUN_ID: dict[str, str] = {}
"""The broker's run id this process saw last, by broker URL."""


class BrokerRestart(enum.Enum):
    """What a reconciler's look at the broker's run id found."""

    NONE = "none"
    """The run id this process saw last, or its first look, or a broker without a run id."""
    OURS = "ours"
    """A new run id, and this process's claim of it (``claim_broker_restart``) succeeded: it publishes
    every queued job again."""
    TAKEN = "taken"
    """A new run id that another reconciler claimed: it publishes every queued job again, this pass of
    this process publishes none (counted as missing while the other publishes, they would be doubled)."""


def broker_restart(app: Celery, queue: str, seen: dict[str, str] = _LAST_RUN_ID) -> BrokerRestart:
    """Whether the broker restarted since this process last looked (its run id changed: the messages
    it held are gone), and whether this process is the one to publish ``queue``'s jobs again for it:
    of the reconcilers that looked before the restart (every pool process of every worker), the one
    whose ``claim_broker_restart`` succeeds, or any of them when the claim fails (a broker whose ACL
    refuses the key: duplicates are harmless, lost messages are not). ``seen`` is the process's memory
    of run ids, by broker URL; a look that fails on the broker leaves it, so that the next pass looks
    again."""
    try:
        run_id = broker_run_id(app)
    except Exception:
        return BrokerRestart.NONE
    if run_id is None:
        return BrokerRestart.NONE
    url = str(app.conf.broker_url)
    previous = seen.get(url)
    if previous is None or previous == run_id:
        seen[url] = run_id
        return BrokerRestart.NONE
    try:
        claimed = claim_broker_restart(app, queue, run_id)
    except Exception as exc:  # the run id was read: a broker that refuses the SET (an ACL) more likely than one gone
        log.warning("reconciler: could not claim the broker's restart (%s); publishing every queued job anyway", exc)
        claimed = True  # a duplicate message is harmless (the claim of a job is conditional), a lost one is not
    seen[url] = run_id
    return BrokerRestart.OURS if claimed else BrokerRestart.TAKEN


def missing_messages(session: Session, app: Celery, settings: Settings) -> int | None:
    """How many queued jobs the broker holds no message for (queued jobs − messages waiting), at
    least 0; None when the queue cannot be read. Messages prefetched by busy workers count as
    missing too: their jobs are the oldest, and re-publishing them adds a duplicate that is
    skipped (the claim is conditional). So does the message of a run handed back until later (the
    PACS unavailable), held by a worker until its ETA: its job's ``enqueued_at`` is when it is due
    (``runs.release_claim``), so it is published again only ``SPINE_QUEUED_TIMEOUT_S`` after that
    (after a broker restart, which loses it, ``reconcile_once`` publishes it at once for its due time)."""
    try:
        depth = queue_depth(app, settings.queue_name)
    except Exception:
        return None
    return max(0, stats.count_all_queued(session) - depth)


def reconcile_once(settings: Settings, app: Celery) -> runs.Reconciliation:
    """One pass of the reconciler: take back running jobs whose lease expired (or fail those out of
    attempts), and publish again the queued jobs whose message is missing: all of them when the
    broker restarted, else as many of the oldest as the broker lacks messages, once they waited
    ``SPINE_QUEUED_TIMEOUT_S``; jobs marked unpublished at once. When the broker restarted, the jobs not
    due yet (runs handed back until later) are published too, each with a countdown to its due time on
    the database's clock (``runs.publish_later``): the messages held until then are gone with it."""
    lost = problem(
        "worker-lost",
        f"the job's worker stopped renewing its lease (SPINE_LEASE_S {settings.lease_s:g} s), "
        f"{settings.max_attempts} times; its worker stopped or lost it",
    )
    queued_timeout = timedelta(seconds=settings.queued_timeout_s)
    restart = broker_restart(app, settings.queue_name)
    restarted = restart is BrokerRestart.OURS
    with session_scope(settings) as session:
        missing: int | None
        if restarted:  # every message is gone: publish every queued job now
            log.warning("reconciler: the broker restarted; publishing every queued job again")
            missing, queued_timeout = None, timedelta(0)
        elif restart is BrokerRestart.TAKEN:
            log.info("reconciler: the broker restarted; another reconciler publishes the queued jobs again")
            missing = 0
        else:
            missing = missing_messages(session, app, settings)
        outcome = runs.reconcile(
            session,
            queued_timeout=queued_timeout,
            max_attempts=settings.max_attempts,
            lost_problem=lost,
            republish_queued=missing,
            not_due=restarted,
        )
    if outcome.requeue:
        with session_scope(settings) as session:
            runs.publish(session, app, outcome.requeue)
    if outcome.later:
        runs.publish_later(app, outcome.later)
        log.info("reconciler: published %d jobs not due yet again, each for its due time", len(outcome.later))
    if outcome.failed:  # their webhooks' outbox rows were written with their failure
        with session_scope(settings) as session:
            deliveries.jobs_ended(session, settings, outcome.failed, app, recorded=True)
    if outcome.requeue or outcome.failed:
        log.info("reconciler: re-enqueued %d jobs, failed %d", len(outcome.requeue), len(outcome.failed))
    webhook_tasks.sweep(settings, app)
    dicom_tasks.sweep(settings, app)
    return outcome


def register_tasks(app: Celery, settings: Settings) -> None:
    """Define the tasks on ``app`` (the time limits come from ``settings``). Not shared: each task holds
    the settings of its app, where Celery would give a shared one to every app the process builds later
    (a publisher, a test's app), before that app's own."""

    @app.task(
        name=RUN_JOB,
        shared=False,
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
        try:
            outcome = execute_job(settings, parsed)
        except NotDue as early:  # its ETA was on its publisher's clock: the time left counted by this worker
            self.app.send_task(RUN_JOB, args=[job_id], countdown=early.countdown, queue=settings.queue_name)
            outcome = (f"came {early.countdown:.3f} s before it is due on the database's clock (this worker's "
                       "clock and its publisher's differ): published again for then")  # fmt: skip
        except RunLater as later:
            self.app.send_task(RUN_JOB, args=[job_id], countdown=later.countdown, queue=settings.queue_name)
            outcome = f"back to the queue for {later.countdown:g} s (PACS unavailable)"
        log.info("job %s %s in %.1f ms", job_id, outcome, (time.perf_counter() - started) * 1000)

    spacing = RunSpacing(settings.reconcile_interval_s / 2)  # each pool process forks its own copy

    @app.task(name=RECONCILE, shared=False, ignore_result=True, autoretry_for=TRANSIENT, max_retries=0,
              soft_time_limit=settings.reconcile_time_limit_s,
              time_limit=settings.reconcile_time_limit_s + HARD_LIMIT_GRACE_S)  # fmt: skip
    def reconcile() -> None:
        if not spacing.due():
            log.debug("reconcile run skipped: this process ran one less than %.1f s ago", spacing.min_gap_s)
            return
        reconcile_once(settings, app)
