"""Faults survived, against real PostgreSQL, Redis and Celery worker processes (tests/faults.py).

Each test runs the real service as processes (uvicorn API, `spine worker`), sends it jobs and a
steady load of single POSTs from a thread, injects one fault, and then checks every accepted job:
it ends with exactly one outcome (none lost, none with two outcomes). The figures are printed
(`reliability: {...}`) and, with SPINE_RELIABILITY_OUT set, appended to that file (JSON lines):
docs/reliability.md reports them. Every wait is bounded; traffic goes only to 127.0.0.1.

- kill -9 of a worker (its whole process group) in the middle of fits;
- (a restart of Redis while jobs are queued is tests/integration/test_loadbench.py's ``restart-redis``
  fault: the load bench's own redis-server, with the 30 s recovery target);
- PostgreSQL stopped for some seconds (our own throwaway cluster): 503 problems, never 500, nothing
  accepted that is not stored, recovery without help, workers retry and finish;
- the same job messages delivered twice, concurrently: one run, one result each;
- cancels racing running fits: each job ends cancelled or succeeded, never both.
"""

from __future__ import annotations

import random
import time
import uuid
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import httpx
import pytest
from sqlalchemy import func, select

from services.core.jobqueue import enqueue, make_celery
from services.core.problems import PROBLEM_BASE
from services.db import jobs as repo
from services.db.engine import session_scope
from services.db.models import Job
from tests.conftest import _postgres_database, _purge_queue, spine_payload
from tests.faults import (
    FaultFigures,
    LiveService,
    Load,
    outcome_figures,
    own_postgres,
    payload_in_logs,
    reliability_env,
    report,
    settle,
    wait_until,
)

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]

LOAD_RATE = 10.0  # single POSTs per second, held during every fault


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory, redis_url: str) -> Iterator[LiveService]:
    """A live service on its own PostgreSQL database (shared server) and queue (shared Redis)."""
    workdir = tmp_path_factory.mktemp("live")
    with _postgres_database("faults") as url:
        env = reliability_env(workdir, url, redis_url)
        service = LiveService(workdir, env)
        try:
            service.start()
            yield service
        finally:
            service.stop()
            _purge_queue(redis_url, env["SPINE_QUEUE_NAME"])


def test_kill_9_a_worker_mid_fits(live: LiveService, capsys: pytest.CaptureFixture[str]) -> None:
    started = time.monotonic()
    ids = live.submit_batch(150)
    load = Load(live, LOAD_RATE, max_s=60)
    load.start()
    try:
        wait_until(lambda: live.count(ids, "succeeded") >= 10, 30, "the worker to be busy")
        states = live.statuses(ids)
        running = sum(1 for v in states.values() if v[0] == "running")
        pending = sum(1 for v in states.values() if v[0] in ("queued", "running"))
        victim = next(w for w in live.workers if w.poll() is None)
        fault_at = time.monotonic()
        live.kill_worker(victim)
        killed_at = datetime.now(UTC)
        at_kill = live.statuses(ids)
        stranded = [i for i, v in at_kill.items() if v[0] == "running"]  # claimed by a process now dead
        time.sleep(3)  # no worker at all for a while; the API keeps accepting
        live.start_worker()
        fault_s = time.monotonic() - fault_at
        time.sleep(2)
    finally:
        load.stop()
    accepted = ids + load.accepted()
    settle(live, accepted, timeout=120)
    figures = outcome_figures(live, accepted)
    report(
        FaultFigures(
            test="kill -9 worker mid-fit",
            fault=f"SIGKILL of the worker's process group (main, 2 pool processes, beat) with {running} fits "
            f"running and {pending} jobs of the batch not done; a new worker 3 s later",
            jobs_submitted=figures["submitted"],
            jobs_completed=figures["completed"],
            jobs_lost=figures["lost"],
            jobs_with_two_outcomes=figures["two_outcomes"],
            load=f"150-job batch, then {LOAD_RATE:g} POST/s single jobs throughout",
            answers_during_fault=load.statuses(fault_at, fault_at + fault_s),
            fault_seconds=round(fault_s, 1),
            test_seconds=round(time.monotonic() - started, 1),
            notes=f"during the fault: {load.latency(fault_at, fault_at + fault_s)}; {len(stranded)} jobs left "
            "running by the killed processes",
        ),
        capsys,
    )
    assert pending > 0, states  # the fault hit jobs in flight: some of the batch were not done
    assert payload_in_logs(live) == []
    after = live.statuses(ids)
    for job_id in stranded:
        status, attempts, finished_at, _ = after[job_id]
        if attempts == at_kill[job_id][1]:
            # The killed process's last statement: its finish (finished_at is the database's clock when it
            # built the statement) reached PostgreSQL before the SIGKILL and was committed after
            # `at_kill` was read. Nobody else can write this attempt: a take-back bumps it.
            assert status == "succeeded" and finished_at is not None and finished_at <= killed_at, (
                at_kill[job_id], after[job_id], killed_at)
        else:  # taken back once its lease expired and run again, to one outcome
            assert (status, attempts) == ("succeeded", at_kill[job_id][1] + 1), (at_kill[job_id], after[job_id])
    assert set(live.measures_rows(ids).values()) == {1}  # one stored measures row per job, none doubled
    assert figures["lost"] == 0, figures
    assert figures["two_outcomes"] == 0, figures
    assert figures["completed"] == len(accepted), figures
    assert set(load.statuses()) == {"202"} and load.transport_errors == 0


