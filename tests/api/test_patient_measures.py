"""GET /v1/patients/{patient_id}/measures: a patient's follow-up, on PostgreSQL with real jobs run by the
worker (the distributed service: PostgreSQL, Redis, a `spine worker` subprocess), restricted to the
caller's jobs; and the flagging rule on its own (5° and 1.96 × the combined SD, which decided)."""

from __future__ import annotations

import math
import uuid
from collections.abc import Iterator
from datetime import UTC, date, datetime, timedelta
from typing import Any
from urllib.parse import quote

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update

from services.api.app import create_app
from services.api.routes.patients import MeasureValue, Visit, change, visit
from services.core.config import Settings
from services.db import jobs as jobs_repo
from services.db.engine import session_factory
from services.db.models import Job
from spine_engine import register
from tests.conftest import Service, make_key, spine_payload

BACKENDS = pytest.mark.parametrize("db_settings", ["sqlite", "postgresql"], indirect=True)
T0 = datetime(2026, 1, 1, 8, 0, tzinfo=UTC)

MEASURES = ("major_cobb", "minor_cobb", "kyphosis_t4_t12", "lordosis_l1_l5", "apex_axial_rotation")


def _visit(value: float, sd: float | None, when: date) -> Visit:
    m = MeasureValue(value_deg=value, sd_deg=sd)
    return Visit(job_id=uuid.uuid4(), study_date=when, kyphosis_t4_t12=m, lordosis_l1_l5=m, major_cobb=m)


@pytest.mark.parametrize(
    ("before", "after", "sd", "flagged", "decided_by"),
    [
        (40.0, 48.0, 1.5, True, "convention_5deg"),  # 1.96·√2·1.5 = 4.2° < 5°: the 5° convention decides
        (40.0, 44.0, 1.5, False, "convention_5deg"),  # 4° < 5°
        (40.0, 48.0, 3.5, False, "combined_sd"),  # 1.96·√2·3.5 = 9.7° > 8°: within the measurement's noise
        (40.0, 30.0, 3.5, True, "combined_sd"),  # a 10° decrease exceeds both
        (40.0, 46.0, None, True, "convention_5deg"),  # no SD: the 5° rule alone
    ],
)
def test_a_change_is_flagged_beyond_both_5_deg_and_1_96_combined_sd(
    before: float, after: float, sd: float | None, flagged: bool, decided_by: str
) -> None:
    c = change("major_cobb", _visit(before, sd, date(2025, 1, 1)), _visit(after, sd, date(2025, 7, 1)))
    assert c is not None
    assert c.change_deg == pytest.approx(after - before)
    assert c.flagged is flagged and c.decided_by == decided_by
    assert c.combined_sd_deg == (None if sd is None else pytest.approx(math.hypot(sd, sd)))


def test_a_spine_below_the_threshold_is_followed_by_its_largest_angle() -> None:
    """A nearly straight spine (no frontal curve of 10°): its visit's major Cobb angle is the
    result's ``largest_cobb``, with its SD and 'below 10°' in the levels; a curved one's is its
    major curve's."""
    curved, mild = register(spine_payload()), register(spine_payload(curve_mm=1.5))
    assert curved["measures"]["cobb"] and not mild["measures"]["cobb"]
    for result, expected in ((curved, next(c for c in curved["measures"]["cobb"] if c["major"])),
                             (mild, mild["measures"]["largest_cobb"])):  # fmt: skip
        job = Job(id=uuid.uuid4(), payload={"study": {"study_date": "2025-01-01"}}, result=result)
        major = visit(job).major_cobb
        assert major is not None
        assert major.value_deg == pytest.approx(expected["angle_deg"])
        assert major.sd_deg == pytest.approx(expected["angle_sd_deg"])
        assert major.levels is not None and major.levels.startswith(f"{expected['upper']}–{expected['lower']}")
        assert ("below 10°" in major.levels) is (result is mild)


