"""The jobs' state changes on real SQLite and PostgreSQL: one outcome per job, whatever races.

These call the repository functions the API and the worker use, on migrated databases.
"""

from __future__ import annotations

import copy
import functools
import uuid
from collections.abc import Callable
from datetime import timedelta
from typing import Any

import pytest
from sqlalchemy import event, inspect, select, text, update
from sqlalchemy.orm import Session

from services.core.config import Settings
from services.db import dicom_stores, runs, stats
from services.db import jobs as repo
from services.db.engine import PSYCOPG_CACHED_PARAMS, get_engine, session_scope, worker_connection
from services.db.migrate import downgrade, upgrade
from services.db.models import Job, JobMeasures, VertebraStrain, utcnow
from spine_engine.models import RegistrationResult
from spine_engine.reconstruction import register_model
from spine_engine.validation import validate_payload
from tests.conftest import queued_job, spine_payload

BACKENDS = pytest.mark.parametrize("db_settings", ["sqlite", "postgresql"], indirect=True)
LOST = {"type": "https://spine.example/problems/worker-lost", "title": "lost", "status": 500, "detail": "x"}


@functools.cache
def _fitted() -> dict[str, Any]:
    """A real engine result (the fit of ``spine_payload()``) as JSON."""
    return register_model(validate_payload(spine_payload())).model_dump(mode="json")


def result_like(major_cobb: float = 23.5) -> RegistrationResult:
    """A real ``RegistrationResult`` with known values where the tests read the measure tables: two
    curves (the major one of ``major_cobb`` degrees), kyphosis, lordosis and per-vertebra strains."""
    result = copy.deepcopy(_fitted())
    for i, v in enumerate(result["vertebrae"]):
        last = i == len(result["vertebrae"]) - 1
        v.update({"u": None if last else [0.001, 0.002 * i, 0.0005], "v": None if last else [0.0, 0.0, 1.0],
                  "sagittal_bending_deg": None if last else 1.5, "frontal_bending_deg": None if last else 0.1 * i,
                  "twist_deg": None if last else 0.2, "axial_rotation_deg": 0.5 * i})  # fmt: skip
    curve = result["measures"]["cobb"][0]
    result["measures"]["cobb"] = [
        {**curve, "upper": "T5", "lower": "T12", "apex": "T8", "angle_deg": major_cobb, "major": True,
         "convexity": "right", "apex_axial_rotation_deg": 7.0, "plane_of_max_curvature_deg": 60.0},
        {**curve, "upper": "T12", "lower": "L4", "apex": "L2", "angle_deg": 12.0, "major": False,
         "convexity": "left", "apex_axial_rotation_deg": -3.0, "plane_of_max_curvature_deg": 80.0},
    ]  # fmt: skip
    result["measures"].update({"thoracic_kyphosis_t4_t12_deg": 30.0, "thoracic_kyphosis_t5_t12_deg": 28.0,
                               "lumbar_lordosis_l1_l5_deg": -40.0})  # fmt: skip
    result["fit"]["mean_registration_error_mm"] = 0.8
    return RegistrationResult.model_validate(result)


def status_of(settings: Settings, job_id: uuid.UUID) -> Job:
    with session_scope(settings) as session:
        return repo.get_job(session, job_id)


@BACKENDS
def test_claim_is_conditional_so_a_second_delivery_does_nothing(db_settings: Settings) -> None:
    job_id = queued_job(db_settings)
    with session_scope(db_settings) as s:
        first = runs.claim_job(s, job_id, "1.0")
    with session_scope(db_settings) as s:
        second = runs.claim_job(s, job_id, "1.0")
    assert first is not None and first.attempt == 1 and first.payload == spine_payload()
    assert second is None
    result = result_like()
    with session_scope(db_settings) as s:
        assert runs.finish_job(s, first, result=result, engine_version="9.9.9")
    with session_scope(db_settings) as s:
        assert not runs.finish_job(s, first, error=LOST)  # a finished job keeps its one outcome
    job = status_of(db_settings, job_id)
    assert (job.status, job.attempts, job.engine_version, job.error) == ("succeeded", 1, "9.9.9", None)
    # stored from pydantic's own JSON text (SerializedJSON): the same document as the model's JSON values
    assert job.result == result.model_dump(mode="json")
    assert job.started_at is not None and job.finished_at is not None and job.finished_at >= job.started_at


