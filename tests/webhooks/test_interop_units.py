"""Webhook policy and signatures, the FHIR builder, the client's CSV tables, and the API's checks of
`study`, `callback_url` and batch Idempotency-Keys (in-process API on a fresh SQLite database)."""

from __future__ import annotations

import base64
import copy
import csv
import io
import re
import uuid
from collections.abc import Iterator
from datetime import UTC, date, datetime, timedelta
from email.utils import format_datetime
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError
from standardwebhooks import Webhook

from services.api.app import create_app
from services.core.config import Settings
from services.core.webhook_policy import (
    WebhooksDisabled,
    allow_list,
    decode_secret,
    destination_problem,
    parse_allow_list,
)
from services.db.deliveries import message_id
from services.db.migrate import upgrade
from services.dicom.sr import PRIVATE_SCHEME_VERSION, PrivateCodes
from services.fhir.export import (
    COBB_ANGLE,
    LOCAL_CODE_SYSTEM,
    LOCAL_CODE_SYSTEM_VERSION,
    LOCAL_CODES,
    effective_date_time,
    observation_bundle,
)
from services.webhooks.delivery import retry_delay
from services.webhooks.signing import signed_headers
from spine_client import tables
from spine_client.client import retry_after_seconds
from spine_engine import register
from tests.conftest import problem_of, spine_payload
from tests.interop_helpers import api_key_for

SECRET = "whsec_" + base64.b64encode(b"0123456789abcdef0123456789abcdef").decode()


@pytest.fixture(scope="module")
def result() -> dict[str, Any]:
    out: dict[str, Any] = register(spine_payload(curve_mm=30.0))
    return out


# ------------------------------------------------------------------ webhook destinations


ALLOWED = "https://ris.hospital.example/hooks/, http://127.0.0.1:9000/cb"


@pytest.mark.parametrize(
    "url",
    [
        "https://ris.hospital.example/hooks/spine",
        "https://RIS.hospital.example:443/hooks/a/b?job=1",
        "https://ris.hospital.example/hooks",
        "http://127.0.0.1:9000/cb",
        "http://127.0.0.1:9000/cb/x",
        "http://127.0.0.1:9000/cb/x;v=1/y",  # parameters on an ordinary segment
        "http://127.0.0.1:9000/cb/..x/y...",  # dots that are not a dot segment
    ],
)
def test_allowed_destinations(url: str) -> None:
    assert destination_problem(url, allow_list(ALLOWED)) is None


@pytest.mark.parametrize(
    ("url", "why"),
    [
        ("https://ris.hospital.example.evil.org/hooks/x", "matches none"),
        ("https://ris.hospital.example/hooksx", "matches none"),
        ("https://ris.hospital.example/other", "matches none"),
        ("http://ris.hospital.example/hooks/x", "matches none"),
        ("https://ris.hospital.example:8443/hooks/x", "matches none"),
        ("http://127.0.0.1:9001/cb", "matches none"),
        ("http://2130706433:9000/cb", "matches none"),
        ("http://localhost:9000/cb", "matches none"),
        ("https://admin:secret@ris.hospital.example/hooks/x", "credentials"),
        ("https://@ris.hospital.example/hooks/x", "credentials"),
        ("https://ris.hospital.example/hooks/../admin", "dot segments"),
        ("https://ris.hospital.example/hooks/%2E%2E/admin", "dot segments"),
        ("https://ris.hospital.example/hooks/..%2fadmin", "dot segments"),
        ("https://ris.hospital.example/hooks/..;/admin", "read it as '..'"),  # Tomcat, Spring: '..'
        ("https://ris.hospital.example/hooks/..;jsessionid=1/admin", "even with parameters"),
        ("https://ris.hospital.example/hooks/.;x/admin", "even with parameters"),
        ("https://ris.hospital.example/hooks/%252e%252e/admin", "encoded '%' (%25)"),  # double-encoded '..'
        ("https://ris.hospital.example/hooks/x%252fadmin", "encoded '%' (%25)"),
        ("ftp://ris.hospital.example/hooks/x", "scheme"),
        ("file:///etc/passwd", "scheme"),
        ("gopher://127.0.0.1:9000/cb", "scheme"),
        ("https:///hooks", "no host"),
        ("https://ris.hospital.example/hooks/a b", "spaces"),
        ("http://127.0.0.1:99999/cb", "parse"),
    ],
)
def test_refused_destinations(url: str, why: str) -> None:
    reason = destination_problem(url, allow_list(ALLOWED))
    assert reason is not None and why in reason