def test_the_same_messages_delivered_twice_run_once(live: LiveService, capsys: pytest.CaptureFixture[str]) -> None:
    started = time.monotonic()
    with session_scope(live.settings) as s:  # stored, not published: we publish each twice below
        ids = [str(repo.create_job(s, spine_payload(curve_mm=3.0 + i), owner="reliability")[0].id) for i in range(40)]
    celery = make_celery(live.settings)
    twice = [uuid.UUID(i) for i in ids for _ in range(2)]  # both copies side by side: 2 pool processes race
    assert enqueue(celery, twice) == 80
    settle(live, ids, timeout=60)
    figures = outcome_figures(live, ids)
    states = live.statuses(ids)
    runs = sum(v[1] for v in states.values())  # attempts: a run needs a claim, a claim adds one
    report(
        FaultFigures(
            test="duplicate delivery",
            fault="every job message published twice, back to back, to a worker with 2 pool processes",
            jobs_submitted=len(ids),
            jobs_completed=figures["completed"],
            jobs_lost=figures["lost"],
            jobs_with_two_outcomes=figures["two_outcomes"],
            load="80 messages for 40 jobs",
            notes=f"runs (claims) in all: {runs}",
            test_seconds=round(time.monotonic() - started, 1),
        ),
        capsys,
    )
    assert figures["lost"] == 0 and figures["two_outcomes"] == 0, figures
    assert all(v[0] == "succeeded" and v[1] == 1 for v in states.values()), states
    assert sum(live.stored_outcomes()[i] for i in ids) == len(ids)  # one stored result per job


def test_cancel_racing_running_fits(live: LiveService, capsys: pytest.CaptureFixture[str]) -> None:
    """Cancel jobs the moment they are seen running (and some queued, some done): never both outcomes."""
    started = time.monotonic()
    cancels: dict[str, int] = {}
    ids: list[str] = []
    rng = random.Random(7)
    deadline = time.monotonic() + 40
    with live.client() as client:
        while time.monotonic() < deadline and (len(ids) < 60 or _mid_run(live, cancels) < 3):
            wave = live.submit_batch(20, curve0=rng.uniform(0, 20))
            ids += wave
            wave_end = time.monotonic() + 15
            while time.monotonic() < wave_end:
                running = client.get("/v1/jobs", params={"status": "running", "limit": 20}).json()["jobs"]
                for job in running:
                    if job["id"] in wave and job["id"] not in cancels:
                        cancels[job["id"]] = client.post(f"/v1/jobs/{job['id']}/cancel").status_code
                left = [i for i in wave if i not in cancels]
                if rng.random() < 0.05 and left:  # now and then, one at a random moment
                    pick = rng.choice(left)
                    cancels[pick] = client.post(f"/v1/jobs/{pick}/cancel").status_code
                if all(v[0] in ("succeeded", "failed", "cancelled") for v in live.statuses(wave).values()):
                    break
    settle(live, ids, timeout=60)
    figures = outcome_figures(live, ids)
    states = live.statuses(ids)
    measures = live.measures_rows(ids)
    stored = live.stored_outcomes()
    mid_run = _mid_run(live, cancels)
    for job_id, code in cancels.items():
        status, _, _, has_result = states[job_id]
        if code == 200:  # the cancel won: cancelled, no result, no measures, no stored outcome
            assert status == "cancelled" and not has_result and measures.get(job_id, 0) == 0, (job_id, states[job_id])
            assert stored.get(job_id, 0) == 0, job_id
        else:  # the fit won: 409, and the job keeps its one result
            assert code == 409 and status == "succeeded" and has_result, (job_id, code, states[job_id])
    report(
        FaultFigures(
            test="cancel racing fits",
            fault="POST /cancel on jobs as soon as GET /v1/jobs?status=running shows them, and on random ones",
            jobs_submitted=len(ids),
            jobs_completed=figures["completed"],
            jobs_lost=figures["lost"],
            jobs_with_two_outcomes=figures["two_outcomes"],
            load=f"waves of 20 jobs; {len(cancels)} cancels: {mid_run} mid-fit, "
            f"{sum(1 for c in cancels.values() if c == 409)} too late (409)",
            notes=f"final: {figures['statuses']}",
            test_seconds=round(time.monotonic() - started, 1),
        ),
        capsys,
    )
    assert figures["lost"] == 0 and figures["two_outcomes"] == 0, figures
    assert mid_run >= 1, f"no cancel landed while a fit ran ({cancels}): the race was not exercised"


