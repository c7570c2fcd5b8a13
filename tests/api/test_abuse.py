"""What an attacker or a careless integrator sends, and what the API must not answer nor log: problems
whose size grows with the faults of the body (``services.api.errors.field_problem``), the PACS's
credentials in the problem of a PACS that did not answer (``services.api.routes.pacs``), a Patient ID
in the logs (``services.api.errors.logged_path``)."""

from __future__ import annotations

import io
import json
import logging
import socket
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient

from services.api.app import create_app
from services.api.errors import MAX_ERRORS
from services.core.config import Settings
from services.core.logs import JsonFormatter
from services.db.migrate import upgrade
from tests.conftest import make_key, problem_of, spine_payload

EXTRA_MEMBERS = 500
"""Unknown members put in one payload: each is one ``extra_forbidden`` error, far more than MAX_ERRORS."""


def _with_unknown_members(n: int) -> dict[str, Any]:
    payload = spine_payload()
    payload.update({f"unknown_{i}": 0 for i in range(n)})
    return payload


def _assert_bounded(problem: dict[str, Any], total: int) -> None:
    assert len(problem["errors"]) == MAX_ERRORS, len(problem["errors"])
    assert problem["detail"].startswith(f"{total} fields failed validation, the first {MAX_ERRORS} listed"), problem


def test_a_job_with_many_faults_lists_the_first_ones_and_counts_them_all(api: TestClient) -> None:
    answer = api.post("/v1/jobs", json=_with_unknown_members(EXTRA_MEMBERS))
    assert answer.status_code == 422
    problem = problem_of(answer)
    _assert_bounded(problem, EXTRA_MEMBERS)
    assert {e["type"] for e in problem["errors"]} == {"extra_forbidden"}


def test_a_batch_entry_with_many_faults_lists_the_first_ones(api: TestClient) -> None:
    answer = api.post("/v1/jobs/batch", json={"jobs": [_with_unknown_members(EXTRA_MEMBERS)] * 3 + [spine_payload()]})
    assert answer.status_code == 200, answer.text
    body = answer.json()
    assert (body["accepted"], body["rejected"]) == (1, 3)
    for entry in body["results"][:3]:
        _assert_bounded(entry["problem"], EXTRA_MEMBERS)
        assert all(e["loc"][:2] == ["jobs", entry["index"]] for e in entry["problem"]["errors"])


def test_a_body_with_many_repeated_names_lists_the_first_ones(api: TestClient) -> None:
    members = ",".join(f'"k{i}": 0, "k{i}": 1' for i in range(EXTRA_MEMBERS))
    answer = api.post("/v1/jobs", content=f"{{{members}}}".encode(), headers={"Content-Type": "application/json"})
    assert answer.status_code == 422
    problem = problem_of(answer)
    _assert_bounded(problem, EXTRA_MEMBERS)
    assert {e["type"] for e in problem["errors"]} == {"duplicate_key"}


def test_a_few_faults_are_all_listed(api: TestClient) -> None:
    answer = api.post("/v1/jobs", json=_with_unknown_members(3))
    problem = problem_of(answer)
    assert len(problem["errors"]) == 3 and problem["detail"].startswith("3 fields failed validation: ")


# ------------------------------------------------------------------ the PACS's credentials

PACS_USER, PACS_PASSWORD, PACS_TOKEN = "pacs-user", "S3cret-pw", "query-token-9"


def _closed_port() -> int:
    """A loopback port nothing listens on (bound, then closed: connecting to it is refused)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])



def test_a_pacs_problem_never_shows_the_credentials_of_the_pacs_url(tmp_path: Path) -> None:
    """A PACS URL configured with ``user:password@`` (which the DICOMweb client sends as basic
    credentials) and a token in its query: a client browsing the PACS while it is down gets the 503
    problem naming the PACS, without either."""
    url = f"http://{PACS_USER}:{PACS_PASSWORD}@127.0.0.1:{_closed_port()}/dicom-web?apikey={PACS_TOKEN}"
    settings = Settings(data_dir=tmp_path, dicomweb_url=url, dicomweb_timeout_s=2, api_key_cache_s=0,
                        pacs_clients="clinic-a")  # fmt: skip
    upgrade(settings, quiet=True)
    with TestClient(create_app(settings)) as client:
        client.headers["Authorization"] = f"Bearer {make_key(settings, 'clinic-a')}"
        for path in ("/v1/pacs/studies/1.2.3/images", "/v1/pacs/studies/1.2.3/series/1.2.4/instances/1.2.5"):
            answer = client.get(path)
            assert answer.status_code == 503, answer.text
            problem = problem_of(answer)
            assert problem["type"].endswith("/dicomweb-unavailable")
            text = json.dumps(problem)
            assert PACS_PASSWORD not in text and PACS_USER not in text and PACS_TOKEN not in text, text
            assert "127.0.0.1" in problem["detail"]  # the PACS is still named, for the operator's diagnosis


# ------------------------------------------------------------------ a Patient ID in the logs

PATIENT_ID = "MRN-0042-LOGS"


def test_no_patient_id_in_the_logs(tmp_path: Path) -> None:
    """The follow-up's path holds a Patient ID: the access log (and an unexpected error's line) write
    the route's template instead, for an answered path and for one under it that names no route."""
    settings = Settings(data_dir=tmp_path, api_key_cache_s=0)
    upgrade(settings, quiet=True)
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(JsonFormatter())
    logger = logging.getLogger("services")
    logger.addHandler(handler)
    try:
        with TestClient(create_app(settings)) as client:
            client.headers["Authorization"] = f"Bearer {make_key(settings, 'clinic-a')}"
            for request_id, path, status in (("pid-1", f"/v1/patients/{PATIENT_ID}/measures", 200),
                                             ("pid-2", f"/v1/patients/{PATIENT_ID}", 404)):  # fmt: skip
                assert client.get(path, headers={"X-Request-ID": request_id}).status_code == status
    finally:
        logger.removeHandler(handler)
    lines = [json.loads(line) for line in stream.getvalue().splitlines()]
    access = {e["request_id"]: e["path"] for e in lines if e["logger"] == "services.access"}
    assert access == {"pid-1": "/v1/patients/{patient_id}/measures", "pid-2": "/v1/patients/{patient_id}"}
    assert PATIENT_ID not in stream.getvalue()