@BACKENDS
def test_measures_are_stored_queryably(db_settings: Settings) -> None:
    ids = []
    for cobb in (10.0, 35.0, 52.0):
        job_id = queued_job(db_settings)
        with session_scope(db_settings) as s:
            claim = runs.claim_job(s, job_id, "1.0")
            assert claim is not None
            assert runs.finish_job(s, claim, result=result_like(cobb))
        ids.append(job_id)
    with session_scope(db_settings) as s:
        severe = s.scalars(select(JobMeasures.job_id).where(JobMeasures.major_cobb_deg > 30)).all()
        assert set(severe) == set(ids[1:])
        row = s.get(JobMeasures, ids[0])
        assert row is not None
        assert (row.major_curve_apex, row.major_convexity, row.curve_count) == ("T8", "right", 2)
        assert row.lumbar_lordosis_l1_l5_deg == -40.0 and row.converged
        strains = s.scalars(select(VertebraStrain).where(VertebraStrain.job_id == ids[0])).all()
        assert len(strains) == 17
        t3 = next(v for v in strains if v.level == "T3")
        assert (t3.u2, t3.v3, t3.twist_deg) == (pytest.approx(0.004), 1.0, 0.2)
        assert (t3.sagittal_bending_deg, t3.frontal_bending_deg) == (1.5, pytest.approx(0.2))  # T3 is index 2
        assert next(v for v in strains if v.level == "L5").u1 is None


@BACKENDS
def test_cancel_mid_fit_is_never_overwritten(db_settings: Settings) -> None:
    job_id = queued_job(db_settings)
    with session_scope(db_settings) as s:
        claim = runs.claim_job(s, job_id, "1.0")
    assert claim is not None
    with session_scope(db_settings) as s:
        job, cancelled_now = repo.cancel_job(s, job_id)
        assert job.status == "cancelled" and cancelled_now
        assert repo.cancel_job(s, job_id)[1] is False  # already cancelled: returned as it is
    with session_scope(db_settings) as s:
        assert not runs.finish_job(s, claim, result=result_like())
    job = status_of(db_settings, job_id)
    assert job.status == "cancelled" and job.result is None
    with session_scope(db_settings) as s:
        assert s.get(JobMeasures, job_id) is None
        assert not s.scalars(select(VertebraStrain).where(VertebraStrain.job_id == job_id)).all()
        assert runs.claim_job(s, job_id, "1.0") is None  # never run again


@BACKENDS
def test_worker_connections_claim_and_finish_in_one_statement_each(db_settings: Settings) -> None:
    """The worker's connections: each statement commits alone; a failed run stores no measures."""
    ok, bad = queued_job(db_settings), queued_job(db_settings)
    with worker_connection(db_settings, durable=False) as s:
        if s.dialect.name == "postgresql":  # the claim does not wait for the WAL flush
            assert s.execute(text("SHOW synchronous_commit")).scalar_one() == "off"
        claims = [runs.claim_job(s, job_id, "1.0") for job_id in (ok, bad)]
    assert all(c is not None for c in claims)
    with worker_connection(db_settings) as s:
        if s.dialect.name == "postgresql":
            assert s.execute(text("SHOW synchronous_commit")).scalar_one() == "on"
        assert runs.finish_job(s, claims[0], result=result_like(41.0))  # type: ignore[arg-type]
        assert runs.finish_job(s, claims[1], error=LOST)  # type: ignore[arg-type]
        assert not runs.finish_job(s, claims[0], error=LOST)  # type: ignore[arg-type]
    with session_scope(db_settings) as s:
        assert status_of(db_settings, ok).status == "succeeded"
        assert s.get(JobMeasures, ok).major_cobb_deg == 41.0  # type: ignore[union-attr]
        assert len(s.scalars(select(VertebraStrain).where(VertebraStrain.job_id == ok)).all()) == 17
        assert status_of(db_settings, bad).status == "failed" and s.get(JobMeasures, bad) is None
        assert not s.scalars(select(VertebraStrain).where(VertebraStrain.job_id == bad)).all()


