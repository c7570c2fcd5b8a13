"""The job API on the embedded default (SQLite, no worker): validation, problems, reads, cancel."""

from __future__ import annotations

import base64
import json
import re
import uuid
from datetime import UTC, datetime
from typing import Any

import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from services.core.config import Settings
from services.core.problems import PROBLEM_BASE, PROBLEM_MEDIA_TYPE
from services.db.migrate import upgrade
from services.db.models import iso_utc
from tests.conftest import make_key, problem_of, spine_payload


def test_submit_answers_202_with_location_and_a_queued_job(api: TestClient, payload: dict[str, Any]) -> None:
    response = api.post("/v1/jobs", json=payload)
    assert response.status_code == 202
    job = response.json()
    assert response.headers["location"] == f"/v1/jobs/{job['id']}"
    assert job["status"] == "queued" and job["attempts"] == 0 and job["owner"] == "test-client"
    assert job["result"] is None and job["error"] is None
    read = api.get(response.headers["location"]).json()
    assert read["payload"] == payload
    assert read["created_at"] == job["created_at"]


def test_validation_problem_lists_every_field_with_its_json_path(api: TestClient, payload: dict[str, Any]) -> None:
    payload["pa"]["landmarks"][3]["level"] = "T13"
    payload["pa"]["landmarks"][5]["point"] = [1.0, "x"]
    del payload["boundary"]["L5"]
    payload["colour"] = "blue"
    response = api.post("/v1/jobs", json=payload)
    assert response.status_code == 422
    problem = problem_of(response)
    assert problem["type"] == PROBLEM_BASE + "validation-error"
    assert problem["instance"] == "/v1/jobs"
    paths = {e["path"] for e in problem["errors"]}
    assert paths == {"pa.landmarks[3].level", "pa.landmarks[5].point[1]", "boundary.L5", "colour"}
    assert all(e["msg"] and e["type"] for e in problem["errors"])
    assert api.get("/v1/jobs").json()["jobs"] == []  # nothing stored


def test_a_number_sent_as_a_string_or_a_boolean_is_a_422_naming_it(api: TestClient, payload: dict[str, Any]) -> None:
    """The contract says number (``spine_engine.models.Number``): ``"100.0"`` and ``true`` are refused with the
    member's JSON path (pydantic's lax mode would have read them as 100.0 and 1.0), a JSON integer is taken;
    in a batch, per entry."""
    payload["pa"]["landmarks"][0]["point"][0] = str(payload["pa"]["landmarks"][0]["point"][0])
    payload["pa"]["landmark_sd_mm"] = True
    payload["boundary"]["L5"]["position"][2] = str(payload["boundary"]["L5"]["position"][2])
    response = api.post("/v1/jobs", json=payload)
    assert response.status_code == 422, response.text
    problem = problem_of(response)
    assert problem["type"] == PROBLEM_BASE + "validation-error"
    found = [(e["path"], e["type"]) for e in problem["errors"]]
    assert found == [("pa.landmarks[0].point[0]", "float_type"), ("pa.landmark_sd_mm", "float_type"),
                     ("boundary.L5.position[2]", "float_type")]  # fmt: skip
    assert all(e["msg"].startswith("a number is expected") for e in problem["errors"])
    assert "pa.landmarks[0].point[0]" in problem["detail"]
    assert api.get("/v1/jobs").json()["jobs"] == []  # nothing stored
    fixed = json.loads(json.dumps(payload))
    fixed["pa"]["landmarks"][0]["point"][0] = 100  # a JSON integer: a number
    fixed["pa"]["landmark_sd_mm"] = 1
    fixed["boundary"]["L5"]["position"][2] = -420
    batch = api.post("/v1/jobs/batch", json={"jobs": [payload, fixed]}).json()
    assert [entry["status"] for entry in batch["results"]] == [422, 202]
    assert batch["results"][0]["problem"]["errors"][0]["path"] == "jobs[0].pa.landmarks[0].point[0]"


def test_cross_field_validation_names_the_field(api: TestClient, payload: dict[str, Any]) -> None:
    payload["pa"]["landmarks"] = payload["pa"]["landmarks"][:1]  # one level: below the PA's minimum of two
    problem = problem_of(api.post("/v1/jobs", json=payload))
    assert [e["path"] for e in problem["errors"]] == ["pa.landmarks"]


def test_malformed_json_is_a_400_problem(api: TestClient) -> None:
    response = api.post("/v1/jobs", content=b'{"pa": [1, 2', headers={"content-type": "application/json"})
    assert response.status_code == 400
    problem = problem_of(response)
    assert problem["type"] == PROBLEM_BASE + "malformed-json"
    assert problem["errors"][0]["path"] == "" and "line 1" in problem["errors"][0]["msg"]