def test_an_empty_allow_list_disables_webhooks() -> None:
    with pytest.raises(WebhooksDisabled):
        destination_problem("https://ris.hospital.example/hooks/x", allow_list(""))


@pytest.mark.parametrize("entry", ["ftp://h/x", "https://u:p@h/", "https://h/x?q=1", "https://h/a/../b", "h/x"])
def test_bad_allow_list_entries_stop_the_service(entry: str) -> None:
    with pytest.raises(ValueError, match="SPINE_WEBHOOK_ALLOWED_URLS"):
        parse_allow_list(entry)
    with pytest.raises(ValidationError):
        Settings(webhook_allowed_urls=entry)


# ------------------------------------------------------------------ signatures and retries


def test_signatures_verify_with_the_standard_webhooks_reference() -> None:
    key = decode_secret(SECRET)
    body = b'{"type":"job.succeeded","data":{"id":"x"}}'
    now = int(datetime.now(UTC).timestamp())
    headers = signed_headers(key, "msg_1", now, body)
    assert headers["webhook-signature"].startswith("v1,")
    assert Webhook(SECRET).verify(body, headers) == {"type": "job.succeeded", "data": {"id": "x"}}
    with pytest.raises(Exception, match="signature"):
        Webhook(SECRET).verify(body + b" ", headers)
    assert decode_secret(SECRET.removeprefix("whsec_")) == key
    for bad in ("whsec_short", "whsec_not base64!", ""):
        with pytest.raises(ValueError):
            decode_secret(bad)
    with pytest.raises(ValidationError):
        Settings(webhook_secret="whsec_c2hvcnQ=")


def test_message_ids_are_stable_per_job_and_outcome() -> None:
    job = uuid.uuid4()
    assert message_id(job, "succeeded") == message_id(str(job), "succeeded") != message_id(job, "cancelled")


def test_backoff_doubles_honours_retry_after_and_is_capped() -> None:
    settings = Settings(webhook_retry_base_s=2.0)
    assert [retry_delay(settings, n) for n in (1, 2, 3)] == [2.0, 4.0, 8.0]
    assert retry_delay(settings, 1, "30") == 30.0
    assert retry_delay(settings, 1, "100000") == 120.0
    assert retry_delay(settings, 20) == 120.0
    later = format_datetime(datetime.now(UTC) + timedelta(seconds=60), usegmt=True)
    assert 50 < retry_delay(settings, 1, later) <= 60
    assert retry_after_seconds("7") == 7.0 and retry_after_seconds("soon") is None
    assert 50 < (retry_after_seconds(later) or 0) <= 60


# ------------------------------------------------------------------ FHIR builder


def test_fhir_bundle_without_study_and_with_model_estimates(result: dict[str, Any]) -> None:
    from fhir.resources.R4B.bundle import Bundle

    estimated = copy.deepcopy(result)
    estimated["fit"]["unreliable"] = ["kyphosis", "axial_rotation"]
    job_id = uuid.uuid4()
    bundle = observation_bundle(job_id, estimated, finished_at=datetime.now(UTC))
    Bundle.model_validate(bundle)
    assert bundle["id"] == str(job_id) and bundle["identifier"]["value"] == f"urn:uuid:{job_id}"
    obs = {e["resource"]["code"]["text"]: e["resource"] for e in bundle["entry"]}
    assert all("derivedFrom" not in o for o in obs.values())
    kyphosis = obs["Thoracic kyphosis T4–T12 (sagittal Cobb angle)"]
    assert any("Model estimate" in n["text"] for n in kyphosis["note"])
    lordosis = obs["Lumbar lordosis L1–L5 (sagittal Cobb angle)"]
    assert not any("Model estimate" in n["text"] for n in lordosis["note"])
    rotation = obs["Apical vertebral axial rotation of the major curve"]
    assert any("Model estimate" in n["text"] for n in rotation["note"])
    cobb = [o for text, o in obs.items() if text.startswith("Cobb angle, frontal plane")]
    assert cobb and not any("interpretation" in o for o in cobb)
    estimated["fit"]["unreliable"] = ["cobb"]  # the PA film's landmarks short of a level
    flagged = observation_bundle(job_id, estimated, finished_at=datetime.now(UTC))
    Bundle.model_validate(flagged)
    marked = {e["resource"]["code"]["text"] for e in flagged["entry"] if "interpretation" in e["resource"]}
    assert marked - {"Apical vertebral axial rotation of the major curve"} == {
        text for text in obs if text.startswith("Cobb angle, frontal plane")}  # fmt: skip
    ids = [e["resource"]["id"] for e in bundle["entry"]]
    again = observation_bundle(job_id, estimated, finished_at=datetime.now(UTC))
    assert [e["resource"]["id"] for e in again["entry"]] == ids and len(set(ids)) == len(ids)  # stable