@BACKENDS
def test_cancel_a_finished_job_is_refused(db_settings: Settings) -> None:
    job_id = queued_job(db_settings)
    with session_scope(db_settings) as s:
        claim = runs.claim_job(s, job_id, "1.0")
        assert claim is not None
        runs.finish_job(s, claim, error=LOST)
    with session_scope(db_settings) as s, pytest.raises(repo.JobFinished):
        repo.cancel_job(s, job_id)
    assert status_of(db_settings, job_id).status == "failed"


def _age(settings: Settings, job_id: uuid.UUID, **values: Any) -> None:
    with session_scope(settings) as s:
        s.execute(update(Job).where(Job.id == job_id).values(**values))


def _reconcile(settings: Settings, job_id: uuid.UUID, max_attempts: int = 2) -> runs.Reconciliation:
    """One reconcile, its outcome for ``job_id`` only: the session's PostgreSQL database is shared by
    the test files, whose jobs (a run left holding a lease, say) the reconciler may take back too."""
    with session_scope(settings) as s:
        outcome = runs.reconcile(
            s,
            queued_timeout=timedelta(minutes=5),
            max_attempts=max_attempts,
            lost_problem=LOST,
        )
    return runs.Reconciliation([i for i in outcome.requeue if i == job_id], [i for i in outcome.failed if i == job_id])


@BACKENDS
def test_reconciler_takes_back_a_lost_run_and_fences_the_stale_worker(db_settings: Settings) -> None:
    job_id = queued_job(db_settings)
    with session_scope(db_settings) as s:
        stale = runs.claim_job(s, job_id, "1.0")
    assert stale is not None
    assert _reconcile(db_settings, job_id).requeue == []  # recent: left alone
    _age(db_settings, job_id, lease_expires_at=utcnow() - timedelta(seconds=1))  # its worker died
    outcome = _reconcile(db_settings, job_id)
    assert outcome.requeue == [job_id] and outcome.failed == []
    job = status_of(db_settings, job_id)
    assert (job.status, job.attempts) == ("queued", 1)
    with session_scope(db_settings) as s:
        fresh = runs.claim_job(s, job_id, "1.0")
    assert fresh is not None and fresh.attempt == 2
    with session_scope(db_settings) as s:
        assert not runs.finish_job(s, stale, result=result_like())  # the lost worker woke up
        assert runs.finish_job(s, fresh, result=result_like())
    job = status_of(db_settings, job_id)
    assert (job.status, job.attempts) == ("succeeded", 2)


@BACKENDS
def test_reconciler_fails_a_job_out_of_attempts(db_settings: Settings) -> None:
    job_id = queued_job(db_settings)
    for _ in range(2):
        with session_scope(db_settings) as s:
            assert runs.claim_job(s, job_id, "1.0") is not None
        _age(db_settings, job_id, lease_expires_at=utcnow() - timedelta(seconds=1))  # its worker died
        _reconcile(db_settings, job_id)
    job = status_of(db_settings, job_id)
    assert (job.status, job.attempts, job.error) == ("failed", 2, LOST)


@BACKENDS
def test_reconciler_republishes_stale_queued_jobs_once_per_timeout(db_settings: Settings) -> None:
    job_id = queued_job(db_settings)
    assert _reconcile(db_settings, job_id).requeue == []
    _age(db_settings, job_id, enqueued_at=utcnow() - timedelta(hours=1))
    assert _reconcile(db_settings, job_id).requeue == [job_id]
    assert _reconcile(db_settings, job_id).requeue == []  # enqueued_at was refreshed
    assert status_of(db_settings, job_id).status == "queued"


@BACKENDS
def test_idempotency_key_is_unique_per_owner(db_settings: Settings) -> None:
    with session_scope(db_settings) as s:
        a, created_a = repo.create_job(s, spine_payload(), idempotency_key="k")
        b, created_b = repo.create_job(s, spine_payload(), idempotency_key="k")
        c, created_c = repo.create_job(s, spine_payload(), owner="clinic-1", idempotency_key="k")
        assert (created_a, created_b, created_c) == (True, False, True)
        assert a.id == b.id != c.id
        with pytest.raises(repo.IdempotencyConflict):
            repo.create_job(s, spine_payload(curve_mm=1.0), idempotency_key="k")