@pytest.mark.parametrize("content_type", ["text/plain", "application/x-www-form-urlencoded", None])
def test_wrong_content_type_is_a_415_problem(api: TestClient, content_type: str | None, payload: Any) -> None:
    headers = {"content-type": content_type} if content_type else {}
    response = api.post("/v1/jobs", content=json.dumps(payload).encode(), headers=headers)
    assert response.status_code == 415
    assert problem_of(response)["type"] == PROBLEM_BASE + "unsupported-media-type"


def test_a_dicom_body_is_a_415_that_says_how_to_send_a_film(api: TestClient) -> None:
    """A radiograph posted as the job (a PACS integrator's first try): refused, with the two ways that work."""
    from services.dicom.dicomweb import part10
    from tools.dicom import synthetic

    film = part10(synthetic.radiograph(rows=64, columns=48, imager_pixel_spacing=(0.2, 0.2)))
    response = api.post("/v1/jobs", content=film, headers={"content-type": "application/dicom"})
    assert response.status_code == 415
    detail = problem_of(response)["detail"]
    assert "study.pa_sop_instance_uid" in detail and "spine submit --pa-dicom" in detail
    assert api.get("/v1/jobs").json()["jobs"] == []  # nothing stored


def test_problem_json_content_type_is_accepted(api: TestClient, payload: Any) -> None:
    response = api.post(
        "/v1/jobs", content=json.dumps(payload), headers={"content-type": "application/json; charset=utf-8"}
    )
    assert response.status_code == 202


def test_body_over_one_mebibyte_is_a_413_problem(api: TestClient, payload: dict[str, Any]) -> None:
    payload["padding"] = "x" * (1024 * 1024)
    response = api.post("/v1/jobs", json=payload)
    assert response.status_code == 413
    assert problem_of(response)["type"] == PROBLEM_BASE + "payload-too-large"

    def chunks() -> Any:  # no Content-Length: the limit holds while streaming too
        for _ in range(20):
            yield b" " * 65536
        yield b"{}"

    response = api.post("/v1/jobs", content=chunks(), headers={"content-type": "application/json"})
    assert response.status_code == 413


def test_idempotency_key_same_body_same_job_other_body_409(api: TestClient, payload: dict[str, Any]) -> None:
    first = api.post("/v1/jobs", json=payload, headers={"Idempotency-Key": "scan-42"})
    reordered = json.loads(json.dumps(payload, sort_keys=True))  # same body, other key order
    again = api.post("/v1/jobs", json=reordered, headers={"Idempotency-Key": "scan-42"})
    assert first.status_code == again.status_code == 202
    assert first.json()["id"] == again.json()["id"]
    assert again.headers["idempotent-replayed"] == "true"
    other = spine_payload(curve_mm=25.0)
    conflict = api.post("/v1/jobs", json=other, headers={"Idempotency-Key": "scan-42"})
    assert conflict.status_code == 409
    problem = problem_of(conflict)
    assert problem["type"] == PROBLEM_BASE + "idempotency-conflict"
    assert problem["job"] == f"/v1/jobs/{first.json()['id']}"
    fresh = api.post("/v1/jobs", json=other, headers={"Idempotency-Key": "scan-43"})
    assert fresh.status_code == 202 and fresh.json()["id"] != first.json()["id"]
    assert len(api.get("/v1/jobs").json()["jobs"]) == 2


def test_batch_validates_each_payload_on_its_own(api: TestClient, payload: dict[str, Any]) -> None:
    bad = spine_payload()
    bad["boundary"]["T1"]["directors"][0] = [2.0, 0.0, 0.0]
    response = api.post("/v1/jobs/batch", json={"jobs": [payload, bad, {"nope": 1}, payload]})
    assert response.status_code == 200
    body = response.json()
    assert body["accepted"] == 2 and body["rejected"] == 2
    assert [e["index"] for e in body["results"]] == [0, 1, 2, 3]
    assert [e["status"] for e in body["results"]] == [202, 422, 422, 202]
    assert body["results"][0]["job"]["status"] == "queued"
    assert [e["path"] for e in body["results"][1]["problem"]["errors"]] == ["jobs[1].boundary.T1.directors"]
    paths = {e["path"] for e in body["results"][2]["problem"]["errors"]}
    assert {"jobs[2].pa", "jobs[2].nope"} <= paths
    ids = {e["job"]["id"] for e in body["results"] if "job" in e}
    assert ids == {j["id"] for j in api.get("/v1/jobs").json()["jobs"]}