def test_a_visit_says_which_values_are_model_estimates_and_names_an_apical_disc() -> None:
    """A visit's values carry the reason they come from the model's prior, the one the SR and FHIR give
    (``services.core.estimates``): here one PA film with landmarks on T1–T8 only, whose Cobb angles
    depend on levels no film shows (``cobb``), and no lateral film (kyphosis, lordosis); a curve of one
    segment has its apex named as the disc."""
    payload = spine_payload()
    payload.pop("lateral", None)
    payload["pa"]["landmarks"] = payload["pa"]["landmarks"][:8]
    result = register(payload)
    assert {"cobb", "kyphosis", "lordosis"} <= set(result["fit"]["unreliable"])
    seen = visit(Job(id=uuid.uuid4(), payload={"study": {"study_date": "2025-01-01"}}, result=result))
    assert seen.major_cobb is not None and seen.major_cobb.model_estimate is not None
    assert "fit.unreliable: cobb" in seen.major_cobb.model_estimate
    assert seen.kyphosis_t4_t12.model_estimate is not None and seen.lordosis_l1_l5.model_estimate is not None

    full = register(spine_payload())
    assert "cobb" not in full["fit"]["unreliable"]
    measured = visit(Job(id=uuid.uuid4(), payload={"study": {"study_date": "2025-01-01"}}, result=full))
    assert measured.major_cobb is not None and measured.major_cobb.model_estimate is None
    curve = next(c for c in full["measures"]["cobb"] if c["major"])
    disc = {**full, "measures": {**full["measures"], "cobb": [{**curve, "upper": "L4", "lower": "L5", "apex": "L4",
                                                               "apical_disc": True}]}}  # fmt: skip
    one_segment = visit(Job(id=uuid.uuid4(), payload={}, result=disc)).major_cobb
    assert one_segment is not None and one_segment.levels == "L4–L5, apex L4/L5 disc"


def test_follow_up_of_a_patient_by_study_date_restricted_to_the_caller(distributed_service: Service) -> None:
    svc = distributed_service
    patient = f"P-{uuid.uuid4().hex[:8]}"
    key_a = make_key(svc.settings, "follow-up-a")
    key_b = make_key(svc.settings, "follow-up-b")

    def submit(key: str, curve_mm: float, when: str | None) -> str:
        payload: dict[str, Any] = spine_payload(curve_mm=curve_mm)
        payload["study"] = {"study_instance_uid": f"1.2.826.0.1.3680043.8.498.{uuid.uuid4().int % 10**12}",
                            "patient_id": patient, **({"study_date": when} if when else {})}  # fmt: skip
        response = svc.client.post("/v1/jobs", json=payload, headers={"Authorization": f"Bearer {key}"})
        assert response.status_code == 202, response.text
        return str(response.json()["id"])

    # the caller's three visits, sent out of date order, one undated; another client's job of the same ID
    dated = {"2026-01-12": submit(key_a, 50.0, "2026-01-12"), "2025-01-10": submit(key_a, 20.0, "2025-01-10"),
             "2025-07-08": submit(key_a, 35.0, "2025-07-08")}  # fmt: skip
    undated = submit(key_a, 40.0, None)
    other = submit(key_b, 30.0, "2025-03-01")
    jobs = {j["id"]: j for j in svc.wait_all([*dated.values(), undated, other])}
    assert all(j["status"] == "succeeded" for j in jobs.values()), [j.get("error") for j in jobs.values()]

    def follow_up(key: str, pid: str = patient) -> dict[str, Any]:
        response = svc.client.get(
            f"/v1/patients/{quote(pid, safe='')}/measures", headers={"Authorization": f"Bearer {key}"}
        )
        assert response.status_code == 200, response.text
        body: dict[str, Any] = response.json()
        return body

    mine = follow_up(key_a)
    assert mine["patient_id"] == patient
    assert [v["job_id"] for v in mine["visits"]] == [*(dated[d] for d in sorted(dated)), undated]
    assert [v["study_date"] for v in mine["visits"]] == [*sorted(dated), None]
    for v in mine["visits"]:
        result = jobs[v["job_id"]]["result"]
        major = next(c for c in result["measures"]["cobb"] if c["major"])
        assert v["major_cobb"]["value_deg"] == major["angle_deg"]
        assert v["major_cobb"]["sd_deg"] == major["angle_sd_deg"]
        assert v["kyphosis_t4_t12"]["value_deg"] == result["measures"]["thoracic_kyphosis_t4_t12_deg"]
        assert v["lordosis_l1_l5"]["sd_deg"] == result["measures"]["lumbar_lordosis_l1_l5_sd_deg"]
        apex = next(x for x in result["vertebrae"] if x["level"] == major["apex"])
        assert v["apex_axial_rotation"]["sd_deg"] == apex["axial_rotation_sd_deg"]
    # changes between consecutive dated visits only, each flagged by the rule it states
    pairs = {(c["from_job"], c["to_job"]) for c in mine["changes"]}
    ordered = [dated[d] for d in sorted(dated)]
    assert pairs == {(ordered[0], ordered[1]), (ordered[1], ordered[2])}
    for c in mine["changes"]:
        sd = c["combined_sd_deg"]
        threshold = max(5.0, 1.96 * sd) if sd is not None else 5.0
        assert c["threshold_deg"] == pytest.approx(threshold)
        assert c["flagged"] == (abs(c["change_deg"]) > threshold)
        assert c["decided_by"] == ("combined_sd" if sd is not None and 1.96 * sd > 5.0 else "convention_5deg")
    assert {c["measure"] for c in mine["changes"]} <= set(MEASURES)
    major_changes = [c for c in mine["changes"] if c["measure"] == "major_cobb"]
    assert len(major_changes) == 2 and all(c["change_deg"] > 0 for c in major_changes)  # the curve grew 20 → 50 mm

    # the other client sees its own job only; an unknown patient is an empty follow-up; the admin sees all
    theirs = follow_up(key_b)
    assert [v["job_id"] for v in theirs["visits"]] == [other] and theirs["changes"] == []
    assert follow_up(key_a, f"P-{uuid.uuid4().hex[:8]}")["visits"] == []
    assert follow_up(key_a, "A/B 7")["patient_id"] == "A/B 7"  # a DICOM LO may hold "/" and spaces
    assert len(follow_up(svc.api_key)["visits"]) == 5