def test_fhir_bundle_without_curves_has_no_cobb_or_apical_rotation(result: dict[str, Any]) -> None:
    straight = copy.deepcopy(result)
    straight["measures"]["cobb"] = []
    bundle = observation_bundle(uuid.uuid4(), straight, finished_at=datetime.now(UTC))
    texts = [e["resource"]["code"]["text"] for e in bundle["entry"]]
    assert len(texts) == 3 and not any("Cobb angle, frontal" in t or "Apical" in t for t in texts)


def test_fhir_bundle_of_a_spine_below_the_threshold_has_its_largest_cobb_angle() -> None:
    """No curve of 10°: one SNOMED "Cobb angle" Observation of ``largest_cobb`` (value, SD, ends, a
    note saying it is below the threshold), and no apical rotation."""
    mild = register(spine_payload(curve_mm=1.5))
    largest = mild["measures"]["largest_cobb"]
    bundle = observation_bundle(uuid.uuid4(), mild, finished_at=datetime.now(UTC))
    cobb = [e["resource"] for e in bundle["entry"] if e["resource"]["code"]["coding"][0]["code"] == "285285000"]
    assert len(cobb) == 1
    obs = cobb[0]
    assert obs["valueQuantity"]["value"] == pytest.approx(largest["angle_deg"], abs=0.005)  # to 0.01°
    parts = {c["code"]["text"]: c for c in obs["component"]}
    assert parts["Upper end vertebra"]["valueString"] == largest["upper"]
    assert parts["Lower end vertebra"]["valueString"] == largest["lower"]
    assert any("No frontal curve of 10°" in n["text"] for n in obs["note"])
    assert not any("Apical" in e["resource"]["code"]["text"] for e in bundle["entry"])


def test_fhir_observations_are_coded_and_keep_their_text(result: dict[str, Any]) -> None:
    """The frontal Cobb angles carry SNOMED CT 285285000 (PS3.16 CID 7550, as the SR); the sagittal
    angles, the apical rotation and the curves' components carry the local code system's codes; every
    code keeps its text."""
    from fhir.resources.R4B.bundle import Bundle

    bundle = observation_bundle(uuid.uuid4(), result, finished_at=datetime.now(UTC))
    Bundle.model_validate(bundle)
    codes = {e["resource"]["code"]["text"]: e["resource"]["code"]["coding"] for e in bundle["entry"]}
    cobb = [c for t, c in codes.items() if t.startswith("Cobb angle, frontal plane")]
    assert cobb and all(c == [COBB_ANGLE] for c in cobb)
    assert COBB_ANGLE == {"system": "http://snomed.info/sct", "code": "285285000", "display": "Cobb angle"}
    local = {t: c[0]["code"] for t, c in codes.items() if c[0]["system"] == LOCAL_CODE_SYSTEM}
    assert local == {
        "Thoracic kyphosis T4–T12 (sagittal Cobb angle)": "KYPH-T4-T12",
        "Thoracic kyphosis T5–T12 (sagittal Cobb angle)": "KYPH-T5-T12",
        "Lumbar lordosis L1–L5 (sagittal Cobb angle)": "LORD-L1-L5",
        "Apical vertebral axial rotation of the major curve": "APEX-AXROT",
    }
    major = next(e["resource"] for e in bundle["entry"] if e["resource"]["code"]["text"].endswith("major curve"))
    coded = {c["code"]["coding"][0]["code"] for c in major["component"] if "coding" in c["code"]}
    assert {"CONVEXITY", "MAJOR-CURVE", "APEX-AXROT", "PMC-ORIENT", "PMC-COBB"} <= coded
    assert all(c["code"]["text"] for c in major["component"])


