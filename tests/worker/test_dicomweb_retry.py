"""The DICOMweb retry delays are settings (SPINE_DICOMWEB_RETRY_BASE_S, SPINE_DICOMWEB_RETRY_MAX_S): the
delay before a job whose PACS was unavailable runs again and between STOW-RS attempts, refused at start
when not positive, naming the variable. Real SQLite database and a real refused TCP connection (a free
loopback port nothing listens on) as the PACS."""

from __future__ import annotations

import uuid
from pathlib import Path

import pytest
from pydantic import ValidationError
from sqlalchemy import update

from services.cli.errors import explain
from services.core.config import Settings
from services.db.clock import db_now
from services.db.engine import session_scope, worker_connection
from services.db.jobs import create_job
from services.db.migrate import upgrade
from services.db.models import Job
from services.db.runs import claim_job, due_in_s
from services.dicom.results import NOT_STORABLE
from services.worker import dicom_tasks
from services.worker.tasks import RunLater, execute_job, resolve_dicom
from tests.conftest import spine_payload
from tests.faults import free_port


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    made = Settings(data_dir=tmp_path, dicomweb_url=f"http://127.0.0.1:{free_port()}/dicom-web", dicomweb_timeout_s=2,
                    dicomweb_retry_base_s=7, dicomweb_retry_max_s=10, max_attempts=5)  # fmt: skip
    upgrade(made, quiet=True)
    return made


def _run_later_s(settings: Settings, job_id: uuid.UUID) -> float:
    """Claim the job as a worker does and resolve its images on the unreachable PACS: the delay it is
    handed back to the queue for."""
    with worker_connection(settings, durable=False) as connection:
        claim = claim_job(connection, job_id, "1.0")
    assert claim is not None
    with pytest.raises(RunLater) as later:
        resolve_dicom(settings, claim, f"/v1/jobs/{job_id}")
    with session_scope(settings) as session:
        assert session.get(Job, job_id).status == "queued"  # type: ignore[union-attr]
        due_in = due_in_s(session, job_id)  # due again after the delay, on the database's clock
        assert due_in is not None and 0 < due_in <= later.value.countdown
        session.execute(update(Job).where(Job.id == job_id).values(enqueued_at=db_now()))  # the delay waited out
    return later.value.countdown


def test_a_job_whose_pacs_is_unavailable_runs_again_after_the_configured_delays(settings: Settings) -> None:
    payload = spine_payload(spacing_mm=0.15)  # in px without a spacing: the PA header is needed
    payload["study"] = {"study_instance_uid": "1.2.3", "pa_sop_instance_uid": "1.2.3.4"}
    with session_scope(settings) as session:
        job, _ = create_job(session, payload)
    assert _run_later_s(settings, job.id) == 7  # SPINE_DICOMWEB_RETRY_BASE_S
    assert _run_later_s(settings, job.id) == 10  # 14 s capped at SPINE_DICOMWEB_RETRY_MAX_S


def test_the_stow_delays_double_from_the_base_up_to_the_cap() -> None:
    settings = Settings(dicomweb_retry_base_s=0.5, dicomweb_retry_max_s=3)
    assert [dicom_tasks.retry_delay_s(settings, attempt) for attempt in (1, 2, 3, 4, 5)] == [0.5, 1, 2, 3, 3]
    default = Settings()
    assert [dicom_tasks.retry_delay_s(default, attempt) for attempt in (1, 4, 5, 6)] == [2, 16, 32, 60]


@pytest.mark.parametrize(
    ("study", "reason"),
    [(None, "the job has no study"), ({"study_instance_uid": "1.2.3"}, "study 1.2.3 has no Patient ID")],
    ids=["no-study", "no-patient-id"],
)
def test_results_without_the_patients_identity_are_not_stored_nor_retried(
    settings: Settings, study: dict[str, str] | None, reason: str
) -> None:
    """A succeeded job without a study, or whose study has no Patient ID: its STOW-RS attempt sends nothing
    (the PACS, a refused port, would make it ``dicomweb-unavailable`` and retried), is recorded with the
    reason, no next attempt and no due time for the sweep, and the job stays succeeded."""
    stow = settings.model_copy(update={"dicomweb_store_results": True})
    payload = spine_payload()
    if study is not None:
        payload["study"] = study
    with session_scope(settings) as session:
        job, _ = create_job(session, payload)
    assert execute_job(settings, job.id) == "succeeded"  # results not stored by this run: no message published
    outcome = dicom_tasks.store_once(stow, job.id, 1)
    assert (outcome.ok, outcome.stored, outcome.problem_type, outcome.next_attempt_at) == (False, [], NOT_STORABLE,
                                                                                         None)  # fmt: skip
    assert outcome.error is not None and reason in outcome.error
    with session_scope(settings) as session:
        row = session.get(Job, job.id)
        assert row is not None and (row.status, row.error, row.dicom_store_due_at) == ("succeeded", None, None)
        assert [(s["attempt"], s["problem_type"]) for s in row.dicom_stores or []] == [(1, NOT_STORABLE)]


@pytest.mark.parametrize("variable", ["SPINE_DICOMWEB_RETRY_BASE_S", "SPINE_DICOMWEB_RETRY_MAX_S"])
@pytest.mark.parametrize("value", ["-1", "0"])
def test_a_delay_that_is_not_positive_is_refused_naming_its_variable(
    monkeypatch: pytest.MonkeyPatch, variable: str, value: str
) -> None:
    monkeypatch.setenv(variable, value)
    with pytest.raises(ValidationError) as refused:
        Settings()
    explained = explain(refused.value)
    assert explained is not None
    assert f"{variable}: Input should be greater than 0" in explained[1], explained