def _mid_run(live: LiveService, cancels: dict[str, int]) -> int:
    """Cancels that landed on a job already claimed by a worker (cancelled with a start time)."""
    won = [i for i, code in cancels.items() if code == 200]
    if not won:
        return 0
    with session_scope(live.settings) as s:
        rows = s.execute(select(Job.id, Job.started_at).where(Job.id.in_([uuid.UUID(i) for i in won]))).all()
    return sum(1 for _, started_at in rows if started_at is not None)


def test_postgres_outage_answers_503_and_recovers(tmp_path: Path, redis_url: str,
                                                  capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    """Our own PostgreSQL cluster stopped (immediate: like a crash) for some seconds, then started."""
    started = time.monotonic()
    outage_s = 6.0
    with own_postgres() as pg:
        env = reliability_env(tmp_path, pg.url, redis_url)
        service = LiveService(tmp_path, env)
        load = Load(service, LOAD_RATE, max_s=60)
        ready: list[int] = []
        try:
            service.start()
            ids = service.submit_batch(300)
            load.start()
            wait_until(lambda: service.count(ids, "succeeded") >= 10, 30, "the worker to be busy")
            pending = sum(1 for v in service.statuses(ids).values() if v[0] in ("queued", "running"))
            fault_at = time.monotonic()
            pg.stop("immediate")
            with httpx.Client(base_url=service.base_url, timeout=10) as probe:
                while time.monotonic() - fault_at < outage_s:
                    ready.append(probe.get("/readyz").status_code)
                    time.sleep(0.5)
                pg.start()
                back_at = time.monotonic()
                wait_until(lambda: probe.get("/readyz").status_code == 200, 30, "the API to be ready again")
                recovered_s = time.monotonic() - back_at
            time.sleep(4)
            load.stop()
            accepted = ids + load.accepted()
            settle(service, accepted, timeout=120)
            figures = outcome_figures(service, accepted)
            leaked = payload_in_logs(service)
            with session_scope(service.settings) as s:
                stored_jobs = int(s.scalar(select(func.count()).select_from(Job)) or 0)
        finally:
            load.stop()
            service.stop()
            _purge_queue(redis_url, env["SPINE_QUEUE_NAME"])
    during = [a for a in load.answers if fault_at <= a.at < back_at]
    report(
        FaultFigures(
            test="PostgreSQL outage",
            fault=f"own PostgreSQL cluster stopped (pg_ctl -m immediate) for {outage_s:g} s, then started; "
            f"{pending} jobs of the batch queued or running when it stopped",
            jobs_submitted=figures["submitted"],
            jobs_completed=figures["completed"],
            jobs_lost=figures["lost"],
            jobs_with_two_outcomes=figures["two_outcomes"],
            load=f"300-job batch, then {LOAD_RATE:g} POST/s single jobs throughout",
            answers_during_fault=load.statuses(fault_at, back_at),
            fault_seconds=round(back_at - fault_at, 1),
            test_seconds=round(time.monotonic() - started, 1),
            notes=f"during the fault: {load.latency(fault_at, back_at)}; /readyz during the outage: "
            f"{sorted(set(ready))}; ready again {recovered_s:.1f} s after the restart; answers after it: "
            f"{load.statuses(back_at)}",
        ),
        capsys,
    )
    assert pending > 0  # the fault hit jobs in flight: queued or running when the database stopped
    assert [a for a in load.answers if a.status >= 500 and a.status != 503] == [], load.statuses()
    assert any(a.status == 503 for a in during), load.statuses(fault_at, back_at)
    for answer in load.answers:
        if answer.status == 503:
            assert answer.content_type.startswith("application/problem+json")
            assert answer.problem_type == PROBLEM_BASE + "service-unavailable"
    assert set(ready) >= {503}
    assert figures["lost"] == 0 and figures["two_outcomes"] == 0, figures  # every 202 was stored, and finished
    assert figures["completed"] == len(accepted), figures
    assert pending > 0  # the outage hit the workers mid-work
    assert set(load.statuses(back_at + recovered_s + 1)) <= {"202"}, load.statuses(back_at)  # recovered by itself
    assert stored_jobs == len(accepted), (stored_jobs, len(accepted))  # a 503 stored nothing
    assert leaked == [], leaked[:3]