def test_batch_limits(api: TestClient, payload: dict[str, Any]) -> None:
    too_many = api.post("/v1/jobs/batch", json={"jobs": [payload] * 1001})
    assert too_many.status_code == 413
    assert problem_of(too_many)["type"] == PROBLEM_BASE + "payload-too-large"
    not_a_list = api.post("/v1/jobs/batch", json=[payload])
    assert not_a_list.status_code == 422
    assert problem_of(not_a_list)["errors"][0]["path"] == "jobs"
    full = api.post("/v1/jobs/batch", json={"jobs": [payload] * 1000})
    assert full.status_code == 200 and full.json()["accepted"] == 1000


def test_list_newest_first_with_filters_and_cursor(api: TestClient, payload: dict[str, Any]) -> None:
    ids = [api.post("/v1/jobs", json=payload).json()["id"] for _ in range(7)]
    cancelled = ids[2]
    assert api.post(f"/v1/jobs/{cancelled}/cancel").status_code == 200
    seen: list[str] = []
    cursor = None
    while True:
        params: dict[str, Any] = {"limit": 3}
        if cursor:
            params["cursor"] = cursor
        page = api.get("/v1/jobs", params=params).json()
        seen += [j["id"] for j in page["jobs"]]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == ids[::-1]
    queued = api.get("/v1/jobs", params={"status": "queued"}).json()["jobs"]
    assert [j["id"] for j in queued] == [i for i in ids[::-1] if i != cancelled]
    both = api.get("/v1/jobs", params=[("status", "queued"), ("status", "cancelled")]).json()["jobs"]
    assert len(both) == 7
    created = api.get(f"/v1/jobs/{ids[3]}").json()["created_at"]
    after = api.get("/v1/jobs", params={"created_after": created}).json()["jobs"]
    assert [j["id"] for j in after] == ids[3:][::-1]
    before = api.get("/v1/jobs", params={"created_before": created}).json()["jobs"]
    assert [j["id"] for j in before] == ids[:3][::-1]


def _cursor(created: str) -> str:
    """A cursor as ``jobs.encode_cursor`` writes one, for a job created at ``created``."""
    return base64.urlsafe_b64encode(f"{created}|{uuid.uuid4()}".encode()).decode().rstrip("=")


def test_list_rejects_bad_parameters_as_problems(api: TestClient) -> None:
    for params, path in [
        ({"status": "done"}, "query.status[0]"),
        ({"limit": 0}, "query.limit"),
        ({"created_after": "yesterday"}, "query.created_after"),
        ({"cursor": "!!!"}, "query.cursor"),
        ({"created_after": "0001-01-01T00:00:00+14:00"}, "query.created_after"),  # year 0 in UTC
        ({"created_before": "9999-12-31T23:59:59-14:00"}, "query.created_before"),  # year 10000 in UTC
        ({"cursor": _cursor("0001-01-01T00:00:00+14:00")}, "query.cursor"),  # a forged one, year 0 in UTC
    ]:
        response = api.get("/v1/jobs", params=params)
        assert response.status_code == 422, params
        assert [e["path"] for e in problem_of(response)["errors"]] == [path]
    assert api.get("/v1/jobs", params={"created_after": "0001-01-01T00:00:00-01:00"}).status_code == 200


def test_cancel_queued_job_and_cancel_again(api: TestClient, payload: dict[str, Any]) -> None:
    job = api.post("/v1/jobs", json=payload).json()
    first = api.post(f"/v1/jobs/{job['id']}/cancel")
    assert first.status_code == 200 and first.json()["status"] == "cancelled"
    assert first.json()["finished_at"] is not None
    again = api.post(f"/v1/jobs/{job['id']}/cancel")
    assert again.status_code == 200 and again.json()["finished_at"] == first.json()["finished_at"]