@BACKENDS
def test_a_batch_that_loses_a_key_to_a_concurrent_request_admits_the_rest_again(db_settings: Settings) -> None:
    """Between a keyed batch's lookup and its insert, a concurrent request stores one of its keys (the
    same body): the insert breaks the unique index, and the entries left are looked up again, admitted
    again (the cap counts what they add now) and stored as batch entries; the lost one replays the other's
    job. Before, they were stored one at a time by the single-key path, which the cap never saw."""
    owner, key = f"c-{uuid.uuid4().hex[:8]}", "K"
    payloads = [(0, spine_payload()), (1, spine_payload(curve_mm=3.0)), (2, spine_payload(curve_mm=4.0))]
    admitted: list[int] = []
    others: list[uuid.UUID] = []

    def admit(n: int) -> None:
        admitted.append(n)
        if not others:  # the concurrent request, in a session of its own, commits first
            with session_scope(db_settings) as other:
                [(job, made)] = repo.create_jobs_idempotent(other, payloads[:1], owner=owner, key=key)
                assert made
                others.append(job.id)

    with session_scope(db_settings) as s:
        outcomes = repo.create_jobs_idempotent(s, payloads, owner=owner, key=key, admit=admit)
        assert admitted == [3, 2]
        made = [outcome for outcome in outcomes if isinstance(outcome, tuple)]
        assert [created for _, created in made] == [False, True, True] and made[0][0].id == others[0]
        kinds = s.execute(select(Job.idempotency_key, Job.idempotency_kind).where(Job.owner == owner)).all()
        assert sorted(kinds) == [("K#0", "batch"), ("K#1", "batch"), ("K#2", "batch")]


@BACKENDS
def test_migrations_go_down_and_up_again(db_settings: Settings) -> None:
    downgrade(db_settings, "base")
    assert set(inspect(get_engine(db_settings)).get_table_names()) <= {"alembic_version"}
    upgrade(db_settings, quiet=True)
    tables = set(inspect(get_engine(db_settings)).get_table_names())
    assert {"jobs", "job_measures", "vertebra_strains"} <= tables
    indexes = {ix["name"] for ix in inspect(get_engine(db_settings)).get_indexes("jobs")}
    assert {"ix_jobs_status_created_at_id", "ix_jobs_created_at_id", "ix_jobs_finished_at"} <= indexes


def test_reconciler_leaves_a_backlog_alone_while_the_broker_holds_its_messages(tmp_path: Any) -> None:
    """Embedded broker (real SQLite queue): stale queued jobs are re-published only if a message is missing."""
    from services.core.jobqueue import enqueue, make_celery, queue_depth
    from services.worker.tasks import reconcile_once

    settings = Settings(data_dir=tmp_path, queue_name="backlog")
    upgrade(settings, quiet=True)
    app = make_celery(settings)
    published = [queued_job(settings), queued_job(settings)]
    enqueue(app, published)
    for job_id in published:
        _age(settings, job_id, enqueued_at=utcnow() - timedelta(hours=1))
    assert reconcile_once(settings, app).requeue == []  # two messages wait for two jobs
    lost = queued_job(settings)  # stored, never published
    _age(settings, lost, enqueued_at=utcnow() - timedelta(hours=1))
    requeued = reconcile_once(settings, app).requeue  # one message missing: the oldest stale job again
    assert len(requeued) == 1 and queue_depth(app, "backlog") == 3