def test_fhir_local_codes_are_the_srs_private_codes() -> None:
    """One meaning, one code value, in DICOM (99SPINE) and in FHIR (``LOCAL_CODE_SYSTEM``)."""
    sr_codes = {c.value: c.meaning for c in vars(PrivateCodes).values() if hasattr(c, "scheme_designator")}
    assert {code: sr_codes.get(code) for code in LOCAL_CODES} == LOCAL_CODES
    assert LOCAL_CODE_SYSTEM_VERSION == PRIVATE_SCHEME_VERSION
    uuid_urn = r"urn:uuid:[0-9a-f]{8}-[0-9a-f]{4}-5[0-9a-f]{3}-[89ab][0-9a-f]{3}-[0-9a-f]{12}"  # RFC 9562 version 5
    assert re.fullmatch(uuid_urn, LOCAL_CODE_SYSTEM)


def test_fhir_subject_has_the_configured_system_and_every_observation_a_time(result: dict[str, Any]) -> None:
    from fhir.resources.R4B.bundle import Bundle

    created = datetime(2026, 12, 1, 8, 0, 5, tzinfo=UTC)
    finished = created + timedelta(seconds=3)
    study = {"study_instance_uid": "1.2.3", "patient_id": "P-17", "patient_name": "Doe^Jane",
             "study_date": "2026-11-30"}  # fmt: skip
    bundle = observation_bundle(uuid.uuid4(), result, finished_at=finished, created_at=created, study=study,
                                patient_id_system="urn:oid:1.2.3.4.5")  # fmt: skip
    Bundle.model_validate(bundle)
    for entry in bundle["entry"]:
        obs = entry["resource"]
        assert obs["subject"]["identifier"] == {"system": "urn:oid:1.2.3.4.5", "value": "P-17"}
        assert obs["subject"]["display"] == "Jane Doe" and obs["effectiveDateTime"] == "2026-11-30"
    # no study, no patient: no subject, and the job's creation as the effective time
    bare = observation_bundle(uuid.uuid4(), result, finished_at=finished, created_at=created)
    Bundle.model_validate(bare)
    effective = {e["resource"]["effectiveDateTime"] for e in bare["entry"]}
    assert effective == {"2026-12-01T08:00:05Z"}  # the job's creation, in UTC as fhir.resources writes it
    assert all("subject" not in e["resource"] for e in bare["entry"])
    # a patient without a configured system: the identifier alone
    unsystematic = observation_bundle(uuid.uuid4(), result, finished_at=finished, study=study)
    assert unsystematic["entry"][0]["resource"]["subject"]["identifier"] == {"value": "P-17"}


@pytest.mark.parametrize(
    ("study", "film", "expected"),
    [
        ({"study_date": "2026-11-30"}, None, "2026-11-30"),
        # a time is written only with its zone (FHIR R4 dateTime), else the date alone
        ({"study_date": "2026-11-30", "study_time": "101500"}, None, "2026-11-30"),
        ({"study_date": "2026-11-30", "study_time": "101500.25", "timezone_offset_from_utc": "+0100"}, None,
         "2026-11-30T10:15:00.25+01:00"),
        ({"study_date": "2026-11-30", "study_time": "0915", "timezone_offset_from_utc": "-0500"}, None,
         "2026-11-30T09:15:00-05:00"),
        ({"study_instance_uid": "1.2.3"}, datetime(2026, 11, 29, 7, 45, tzinfo=UTC), "2026-11-29T07:45:00+00:00"),
        (None, datetime(2026, 11, 29, 7, 45), "2026-11-29"),
        (None, date(2026, 11, 28), "2026-11-28"),
        (None, None, "2026-12-01T08:00:05+00:00"),
    ],
)  # fmt: skip
def test_fhir_effective_time_is_the_studys_else_the_films_else_the_jobs(
    study: dict[str, Any] | None, film: datetime | date | None, expected: str
) -> None:
    from fhir.resources.R4B.observation import Observation

    created = datetime(2026, 12, 1, 8, 0, 5, tzinfo=UTC)
    value = effective_date_time(study, film, created)
    assert value == expected
    Observation.model_validate({"resourceType": "Observation", "status": "final", "code": {"text": "x"},
                                "effectiveDateTime": value})  # fmt: skip


# ------------------------------------------------------------------ CSV tables


