"""End to end, on the embedded default and on PostgreSQL + Redis: the in-process API and a real
`spine worker` subprocess run jobs through the real engine to one stored outcome each.
"""

from __future__ import annotations

import time
import uuid
from datetime import timedelta
from typing import Any

import pytest
from sqlalchemy import func, select, update

from services.core.jobqueue import enqueue
from services.core.problems import PROBLEM_BASE
from services.db import jobs as repo
from services.db.engine import session_scope
from services.db.models import Job, JobMeasures, VertebraStrain, utcnow
from spine_engine.models import RegistrationResult
from tests.conftest import Service, engine_refused_payload, spine_payload

pytestmark = pytest.mark.integration


def stored(service: Service, job_id: str) -> tuple[int, int]:
    """(job_measures rows, vertebra_strains rows) of a job."""
    with session_scope(service.settings) as s:
        measures = s.scalar(select(func.count()).where(JobMeasures.job_id == uuid.UUID(job_id)))
        strains = s.scalar(select(func.count()).where(VertebraStrain.job_id == uuid.UUID(job_id)))
        return int(measures or 0), int(strains or 0)


def test_a_job_runs_to_a_stored_result(service: Service) -> None:
    job = service.submit(spine_payload())
    done = service.wait(job["id"])
    assert done["status"] == "succeeded", done["error"]
    assert done["attempts"] == 1 and done["error"] is None
    assert done["created_at"] <= done["started_at"] <= done["finished_at"]
    result = RegistrationResult.model_validate(done["result"])
    assert result.vertebrae[0].level == "T1" and len(result.vertebrae) == 17
    assert done["engine_version"] == result.engine.version
    assert stored(service, job["id"]) == (1, 17)
    listed = service.client.get("/v1/jobs", params={"status": "succeeded"}).json()["jobs"]
    assert job["id"] in {j["id"] for j in listed}


def test_an_engine_rejection_fails_the_job_with_a_problem(service: Service) -> None:
    done = service.wait(service.submit(engine_refused_payload())["id"])  # passes the API, refused by the engine
    assert done["status"] == "failed" and done["result"] is None
    assert done["error"]["type"] == PROBLEM_BASE + "validation-error"
    assert [e["path"] for e in done["error"]["errors"]] == ["pa.landmark_sd_mm", "lateral.landmark_sd_mm"]
    assert done["attempts"] == 1


def test_a_message_delivered_three_times_runs_once(service: Service) -> None:
    with session_scope(service.settings) as s:
        job, _ = repo.create_job(s, spine_payload(curve_mm=20.0))
    enqueue(service.client.app.state.celery, [job.id, job.id, job.id])  # type: ignore[attr-defined]
    done = service.wait(str(job.id))
    assert done["status"] == "succeeded" and done["attempts"] == 1
    time.sleep(0.5)
    assert service.job(str(job.id))["finished_at"] == done["finished_at"]
    assert stored(service, str(job.id)) == (1, 17)


def test_a_cancelled_job_is_never_run(service: Service) -> None:
    with session_scope(service.settings) as s:
        job, _ = repo.create_job(s, spine_payload())
    cancel = service.client.post(f"/v1/jobs/{job.id}/cancel")
    assert cancel.status_code == 200 and cancel.json()["status"] == "cancelled"
    enqueue(service.client.app.state.celery, [job.id])  # type: ignore[attr-defined]
    sentinel = service.submit(spine_payload())
    service.wait(sentinel["id"])
    time.sleep(0.5)
    after = service.job(str(job.id))
    assert (after["status"], after["started_at"], after["attempts"]) == ("cancelled", None, 0)


def test_the_reconciler_recovers_a_lost_message_and_a_dead_run(service: Service) -> None:
    long_ago = utcnow() - timedelta(hours=1)
    with session_scope(service.settings) as s:
        lost, _ = repo.create_job(s, spine_payload())  # never published
        stranded, _ = repo.create_job(s, spine_payload())  # its worker died mid-fit
        hopeless, _ = repo.create_job(s, spine_payload())  # died on its last allowed attempt
        s.execute(update(Job).where(Job.id == lost.id).values(enqueued_at=long_ago))
        dead = {"status": "running", "started_at": long_ago, "lease_expires_at": long_ago}  # no renewal since
        s.execute(update(Job).where(Job.id == stranded.id).values(attempts=1, **dead))
        s.execute(update(Job).where(Job.id == hopeless.id).values(attempts=2, **dead))
    assert service.wait(str(lost.id), 30)["status"] == "succeeded"
    recovered = service.wait(str(stranded.id), 30)
    assert (recovered["status"], recovered["attempts"]) == ("succeeded", 2)
    failed = service.wait(str(hopeless.id), 30)
    assert (failed["status"], failed["attempts"]) == ("failed", 2)
    assert failed["error"]["type"] == PROBLEM_BASE + "worker-lost"


def test_a_batch_runs_every_valid_payload_once(service: Service) -> None:
    payloads: list[Any] = [spine_payload(curve_mm=5.0 + i) for i in range(20)]
    payloads.insert(3, {"pa": {}})
    body = service.client.post("/v1/jobs/batch", json={"jobs": payloads}).json()
    assert (body["accepted"], body["rejected"]) == (20, 1)
    ids = [e["job"]["id"] for e in body["results"] if "job" in e]
    finished = service.wait_all(ids)
    assert {j["status"] for j in finished} == {"succeeded"}
    assert {j["attempts"] for j in finished} == {1}
    metrics = service.client.get("/metrics").text
    assert 'spine_fit_duration_seconds{quantile="0.5"} NaN' not in metrics