def test_a_job_whose_message_could_not_be_published_is_published_at_the_next_reconcile(tmp_path: Any) -> None:
    """A real publish refused (a broker on a closed port): the POST still answers 202, the job is
    marked unpublished, and the next reconciler pass publishes it without waiting for the queued
    timeout, on a real (embedded) broker."""
    from fastapi.testclient import TestClient

    from services.api.app import create_app
    from services.core.jobqueue import make_celery, queue_depth
    from services.worker.tasks import reconcile_once
    from tests.conftest import make_key

    down = Settings(data_dir=tmp_path, CELERY_BROKER_URL="redis://127.0.0.1:1/0", queue_name="unpublished")
    upgrade(down, quiet=True)
    with TestClient(create_app(down)) as api:
        api.headers["Authorization"] = f"Bearer {make_key(down, 'unpublished', 'admin')}"
        single = api.post("/v1/jobs", json=spine_payload())
        batch = api.post("/v1/jobs/batch", json={"jobs": [spine_payload(curve_mm=3.0), spine_payload(curve_mm=4.0)]})
    assert single.status_code == 202 and batch.status_code == 200 and batch.json()["accepted"] == 2
    ids = [uuid.UUID(single.json()["id"]), *(uuid.UUID(e["job"]["id"]) for e in batch.json()["results"])]
    assert all(status_of(down, i).enqueued_at is None and status_of(down, i).status == "queued" for i in ids)

    up = Settings(data_dir=tmp_path, queue_name="unpublished", queued_timeout_s=3600)  # the embedded broker
    app = make_celery(up)
    outcome = reconcile_once(up, app)
    assert sorted(outcome.requeue) == sorted(ids) and queue_depth(app, "unpublished") == 3
    assert all(status_of(up, i).enqueued_at is not None for i in ids)
    assert reconcile_once(up, app).requeue == []  # published: left alone until the queued timeout


@BACKENDS
def test_a_renewed_lease_keeps_a_long_run_and_an_expired_one_is_taken_back(db_settings: Settings) -> None:
    """Leases: a run renewing its lease is left alone however long it runs; once it stops
    renewing, the reconciler takes the job back; a stale run's renewal is refused (fenced by attempt)."""
    job_id = queued_job(db_settings)
    with session_scope(db_settings) as s:
        run = runs.claim_job(s, job_id, "1.0", lease=timedelta(seconds=30))
    assert run is not None
    _age(db_settings, job_id, started_at=utcnow() - timedelta(hours=1))  # long past any fit time limit
    assert _reconcile(db_settings, job_id).requeue == []  # its lease holds
    with session_scope(db_settings) as s:
        assert runs.renew_leases(s, [run], timedelta(seconds=30)) == [run]
    _age(db_settings, job_id, lease_expires_at=utcnow() - timedelta(milliseconds=1))  # it stopped renewing
    assert _reconcile(db_settings, job_id).requeue == [job_id]
    with session_scope(db_settings) as s:
        assert runs.renew_leases(s, [run], timedelta(seconds=30)) == []  # the dead run cannot renew
        fresh = runs.claim_job(s, job_id, "1.0")
    assert fresh is not None and fresh.attempt == 2
    assert status_of(db_settings, job_id).lease_expires_at is not None


@BACKENDS
def test_the_reconcilers_queued_count_equals_the_count_by_status(db_settings: Settings) -> None:
    """``stats.count_all_queued`` (the reconciler's broker check, read through the status index)
    counts what the full count by status counts: here 3 jobs stored, one claimed, one cancelled."""
    with session_scope(db_settings) as s:
        before = stats.count_all_queued(s)  # the database is shared by this module's tests
    ids = [queued_job(db_settings) for _ in range(3)]
    with session_scope(db_settings) as s:
        assert runs.claim_job(s, ids[0], "1.0") is not None
    with session_scope(db_settings) as s:
        repo.cancel_job(s, ids[1])
    with session_scope(db_settings) as s:
        assert stats.count_all_queued(s) == before + 1 == stats.count_by_status(s)["queued"]


def _statements(settings: Settings, call: Callable[[Session], object]) -> list[tuple[str, Any]]:
    """The (SQL, parameters) of every statement ``call`` sent, in a session rolled back after."""
    sent: list[tuple[str, Any]] = []

    def record(_conn: Any, _cursor: Any, statement: str, parameters: Any, _context: Any, _many: bool) -> None:
        sent.append((statement, parameters))

    engine = get_engine(settings)
    event.listen(engine, "before_cursor_execute", record)
    try:
        with Session(engine) as session:
            call(session)
            session.rollback()
    finally:
        event.remove(engine, "before_cursor_execute", record)
    return sent