def test_vertebrae_and_measures_csv(result: dict[str, Any]) -> None:
    rows = list(csv.DictReader(io.StringIO(tables.vertebrae_csv(result))))
    assert list(rows[0]) == tables.VERTEBRA_COLUMNS and len(rows) == 17
    v3 = result["vertebrae"][3]
    assert float(rows[3]["frontal_bending_deg"]) == pytest.approx(v3["frontal_bending_deg"])
    assert float(rows[3]["sagittal_bending_deg"]) == pytest.approx(v3["sagittal_bending_deg"])
    # the contract's deprecated aliases stay as the last columns, with the same values, until it removes them
    assert tables.VERTEBRA_COLUMNS[-2:] == ["pa_bending_deg", "lateral_bending_deg"]
    assert (rows[3]["pa_bending_deg"], rows[3]["lateral_bending_deg"]) == (
        rows[3]["sagittal_bending_deg"], rows[3]["frontal_bending_deg"])  # fmt: skip
    assert float(rows[3]["u2_rad_per_mm"]) == pytest.approx(result["vertebrae"][3]["u"][1])
    assert rows[16]["level"] == "L5" and rows[16]["v3"] == ""
    measures = list(csv.DictReader(io.StringIO(tables.measures_csv(result))))
    assert list(measures[0]) == tables.MEASURE_COLUMNS
    cobb = [m for m in measures if m["measure"] == "cobb_angle"]
    assert len(cobb) == len(result["measures"]["cobb"]) and {m["major"] for m in cobb} <= {"true", "false"}
    assert measures[-2]["measure"] == "mean_registration_error" and measures[-2]["unit"] == "mm"
    misfit = measures[-1]  # the fit's last row: how far its landmarks lie against their stated SD
    assert misfit["measure"] == "landmark_misfit_ratio" and misfit["unit"] == "1"
    assert float(misfit["value"]) == pytest.approx(result["fit"]["landmark_misfit_ratio"])


def test_the_measures_csv_of_a_spine_below_the_threshold_has_its_largest_angle(result: dict[str, Any]) -> None:
    """No curve of 10°: one ``largest_cobb_angle`` row (the page's "Largest frontal angle") with its SD
    and ends; a curved spine's measures have none (its major curve is the largest angle)."""
    mild = register(spine_payload(curve_mm=1.5))
    largest = mild["measures"]["largest_cobb"]
    rows = [r for r in csv.DictReader(io.StringIO(tables.measures_csv(mild))) if r["measure"] == "largest_cobb_angle"]
    assert len(rows) == 1
    assert float(rows[0]["value"]) == pytest.approx(largest["angle_deg"])
    assert float(rows[0]["sd"]) == pytest.approx(largest["angle_sd_deg"])
    assert (rows[0]["upper"], rows[0]["lower"]) == (largest["upper"], largest["lower"])
    assert "largest_cobb_angle" not in {r["measure"] for r in csv.DictReader(io.StringIO(tables.measures_csv(result)))}


def test_csvs_carry_the_sds_and_the_model_estimate_marks_as_the_page_does(result: dict[str, Any]) -> None:
    """The columns and meanings of the page's CSVs (web/src/csv.ts, web/src/results.ts): SDs from the
    result, and the model-estimate mark on what ``fit.unreliable`` names."""
    measured = list(csv.DictReader(io.StringIO(tables.vertebrae_csv(result))))
    v3 = result["vertebrae"][3]
    assert [float(measured[3][f"position_sd_{a}_mm"]) for a in "xyz"] == pytest.approx(v3["position_sd_mm"])
    assert float(measured[3]["axial_rotation_sd_deg"]) == pytest.approx(v3["axial_rotation_sd_deg"])
    # T1 and L5 given, one PA film without pedicles: the sagittal measures, whose SDs are a large part
    # of the population's, and the axial rotations (the population's) are model estimates
    # (fit.unreliable); the rest is measured
    assert set(result["fit"]["unreliable"]) - {"kyphosis", "lordosis"} == {"axial_rotation"}
    assert {r["model_estimate"] for r in measured} <= {
        "axial_rotation_deg", "axial_rotation_deg;sagittal_bending_deg;pa_bending_deg"}  # fmt: skip
    rows = {r["measure"]: r for r in csv.DictReader(io.StringIO(tables.measures_csv(result)))}
    assert float(rows["thoracic_kyphosis_t4_t12"]["sd"]) == pytest.approx(
        result["measures"]["thoracic_kyphosis_t4_t12_sd_deg"])  # fmt: skip
    assert float(rows["cobb_angle"]["sd"]) == pytest.approx(result["measures"]["cobb"][-1]["angle_sd_deg"])
    assert rows["mean_registration_error"]["sd"] == "" and rows["cobb_angle"]["model_estimate"] == ""

    estimated = copy.deepcopy(result)
    estimated["fit"]["unreliable"] = ["depth", "kyphosis", "axial_rotation", "twist"]
    marks = {r["model_estimate"] for r in csv.DictReader(io.StringIO(tables.vertebrae_csv(estimated)))}
    assert marks == {"y_mm;sagittal_bending_deg;pa_bending_deg;axial_rotation_deg;u3_rad_per_mm;twist_deg"}
    rows = {r["measure"]: r for r in csv.DictReader(io.StringIO(tables.measures_csv(estimated)))}
    marked = {name for name, r in rows.items() if r["model_estimate"] == "model estimate"}
    assert marked == {"thoracic_kyphosis_t4_t12", "thoracic_kyphosis_t5_t12", "apex_axial_rotation"}
    estimated["fit"]["unreliable"] = ["cobb"]
    rows = {r["measure"]: r for r in csv.DictReader(io.StringIO(tables.measures_csv(estimated)))}
    assert {name for name, r in rows.items() if r["model_estimate"] == "model estimate"} == {"cobb_angle"}
    # the frontal tilts the Cobb angles are read from are the prior's too (docs/measures.md: `cobb`)
    marks = {r["model_estimate"] for r in csv.DictReader(io.StringIO(tables.vertebrae_csv(estimated)))}
    assert marks == {"frontal_tilt_deg"}