# ------------------------------------------------------------------ which jobs are the visits (both databases)


@pytest.fixture(scope="module")
def result() -> dict[str, Any]:
    """One engine result, stored as the result of every succeeded job below (the follow-up reads it)."""
    return register(spine_payload())


@pytest.fixture
def client(db_settings: Settings) -> Iterator[TestClient]:
    """The API alone on the database (no worker: the tests below mark their jobs succeeded), with the
    key of a client of its own (the PostgreSQL database is the session's, shared with other tests)."""
    with TestClient(create_app(db_settings)) as c:
        c.headers["Authorization"] = f"Bearer {make_key(db_settings, f'visits-{uuid.uuid4().hex[:8]}')}"
        yield c


def _study(patient: str, when: str | None, uid: str | None = None, **more: str) -> dict[str, Any]:
    uid = uid or f"1.2.826.0.1.3680043.8.498.{uuid.uuid4().int % 10**12}"
    return {"study_instance_uid": uid, "patient_id": patient, **({"study_date": when} if when else {}), **more}


def _succeeded(client: TestClient, settings: Settings, result: dict[str, Any], study: dict[str, Any] | None,
               created_s: float, finished_s: float, patient_column: str | None = None) -> str:  # fmt: skip
    """A job of ``study`` made through the API, then marked succeeded with ``result``, created and
    finished at these seconds after T0 (``patient_column``: the Patient ID the DICOM layer would have
    read from a header, for a payload without a study)."""
    payload = spine_payload()
    if study is not None:
        payload["study"] = study
    answer = client.post("/v1/jobs", json=payload)
    assert answer.status_code == 202, answer.text
    job_id = uuid.UUID(answer.json()["id"])
    extra = {"patient_id": patient_column} if patient_column is not None else {}
    with session_factory(settings)() as session:
        session.execute(update(Job).where(Job.id == job_id).values(
            status="succeeded", result=result, created_at=T0 + timedelta(seconds=created_s),
            started_at=T0 + timedelta(seconds=created_s), finished_at=T0 + timedelta(seconds=finished_s), **extra,
        ))  # fmt: skip
        session.commit()
    return str(job_id)


def _follow_up(client: TestClient, patient: str) -> dict[str, Any]:
    answer = client.get(f"/v1/patients/{quote(patient, safe='')}/measures")
    assert answer.status_code == 200, answer.text
    body: dict[str, Any] = answer.json()
    return body