def _served_by(settings: Settings, index: str, statement: str, parameters: Any) -> str:
    """The plan of a SELECT on ``jobs`` when ``index`` is the only index the planner may take (the
    test tables are nearly empty, so left alone it would take any): on SQLite the statement with
    ``INDEXED BY`` (an error when the index cannot serve it); on PostgreSQL with the table's other
    indexes dropped in a transaction rolled back after, and sequential scans priced out."""
    with get_engine(settings).connect() as conn:
        if conn.dialect.name == "sqlite":
            forced = statement.replace("FROM jobs", f"FROM jobs INDEXED BY {index}", 1)
            rows = conn.exec_driver_sql("EXPLAIN QUERY PLAN " + forced, parameters).all()
            return "\n".join(str(row[-1]) for row in rows)
        with conn.begin() as transaction:
            others = conn.exec_driver_sql(
                "SELECT indexname FROM pg_indexes WHERE tablename = 'jobs' AND indexname NOT IN (%(keep)s, 'pk_jobs')",
                {"keep": index},
            ).scalars().all()
            for name in others:
                conn.exec_driver_sql(f"DROP INDEX {name}")
            conn.exec_driver_sql("SET LOCAL enable_seqscan = off")
            plan = "\n".join(r[0] for r in conn.exec_driver_sql("EXPLAIN " + statement, parameters).all())
            transaction.rollback()
        return plan


@BACKENDS
def test_the_partial_indexes_still_serve_their_queries(db_settings: Settings) -> None:
    """Migration 0010 made six indexes of ``jobs`` partial (column IS NOT NULL): each query that used
    one still does (its strict comparison implies the predicate), on SQLite and PostgreSQL."""
    since = utcnow() - timedelta(minutes=5)
    queries: dict[str, Callable[[Session], object]] = {
        "ix_jobs_owner_study_instance_uid": lambda s: repo.list_jobs(s, owner="c", study_instance_uid="1.2.3"),
        "ix_jobs_owner_accession_number": lambda s: repo.list_jobs(s, owner="c", accession_number="A1"),
        "ix_jobs_owner_patient_id": lambda s: repo.list_jobs(s, owner="c", patient_id="P1"),
        "ix_jobs_finished_at": lambda s: stats.recent_durations(s, since),
        "ix_jobs_dicom_store_due_at": lambda s: dicom_stores.overdue(s, utcnow()),  # the STOW-RS sweep's query
        "uq_jobs_owner_idempotency_key": lambda s: repo.create_job(s, spine_payload(), owner="c", idempotency_key="k"),
    }
    for index, call in queries.items():
        statement, parameters = _statements(db_settings, call)[0]
        assert statement.lstrip().startswith("SELECT"), statement
        plan = _served_by(db_settings, index, statement, parameters)
        assert index in plan, (index, plan)
        if index == "uq_jobs_owner_idempotency_key" and "Index Cond" in plan:  # PostgreSQL: searched by both keys
            condition = next(line for line in plan.splitlines() if "Index Cond" in line)
            assert "COALESCE(owner" in condition and "idempotency_key" in condition, plan


@pytest.mark.parametrize("db_settings", ["postgresql"], indirect=True)
def test_a_batch_of_jobs_is_a_few_multi_row_inserts_on_postgresql(db_settings: Settings) -> None:
    """``create_jobs`` of 100 payloads sends multi-row INSERTs (insertmanyvalues), not 100, each small
    enough for psycopg to cache its conversion (at most 50 parameters, 4,096 bytes)."""
    sent = _statements(db_settings, lambda s: repo.create_jobs(s, [spine_payload()] * 100, owner="c"))
    inserts = [(sql, p) for sql, p in sent if sql.lstrip().startswith("INSERT INTO jobs")]
    assert 1 < len(inserts) <= 20, [sql[:80] for sql, _ in sent]
    assert all(isinstance(p, dict) and len(p) <= PSYCOPG_CACHED_PARAMS and len(sql) <= 4096 for sql, p in inserts)