# ------------------------------------------------------------------ API checks


@pytest.fixture
def hooks_api(tmp_path: Path) -> Iterator[TestClient]:
    """The API (no worker) with webhooks allowed to http://127.0.0.1:9/hooks."""
    settings = Settings(data_dir=tmp_path, webhook_allowed_urls="http://127.0.0.1:9/hooks", webhook_secret=SECRET)
    upgrade(settings, quiet=True)
    with TestClient(create_app(settings)) as client:
        key = api_key_for(settings, "units")
        if key:
            client.headers["Authorization"] = f"Bearer {key}"
        yield client


def test_study_is_validated_and_carried_unchanged(api: TestClient) -> None:
    payload = spine_payload()
    payload["study"] = {"study_instance_uid": "1.2.3", "series_instance_uid": "1..2", "lateral_sop_instance_uid": "x",
                        "pa_sop_instance_uid": "1" * 65, "modality": "DX"}  # fmt: skip
    problem = problem_of(api.post("/v1/jobs", json=payload))
    assert {e["path"] for e in problem["errors"]} == {
        "study.series_instance_uid", "study.lateral_sop_instance_uid", "study.pa_sop_instance_uid", "study.modality",
    }  # fmt: skip
    payload["study"] = {"study_instance_uid": "1.2.840.10008.1.2", "pa_sop_instance_uid": "0.1." + "9" * 60}
    job = api.post("/v1/jobs", json=payload).json()
    assert job["study"] == payload["study"]
    assert api.get(f"/v1/jobs/{job['id']}").json()["study"] == payload["study"]
    assert api.post("/v1/jobs", json=spine_payload()).json()["study"] is None


def test_callback_url_is_refused_while_webhooks_are_off(api: TestClient) -> None:
    payload = spine_payload()
    payload["callback_url"] = "https://ris.hospital.example/hooks"
    problem = problem_of(api.post("/v1/jobs", json=payload))
    assert problem["status"] == 422
    assert [(e["path"], e["type"]) for e in problem["errors"]] == [("callback_url", "webhooks_disabled")]
    batch = api.post("/v1/jobs/batch", json={"jobs": [spine_payload(), payload]}).json()
    assert (batch["accepted"], batch["rejected"]) == (1, 1)
    assert batch["results"][1]["problem"]["errors"][0]["path"] == "jobs[1].callback_url"


def test_callback_url_accepted_when_allowed(hooks_api: TestClient) -> None:
    payload = spine_payload()
    payload["callback_url"] = "http://127.0.0.1:9/hooks/spine"
    job = hooks_api.post("/v1/jobs", json=payload)
    assert job.status_code == 202, job.text
    read = hooks_api.get(f"/v1/jobs/{job.json()['id']}").json()
    assert read["deliveries"] == [] and read["payload"]["callback_url"] == payload["callback_url"]
    payload["callback_url"] = "http://127.0.0.1:9/other"
    problem = problem_of(hooks_api.post("/v1/jobs", json=payload))
    assert [(e["path"], e["type"]) for e in problem["errors"]] == [("callback_url", "callback_url_not_allowed")]
    assert "127.0.0.1:9/hooks" not in problem["detail"]  # the allow-list is not told to clients