@BACKENDS
def test_a_follow_up_keeps_the_newest_visits_and_says_older_ones_were_left_out(
    client: TestClient, db_settings: Settings, result: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Past MAX_PATIENT_JOBS succeeded jobs, the follow-up kept the oldest and said nothing: a clinician
    lost the latest visits. The limit is lowered to 3 for the test (the code reads it per request)."""
    patient = f"P-{uuid.uuid4().hex[:8]}"
    years = ["2021", "2022", "2023", "2024", "2025"]
    ids = [_succeeded(client, db_settings, result, _study(patient, f"{y}-03-01"), i, i + 0.5)
           for i, y in enumerate(years)]  # fmt: skip
    full = _follow_up(client, patient)
    assert [v["job_id"] for v in full["visits"]] == ids and full["older_visits_left_out"] is False
    monkeypatch.setattr(jobs_repo, "MAX_PATIENT_JOBS", 3)
    newest = _follow_up(client, patient)
    assert [v["job_id"] for v in newest["visits"]] == ids[-3:]  # the newest three, oldest first
    assert [v["study_date"] for v in newest["visits"]] == [f"{y}-03-01" for y in years[-3:]]
    assert newest["older_visits_left_out"] is True
    assert {c["from_job"] for c in newest["changes"]} | {c["to_job"] for c in newest["changes"]} == set(ids[-3:])
    monkeypatch.setattr(jobs_repo, "MAX_PATIENT_JOBS", 5)
    assert _follow_up(client, patient)["older_visits_left_out"] is False


@BACKENDS
def test_a_study_read_again_is_one_visit_its_latest_job(
    client: TestClient, db_settings: Settings, result: dict[str, Any]
) -> None:
    """Two succeeded jobs of one Study Instance UID (a film whose landmarks were corrected and sent
    again) were two visits and a change over 0 days; one visit per study, the job that finished last
    standing for it (then the one made last), and a job without a Study Instance UID a visit of its own."""
    patient = f"P-{uuid.uuid4().hex[:8]}"
    first, second = _study(patient, "2025-01-10"), _study(patient, "2025-07-08")
    _succeeded(client, db_settings, result, first, 0, 10)
    reread = _succeeded(client, db_settings, result, first, 1, 11)  # read again, finished last: it stands
    slow = _succeeded(client, db_settings, result, second, 2, 30)  # made first but finished last: it stands
    _succeeded(client, db_settings, result, second, 3, 12)
    tie = _study(patient, "2026-01-12")
    _succeeded(client, db_settings, result, tie, 4, 40)
    later = _succeeded(client, db_settings, result, tie, 5, 40)  # same finish: the one made last
    # no study in the payload: the Patient ID only in the column (as the DICOM layer fills it from a header)
    loose = [_succeeded(client, db_settings, result, None, 6 + i, 50, patient_column=patient) for i in range(2)]

    body = _follow_up(client, patient)
    assert [v["job_id"] for v in body["visits"]] == [reread, slow, later, *loose]
    assert [v["study_date"] for v in body["visits"]] == ["2025-01-10", "2025-07-08", "2026-01-12", None, None]
    majors = [(c["from_job"], c["to_job"], c["from_date"], c["to_date"])
              for c in body["changes"] if c["measure"] == "major_cobb"]  # fmt: skip
    assert majors == [(reread, slow, "2025-01-10", "2025-07-08"), (slow, later, "2025-07-08", "2026-01-12")]


@BACKENDS
def test_padding_spaces_do_not_make_another_patient(
    client: TestClient, db_settings: Settings, result: dict[str, Any]
) -> None:
    """DICOM LO and SH values' leading and trailing spaces are padding (PS3.5 §6.2): "P " was another
    patient than "P" in the DICOM filters and the follow-up. The payload keeps the text as sent."""
    patient = f"P-{uuid.uuid4().hex[:8]}"
    padded = _succeeded(client, db_settings, result, _study(f"{patient} ", "2025-01-10", accession_number=" A7 "), 0, 1)
    plain = _succeeded(client, db_settings, result, _study(patient, "2025-07-08", accession_number="A7"), 2, 3)
    assert client.get(f"/v1/jobs/{padded}").json()["study"]["patient_id"] == f"{patient} "
    for asked in (patient, f"{patient} ", f"  {patient}"):
        listed = {j["id"] for j in client.get("/v1/jobs", params={"patient_id": asked}).json()["jobs"]}
        assert listed == {padded, plain}, asked
        body = _follow_up(client, asked)
        assert body["patient_id"] == patient
        assert [v["job_id"] for v in body["visits"]] == [padded, plain]
    for asked in ("A7", "A7 "):
        listed = {j["id"] for j in client.get("/v1/jobs", params={"accession_number": asked}).json()["jobs"]}
        assert {padded, plain} <= listed, asked