def test_unknown_job_and_unknown_route_are_404_problems(api: TestClient) -> None:
    """Each its own problem type (RFC 9457 §3.1.1: the type identifies the problem): an unknown route
    had the type of an unknown job, so a client could not tell a typo in its URL from a job gone."""
    missing = uuid.uuid4()
    for response in (api.get(f"/v1/jobs/{missing}"), api.post(f"/v1/jobs/{missing}/cancel")):
        assert response.status_code == 404
        assert problem_of(response)["type"] == PROBLEM_BASE + "not-found"
        assert problem_of(response)["detail"] == f"there is no job {missing}"
    for path in ("/v2/x", "/v1/job", f"/v1/jobs/{missing}/nothing", "/assets/no-such-file.js"):
        response = api.get(path)
        assert response.status_code == 404, path
        problem = problem_of(response)
        assert problem["type"] == PROBLEM_BASE + "route-not-found" and problem["instance"] == path
        assert problem["title"] == "Nothing is served at this path" and path in problem["detail"]
    malformed = api.get("/v1/jobs/not-a-uuid")
    assert malformed.status_code == 422
    assert problem_of(malformed)["errors"][0]["path"] == "path.job_id"
    assert "payload" not in problem_of(malformed)["title"]  # a path, not a payload, broke the contract
    wrong_method = api.delete("/v1/jobs")
    assert wrong_method.status_code == 405
    assert problem_of(wrong_method)["type"] == PROBLEM_BASE + "method-not-allowed"


@pytest.mark.parametrize(
    ("method", "path", "allow"),
    [
        ("DELETE", "/v1/jobs", "GET, HEAD, POST"),  # HEAD wherever GET is (security.HeadAsGet)
        ("PUT", "/v1/jobs/{id}", "GET, HEAD"),
        ("DELETE", "/v1/jobs/{id}/cancel", "POST"),
        ("HEAD", "/v1/jobs/{id}/cancel", "POST"),  # HEAD is not answered where GET is not
        ("POST", "/v1/jobs/{id}/fhir", "GET, HEAD"),
        ("GET", "/v1/jobs/batch", "POST"),  # not the job route's GET of a job id "batch"
        ("HEAD", "/v1/jobs/batch", "POST"),
        ("TRACE", "/v1/jobs/batch", "POST"),
        ("POST", "/healthz", "GET, HEAD"),
        ("POST", "/v1/pacs", "GET, HEAD"),
        ("POST", "/", "GET, HEAD"),  # the page
        ("POST", "/assets/any.js", "GET, HEAD"),  # a mount of static files
    ],
)
def test_a_405_lists_the_methods_the_resource_has(api: TestClient, method: str, path: str, allow: str) -> None:
    """RFC 9110 §15.5.6: a 405 carries ``Allow`` with the target resource's methods (the routes of
    included routers and mounts too, and not a method the path only refuses)."""
    response = api.request(method, path.replace("{id}", str(uuid.uuid4())))
    assert response.status_code == 405, response.text
    assert response.headers["allow"] == allow
    if method == "HEAD":  # GET's answer without its content
        assert response.content == b"" and response.headers["content-type"] == PROBLEM_MEDIA_TYPE
        return
    assert problem_of(response)["type"] == PROBLEM_BASE + "method-not-allowed"


def test_a_key_given_twice_is_a_422_naming_it(api: TestClient, payload: dict[str, Any]) -> None:
    """RFC 8259 §4: a receiver's reading of repeated names is unpredictable (Python's json keeps the
    last): the body is refused, each repeated key named by its JSON path, not read one way."""
    text = json.dumps(payload)
    twice = text.replace('"pa": {', '"pa": {"units": "px", "units": "mm", ', 1)
    response = api.post("/v1/jobs", content=twice, headers={"Content-Type": "application/json"})
    assert response.status_code == 422
    problem = problem_of(response)
    assert problem["type"] == PROBLEM_BASE + "validation-error"
    assert [(e["path"], e["loc"], e["type"]) for e in problem["errors"]] == [("pa.units", ["pa", "units"],
                                                                               "duplicate_key")]  # fmt: skip
    assert "'units' is given 2 times" in problem["errors"][0]["msg"] and "pa.units" in problem["detail"]
    # in a batch, every repeated key of every entry, deep ones included; nothing is stored
    entry = json.dumps(payload).replace('"level": "T4"', '"level": "T4", "level": "T5"', 1)
    batch = '{"jobs": [' + ", ".join((json.dumps(payload), twice, entry)) + ']}'
    before = len(api.get("/v1/jobs").json()["jobs"])
    answer = api.post("/v1/jobs/batch", content=batch, headers={"Content-Type": "application/json"})
    assert answer.status_code == 422
    paths = [e["path"] for e in problem_of(answer)["errors"]]
    assert paths == ["jobs[1].pa.units", "jobs[2].pa.landmarks[3].level"]
    assert len(api.get("/v1/jobs").json()["jobs"]) == before
    # the same body without the repetition is a job
    assert api.post("/v1/jobs", content=text, headers={"Content-Type": "application/json"}).status_code == 202