def test_batch_with_an_idempotency_key_replays(api: TestClient) -> None:
    payloads: list[Any] = [spine_payload(curve_mm=5.0 + i) for i in range(3)]
    payloads.insert(1, {"pa": {}})
    first = api.post("/v1/jobs/batch", json={"jobs": payloads}, headers={"Idempotency-Key": "run-1"})
    again = api.post("/v1/jobs/batch", json={"jobs": payloads}, headers={"Idempotency-Key": "run-1"})
    assert first.status_code == again.status_code == 200
    assert "idempotent-replayed" not in first.headers and again.headers["idempotent-replayed"] == "true"
    ids = [e.get("job", {}).get("id") for e in first.json()["results"]]
    assert [e.get("job", {}).get("id") for e in again.json()["results"]] == ids and ids[1] is None
    assert (again.json()["accepted"], again.json()["rejected"]) == (3, 1)
    changed = copy.deepcopy(payloads)
    changed[2] = spine_payload(curve_mm=40.0)
    mixed = api.post("/v1/jobs/batch", json={"jobs": changed}, headers={"Idempotency-Key": "run-1"}).json()
    assert mixed["results"][2]["status"] == 409
    assert mixed["results"][2]["problem"]["type"].endswith("/idempotency-conflict")
    assert [mixed["results"][i]["job"]["id"] for i in (0, 3)] == [ids[0], ids[3]]
    listed = api.get("/v1/jobs", params={"limit": 500}).json()["jobs"]
    assert len(listed) == 3  # one job per payload, however often the batch was sent
    too_long = api.post("/v1/jobs/batch", json={"jobs": payloads}, headers={"Idempotency-Key": "k" * 241})
    assert too_long.status_code == 422


def test_fhir_of_unknown_or_unfinished_jobs(api: TestClient) -> None:
    assert problem_of(api.get(f"/v1/jobs/{uuid.uuid4()}/fhir"))["status"] == 404
    job = api.post("/v1/jobs", json=spine_payload()).json()
    problem = problem_of(api.get(f"/v1/jobs/{job['id']}/fhir"))
    assert problem["status"] == 409 and problem["type"].endswith("/job-has-no-result")
    assert problem["job_status"] == "queued"


def test_fhir_observations_carry_the_results_sd(result: dict[str, Any]) -> None:
    """Each measure with an SD in the result has it as a component in degrees (every number
    with its trust), equal to the result's value."""
    sds = copy.deepcopy(result)
    sds["measures"]["thoracic_kyphosis_t4_t12_sd_deg"] = 2.5
    sds["measures"]["thoracic_kyphosis_t5_t12_sd_deg"] = None
    for curve in sds["measures"]["cobb"]:
        curve["angle_sd_deg"] = 1.25
    bundle = observation_bundle(uuid.uuid4(), sds, finished_at=datetime.now(UTC))
    found: dict[str, float] = {}
    for entry in bundle["entry"]:
        obs = entry["resource"]
        for component in obs.get("component", []):
            if component["code"]["text"].startswith("Standard deviation"):
                assert component["valueQuantity"]["unit"] == obs["valueQuantity"]["unit"]
                found[obs["code"]["text"]] = component["valueQuantity"]["value"]
    assert found["Thoracic kyphosis T4–T12 (sagittal Cobb angle)"] == 2.5
    cobb = [v for k, v in found.items() if k.startswith("Cobb angle")]
    assert cobb and all(v == 1.25 for v in cobb)
    assert "Thoracic kyphosis T5–T12 (sagittal Cobb angle)" not in found  # no SD in the result: none invented


def test_the_fhir_route_takes_the_pa_films_date_time_else_the_laterals() -> None:
    """``routes.fhir.film_datetime``: what the header read recorded in the job's ``dicom`` block."""
    from services.api.routes.fhir import film_datetime

    assert film_datetime(None) is None and film_datetime({"pa": {"film_datetime": None}}) is None
    both = {"pa": {"film_datetime": "2026-11-15"}, "lateral": {"film_datetime": "2026-11-16"}}
    assert film_datetime(both) == "2026-11-15"
    assert film_datetime({"lateral": {"film_datetime": "2026-11-16"}}) == "2026-11-16"