def test_unexpected_error_is_a_500_problem_without_traceback(api: TestClient) -> None:
    def explode() -> None:
        raise RuntimeError("secret internals")

    api.app.add_api_route("/explode", explode)  # type: ignore[attr-defined]
    client = TestClient(api.app, raise_server_exceptions=False)
    response = client.get("/explode")
    assert response.status_code == 500
    problem = problem_of(response)
    assert problem["type"] == PROBLEM_BASE + "internal-error"
    assert "secret" not in response.text and "Traceback" not in response.text


def test_health_ready_and_metrics(api: TestClient, payload: dict[str, Any]) -> None:
    assert api.get("/healthz").json()["status"] == "ok"
    ready = api.get("/readyz")
    assert ready.status_code == 200 and ready.json()["checks"] == {"database": "ok", "broker": "ok"}
    api.post("/v1/jobs", json=payload)
    api.post("/v1/jobs", json=payload)
    metrics = api.get("/metrics")
    assert metrics.status_code == 200 and metrics.headers["content-type"].startswith("text/plain")
    text = metrics.text
    assert 'spine_jobs{status="queued"} 2.0' in text
    assert "spine_queue_depth 2.0" in text
    assert 'spine_fit_duration_seconds{quantile="0.99"}' in text
    assert 'spine_job_duration_seconds{quantile="0.5"}' in text
    assert 'spine_http_requests_total{method="POST",route="/v1/jobs",status="202"} 2.0' in text


def test_readyz_is_503_when_the_broker_or_database_is_unreachable(tmp_path: Any, payload: Any) -> None:
    settings = Settings(data_dir=tmp_path, CELERY_BROKER_URL="redis://127.0.0.1:9/0")
    upgrade(settings, quiet=True)
    client = TestClient(create_app(settings), headers={"Authorization": f"Bearer {make_key(settings)}"})
    response = client.get("/readyz")
    assert response.status_code == 503
    problem = problem_of(response)
    assert problem["type"] == PROBLEM_BASE + "service-unavailable"
    assert problem["checks"]["database"] == "ok" and problem["checks"]["broker"] != "ok"
    # the job is stored even though it cannot be published now: the reconciler will publish it
    assert client.post("/v1/jobs", json=payload).status_code == 202

    down = Settings(data_dir=tmp_path, DATABASE_URL="postgresql+psycopg://nobody@127.0.0.1:9/none")
    well_formed = "spine_0123456789ab_" + "x" * 43  # its lookup needs the database, which is down
    client = TestClient(create_app(down), raise_server_exceptions=False,
                        headers={"Authorization": f"Bearer {well_formed}"})  # fmt: skip
    response = client.get("/readyz")
    assert response.status_code == 503 and problem_of(response)["checks"]["database"] != "ok"
    submit = client.post("/v1/jobs", json=payload)
    assert submit.status_code == 503
    assert problem_of(submit)["type"] == PROBLEM_BASE + "service-unavailable"


TIMESTAMP = re.compile(r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{6}Z$")


def test_every_job_view_writes_timestamps_in_one_format(api: TestClient, payload: dict[str, Any]) -> None:
    """created/started/finished in the POST answer, the job, the list, the batch and the cancel answer:
    UTC with microseconds and Z, whatever the microseconds (a whole second too)."""
    posted = api.post("/v1/jobs", json=payload).json()
    batch = api.post("/v1/jobs/batch", json={"jobs": [payload]}).json()["results"][0]["job"]
    cancelled = api.post(f"/v1/jobs/{posted['id']}/cancel").json()
    read = api.get(f"/v1/jobs/{posted['id']}").json()
    listed = api.get("/v1/jobs").json()["jobs"]
    stamps = [posted["created_at"], batch["created_at"], cancelled["created_at"], cancelled["finished_at"],
              read["created_at"], read["finished_at"], *(j["created_at"] for j in listed)]  # fmt: skip
    assert all(TIMESTAMP.match(s) for s in stamps), stamps
    assert iso_utc(datetime(2026, 12, 1, 17, 0, 0, tzinfo=UTC)) == "2026-12-01T17:00:00.000000Z"


def test_an_unknown_profile_is_refused_at_the_door(api: TestClient, payload: dict[str, Any]) -> None:
    """It used to pass the API and fail the job in the worker; the problem names the field and the
    profiles there are."""
    payload["options"] = {"profile": "defualt"}
    response = api.post("/v1/jobs", json=payload)
    assert response.status_code == 422
    errors = problem_of(response)["errors"]
    assert [(e["path"], e["type"]) for e in errors] == [("options.profile", "unknown_profile")]
    assert "'default'" in errors[0]["msg"]
    assert api.get("/v1/jobs").json()["jobs"] == []
