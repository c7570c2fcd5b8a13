"""API keys, tenant isolation, audit trail, request ids, security headers, CORS, the queued cap,
`spine keys`, JSON logs: the real app in process on a fresh embedded database."""

from __future__ import annotations

import hashlib
import io
import json
import logging
import re
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from alembic.script import ScriptDirectory
from fastapi.testclient import TestClient
from sqlalchemy import select, text

from services.api.app import create_app
from services.cli.keys import ensure_first_key
from services.core.config import Settings
from services.core.logs import JsonFormatter
from services.core.problems import PROBLEM_BASE
from services.db.engine import session_factory
from services.db.keys import audit_trail, revoke
from services.db.migrate import alembic_config, upgrade
from services.db.models import ApiKey, Job
from tests.conftest import make_key, problem_of, spine_cli, spine_payload

KEY_LINE = re.compile(r"^spine_[0-9a-f]{12}_[A-Za-z0-9_-]{43}$")


class Tenants:
    def __init__(self, settings: Settings, client: TestClient):
        self.settings = settings
        self.client = client
        self.a = {"Authorization": f"Bearer {make_key(settings, 'clinic-a')}"}
        self.b = {"Authorization": f"Bearer {make_key(settings, 'clinic-b')}"}
        self.admin = {"Authorization": f"Bearer {make_key(settings, 'ops', 'admin')}"}


def _app(tmp_path: Path, database_url: str | None = None, **settings: Any) -> tuple[Settings, TestClient]:
    s = Settings(**{"data_dir": tmp_path, "api_key_cache_s": 0, "DATABASE_URL": database_url, **settings})
    upgrade(s, quiet=True)
    return s, TestClient(create_app(s))


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request: pytest.FixtureRequest) -> str | None:
    """None (the embedded SQLite) or a fresh PostgreSQL database: isolation, audit and the cap are
    checked on both."""
    if request.param == "postgresql":
        url: str = request.getfixturevalue("fresh_postgres_url")
        return url
    return None


@pytest.fixture
def tenants(tmp_path: Path, database_url: str | None) -> Iterator[Tenants]:
    settings, client = _app(tmp_path, database_url)
    with client:
        yield Tenants(settings, client)


def _v1_operations(client: TestClient) -> list[tuple[str, str]]:
    schema = client.get("/openapi.json").json()
    some_id = str(uuid.uuid4())
    return [(method.upper(), path.replace("{job_id}", some_id)) for path, item in schema["paths"].items()
            if path.startswith("/v1") for method in item]  # fmt: skip


def test_every_v1_operation_needs_a_key(tenants: Tenants) -> None:
    operations = _v1_operations(tenants.client)
    assert len(operations) >= 7
    for method, path in operations:
        for headers in ({}, {"Authorization": "Bearer nope"}, {"Authorization": "Basic Zm9vOmJhcg=="}):
            response = tenants.client.request(method, path, headers=headers, json={})
            assert response.status_code == 401, (method, path, headers)
            assert problem_of(response)["type"] == PROBLEM_BASE + "unauthorized"
            assert response.headers["www-authenticate"].startswith('Bearer realm="spine"')
    assert tenants.client.get("/v1/nothing-here").status_code == 401  # no route probing without a key


def test_health_metrics_and_the_page_stay_open(tenants: Tenants) -> None:
    for path in ("/healthz", "/readyz", "/metrics", "/", "/openapi.json"):
        assert tenants.client.get(path).status_code == 200, path
    html = tenants.client.get("/").text
    asset = re.search(r'src="(/assets/[^"]+\.js)"', html)
    assert asset and tenants.client.get(asset.group(1)).status_code == 200


def test_metrics_can_require_an_admin_key(tmp_path: Path) -> None:
    settings, client = _app(tmp_path, metrics_require_key=True)
    assert client.get("/metrics").status_code == 401
    client_key = {"Authorization": f"Bearer {make_key(settings)}"}
    assert problem_of(client.get("/metrics", headers=client_key))["type"] == PROBLEM_BASE + "forbidden"
    admin = {"Authorization": f"Bearer {make_key(settings, 'ops', 'admin')}"}
    assert client.get("/metrics", headers=admin).status_code == 200


def test_a_client_sees_and_cancels_only_its_own_jobs(tenants: Tenants) -> None:
    c = tenants.client
    job = c.post("/v1/jobs", json=spine_payload(), headers=tenants.a).json()
    assert job["owner"] == "clinic-a"
    unknown = str(uuid.uuid4())
    for method, suffix in (("GET", ""), ("POST", "/cancel"), ("GET", "/figure.png"), ("GET", "/figure.svg"),
                           ("GET", "/fhir")):  # fmt: skip
        theirs = c.request(method, f"/v1/jobs/{job['id']}{suffix}", headers=tenants.b)
        missing = c.request(method, f"/v1/jobs/{unknown}{suffix}", headers=tenants.b)
        assert theirs.status_code == missing.status_code == 404
        assert theirs.json() == json.loads(missing.text.replace(unknown, job["id"]))  # the very same answer
    assert c.get("/v1/jobs", headers=tenants.b).json()["jobs"] == []
    assert [j["id"] for j in c.get("/v1/jobs", headers=tenants.a).json()["jobs"]] == [job["id"]]
    assert c.get(f"/v1/jobs/{job['id']}", headers=tenants.a).json()["status"] == "queued"
    # the admin role sees and cancels every job; its own jobs have no owner
    mine = c.post("/v1/jobs", json=spine_payload(), headers=tenants.admin).json()
    assert mine["owner"] is None
    assert {j["id"] for j in c.get("/v1/jobs", headers=tenants.admin).json()["jobs"]} == {job["id"], mine["id"]}
    assert c.post(f"/v1/jobs/{job['id']}/cancel", headers=tenants.admin).json()["status"] == "cancelled"
    assert c.get("/v1/jobs", headers=tenants.a).json()["jobs"][0]["status"] == "cancelled"
    assert mine["id"] not in {j["id"] for j in c.get("/v1/jobs", headers=tenants.a).json()["jobs"]}


def test_idempotency_keys_are_per_client(tenants: Tenants) -> None:
    c = tenants.client
    a = c.post("/v1/jobs", json=spine_payload(), headers={**tenants.a, "Idempotency-Key": "scan-1"})
    b = c.post("/v1/jobs", json=spine_payload(curve_mm=30.0), headers={**tenants.b, "Idempotency-Key": "scan-1"})
    assert a.status_code == b.status_code == 202 and a.json()["id"] != b.json()["id"]
    again = c.post("/v1/jobs", json=spine_payload(), headers={**tenants.a, "Idempotency-Key": "scan-1"})
    assert again.json()["id"] == a.json()["id"] and again.headers["idempotent-replayed"] == "true"


def test_a_revoked_key_is_trusted_for_the_cache_window_then_refused(tmp_path: Path) -> None:
    """SPINE_API_KEY_CACHE_S: a verified key is trusted that long without a database read, so a key
    revoked meanwhile still passes inside the window and is refused after it (docs/security.md, "API keys")."""
    window_s = 1.5
    settings, client = _app(tmp_path, api_key_cache_s=window_s)
    headers = {"Authorization": f"Bearer {make_key(settings, 'clinic-w')}"}
    assert client.get("/v1/jobs", headers=headers).status_code == 200  # verified: cached from now
    cached_at = time.monotonic()
    with session_factory(settings)() as session:
        assert [k.name for k in revoke(session, "clinic-w")] == ["clinic-w"]
    inside = client.get("/v1/jobs", headers=headers).status_code
    assert time.monotonic() - cached_at < window_s  # (else this machine was too slow to say anything)
    assert inside == 200  # still trusted inside the window
    time.sleep(max(0.0, window_s - (time.monotonic() - cached_at)) + 0.1)
    assert client.get("/v1/jobs", headers=headers).status_code == 401  # refused once it has passed


def test_one_idempotency_key_raced_by_two_submissions_makes_one_job(tmp_path: Path, database_url: str | None) -> None:
    """Two POSTs with the same Idempotency-Key and body at the same moment (a client retrying while
    its first request is still in flight): one job, the same id in both answers, one of them a replay."""
    settings, app_client = _app(tmp_path, database_url)
    headers = {"Authorization": f"Bearer {make_key(settings, 'clinic-i')}"}
    for round_ in range(10):
        key = f"race-{round_}"
        barrier = threading.Barrier(2)
        answers: list[Any] = [None, None]

        def post(i: int, key: str = key, barrier: threading.Barrier = barrier, answers: list[Any] = answers) -> None:
            with TestClient(app_client.app) as client:  # its own connection and thread
                barrier.wait()
                answers[i] = client.post("/v1/jobs", json=spine_payload(), headers={**headers, "Idempotency-Key": key})

        threads = [threading.Thread(target=post, args=(i,)) for i in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        assert [a.status_code for a in answers] == [202, 202], [a.text for a in answers]
        assert answers[0].json()["id"] == answers[1].json()["id"]
        assert sorted(a.headers.get("idempotent-replayed", "false") for a in answers) == ["false", "true"]
    with session_factory(settings)() as session:
        stored = session.scalars(select(Job.idempotency_key).where(Job.owner == "clinic-i")).all()
    assert sorted(str(k) for k in stored) == sorted(f"race-{i}" for i in range(10))  # one job per key, no more


def test_a_revoked_key_is_refused(tmp_path: Path) -> None:
    settings, client = _app(tmp_path)
    key = make_key(settings, "clinic-r")
    headers = {"Authorization": f"Bearer {key}"}
    assert client.get("/v1/jobs", headers=headers).status_code == 200
    with session_factory(settings)() as session:
        assert [k.name for k in revoke(session, "clinic-r")] == ["clinic-r"]
    response = client.get("/v1/jobs", headers=headers)
    assert response.status_code == 401 and 'error="invalid_token"' in response.headers["www-authenticate"]


def test_keys_are_stored_as_digests_only(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path)
    upgrade(settings, quiet=True)
    key = make_key(settings, "clinic-h")
    with session_factory(settings)() as session:
        row = session.scalars(select(ApiKey).where(ApiKey.name == "clinic-h")).one()
    assert row.key_hash == hashlib.sha256(key.encode()).hexdigest()
    assert key.startswith(f"spine_{row.id}_") and KEY_LINE.match(key)
    assert key not in (tmp_path / "spine.db").read_bytes().decode("latin-1")


def test_the_audit_trail_records_who_did_what_in_which_request(tenants: Tenants) -> None:
    c = tenants.client
    created = c.post("/v1/jobs", json=spine_payload(), headers={**tenants.a, "X-Request-ID": "req-create-1"})
    job_id = created.json()["id"]
    assert created.headers["x-request-id"] == "req-create-1"
    c.get(f"/v1/jobs/{job_id}", headers={**tenants.a, "X-Request-ID": "req-read-1"})
    fhir = c.get(f"/v1/jobs/{job_id}/fhir", headers={**tenants.a, "X-Request-ID": "req-fhir-1"})
    assert fhir.status_code == 409  # still queued, but the read is audited like any other
    c.get("/v1/jobs", headers={**tenants.b, "X-Request-ID": "req-list-b"})  # sees nothing: no row
    c.get("/v1/jobs", headers={**tenants.admin, "X-Request-ID": "req-list-admin"})
    c.post(f"/v1/jobs/{job_id}/cancel", headers={**tenants.a, "X-Request-ID": "req-cancel-1"})
    bad = c.get(f"/v1/jobs/{job_id}", headers={**tenants.a, "X-Request-ID": "bad id with spaces"})
    assert re.fullmatch(r"[0-9a-f]{32}", bad.headers["x-request-id"])  # replaced by a generated one
    with session_factory(tenants.settings)() as session:
        trail = [(row.action, row.request_id) for row in audit_trail(session, uuid.UUID(job_id))]
        key_ids = {row.key_id for row in audit_trail(session, uuid.UUID(job_id))}
    assert trail == [("create", "req-create-1"), ("read", "req-read-1"), ("read", "req-fhir-1"),
                     ("list", "req-list-admin"),
                     ("cancel", "req-cancel-1"), ("read", bad.headers["x-request-id"])]  # fmt: skip
    assert len(key_ids) == 2  # clinic-a's key and the admin's


def test_security_headers_on_every_answer(tmp_path: Path) -> None:
    _, client = _app(tmp_path, hsts_max_age_s=31536000)
    key = make_key(client.app.state.settings)  # type: ignore[attr-defined]
    for path, headers in (("/v1/jobs", {"Authorization": f"Bearer {key}"}), ("/v1/jobs", {}), ("/healthz", {}),
                          ("/nowhere", {}), ("/", {})):  # fmt: skip
        response = client.get(path, headers=headers)
        h = response.headers
        assert h["x-content-type-options"] == "nosniff", path
        assert h["x-frame-options"] == "DENY" and h["referrer-policy"] == "no-referrer"
        assert "frame-ancestors 'none'" in h["content-security-policy"]
        assert h["strict-transport-security"] == "max-age=31536000; includeSubDomains"
        assert re.fullmatch(r"[0-9a-f]{32}", h["x-request-id"])
        if path.startswith("/v1"):
            assert h["cache-control"] == "no-store"
            assert h["content-security-policy"].startswith("default-src 'none'")
    page = client.get("/").headers["content-security-policy"]
    assert "script-src 'self'" in page and "connect-src 'self'" in page  # the page's own policy is kept


def test_no_hsts_by_default(tenants: Tenants) -> None:
    assert "strict-transport-security" not in tenants.client.get("/healthz").headers


def test_cors_is_off_unless_origins_are_configured(tmp_path: Path) -> None:
    preflight = {"Origin": "https://pacs.example", "Access-Control-Request-Method": "POST",
                 "Access-Control-Request-Headers": "authorization,content-type"}  # fmt: skip
    _, closed = _app(tmp_path / "closed")
    answer = closed.options("/v1/jobs", headers=preflight)
    assert "access-control-allow-origin" not in answer.headers
    assert "access-control-allow-origin" not in closed.get("/healthz", headers={"Origin": "https://pacs.example"}).headers
    settings, opened = _app(tmp_path / "open", cors_origins="https://pacs.example, https://viewer.example")
    answer = opened.options("/v1/jobs", headers=preflight)
    assert answer.status_code == 200 and answer.headers["access-control-allow-origin"] == "https://pacs.example"
    assert "authorization" in answer.headers["access-control-allow-headers"].lower()
    other = opened.options("/v1/jobs", headers={**preflight, "Origin": "https://evil.example"})
    assert other.status_code == 400 and "access-control-allow-origin" not in other.headers
    key = make_key(settings)
    simple = opened.get("/v1/jobs", headers={"Origin": "https://pacs.example", "Authorization": f"Bearer {key}"})
    assert simple.headers["access-control-allow-origin"] == "https://pacs.example"
    assert "x-request-id" in simple.headers["access-control-expose-headers"].lower()


def test_cors_lets_a_page_make_the_conditional_gets_of_the_artifacts(tmp_path: Path) -> None:
    """A page of an allowed origin may send ``If-None-Match`` (its preflight is answered yes) and read
    ``ETag`` (exposed): the conditional GET of an artifact (RFC 9110 §13.1.2) works across origins."""
    settings, opened = _app(tmp_path, cors_origins="https://viewer.example")
    origin = {"Origin": "https://viewer.example"}
    figure = f"/v1/jobs/{uuid.uuid4()}/figure.png"
    asks = {"Access-Control-Request-Method": "GET", "Access-Control-Request-Headers": "authorization,if-none-match"}
    preflight = opened.options(figure, headers={**origin, **asks})
    assert preflight.status_code == 200, preflight.text
    assert "if-none-match" in preflight.headers["access-control-allow-headers"].lower()
    answer = opened.get(figure, headers={**origin, "Authorization": f"Bearer {make_key(settings)}",
                                         "If-None-Match": '"figure-png-0"'})  # fmt: skip
    exposed = {h.strip().lower() for h in answer.headers["access-control-expose-headers"].split(",")}
    assert "etag" in exposed, exposed


def test_the_queued_cap_answers_429_with_retry_after(tmp_path: Path, database_url: str | None) -> None:
    settings, client = _app(tmp_path, database_url, max_queued_per_client=3)
    a = {"Authorization": f"Bearer {make_key(settings, 'clinic-a')}"}
    for _ in range(3):
        assert client.post("/v1/jobs", json=spine_payload(), headers=a).status_code == 202
    full = client.post("/v1/jobs", json=spine_payload(), headers=a)
    assert full.status_code == 429 and int(full.headers["retry-after"]) > 0
    assert problem_of(full)["type"] == PROBLEM_BASE + "too-many-queued-jobs"
    assert client.post("/v1/jobs/batch", json={"jobs": [spine_payload()]}, headers=a).status_code == 429
    b = {"Authorization": f"Bearer {make_key(settings, 'clinic-b')}"}  # another client has its own cap
    assert client.post("/v1/jobs/batch", json={"jobs": [spine_payload()] * 3}, headers=b).status_code == 200
    assert client.post("/v1/jobs/batch", json={"jobs": [spine_payload()] * 4}, headers=b).status_code == 429
    admin = {"Authorization": f"Bearer {make_key(settings, 'ops', 'admin')}"}
    assert client.post("/v1/jobs/batch", json={"jobs": [spine_payload()] * 5}, headers=admin).status_code == 200
    job = client.get("/v1/jobs", headers=a).json()["jobs"][0]
    client.post(f"/v1/jobs/{job['id']}/cancel", headers=a)
    assert client.post("/v1/jobs", json=spine_payload(), headers=a).status_code == 202  # counted at each request


def test_a_replay_at_the_queued_cap_is_answered_not_refused(tmp_path: Path, database_url: str | None) -> None:
    """A client at its cap that resends a request it already made (same Idempotency-Key, same body) gets
    its replay (it makes no job), on the single and the batch route; a new key is still a 429."""
    settings, client = _app(tmp_path, database_url, max_queued_per_client=2)
    a = {"Authorization": f"Bearer {make_key(settings, 'clinic-a')}"}
    payload = spine_payload()
    made = client.post("/v1/jobs", json=payload, headers={**a, "Idempotency-Key": "k1"})
    batch = client.post("/v1/jobs/batch", json={"jobs": [payload]}, headers={**a, "Idempotency-Key": "b1"})
    assert made.status_code == 202 and batch.status_code == 200 and batch.json()["accepted"] == 1
    for _ in range(2):
        again = client.post("/v1/jobs", json=payload, headers={**a, "Idempotency-Key": "k1"})
        assert again.status_code == 202, again.text
        assert again.json()["id"] == made.json()["id"] and again.headers["Idempotent-Replayed"] == "true"
        resent = client.post("/v1/jobs/batch", json={"jobs": [payload]}, headers={**a, "Idempotency-Key": "b1"})
        assert resent.status_code == 200, resent.text
        assert resent.json()["results"] == batch.json()["results"] and resent.headers["Idempotent-Replayed"] == "true"
        assert client.post("/v1/jobs", json=payload, headers={**a, "Idempotency-Key": "k2"}).status_code == 429
        full = client.post("/v1/jobs/batch", json={"jobs": [payload]}, headers={**a, "Idempotency-Key": "b2"})
        assert full.status_code == 429 and problem_of(full)["type"] == PROBLEM_BASE + "too-many-queued-jobs"
    assert len(client.get("/v1/jobs", headers=a).json()["jobs"]) == 2


def test_spine_keys_create_list_revoke(tmp_path: Path) -> None:
    created = spine_cli("keys", "create", "--name", "clinic-x", "--role", "client", data_dir=tmp_path)
    assert created.returncode == 0, created.stderr
    key = created.stdout.strip().splitlines()[-1]
    assert KEY_LINE.match(key), created.stdout
    key_id = key.split("_")[1]
    admin = spine_cli("keys", "create", "--name", "ops", "--role", "admin", data_dir=tmp_path)
    listed = spine_cli("keys", "list", data_dir=tmp_path)
    assert key_id in listed.stdout and "clinic-x" in listed.stdout and "admin" in listed.stdout
    assert key not in listed.stdout and admin.stdout.strip().splitlines()[-1] not in listed.stdout
    assert spine_cli("keys", "create", "--name", "bad name!", data_dir=tmp_path).returncode == 2
    by_id = spine_cli("keys", "revoke", key_id, data_dir=tmp_path)
    assert by_id.returncode == 0 and key_id in by_id.stdout
    assert spine_cli("keys", "revoke", key_id, data_dir=tmp_path).returncode == 1  # already revoked
    assert spine_cli("keys", "revoke", "ops", data_dir=tmp_path).returncode == 0  # by name
    settings = Settings(data_dir=tmp_path, api_key_cache_s=0)
    client = TestClient(create_app(settings))
    assert client.get("/v1/jobs", headers={"Authorization": f"Bearer {key}"}).status_code == 401


def test_the_first_start_creates_one_admin_key_and_prints_it_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    settings = Settings(data_dir=tmp_path, api_key_cache_s=0)
    upgrade(settings, quiet=True)
    ensure_first_key(settings)
    first = capsys.readouterr().out.strip().splitlines()
    assert KEY_LINE.match(first[-1]) and "admin" in first[0]
    ensure_first_key(settings)
    assert capsys.readouterr().out == ""
    client = TestClient(create_app(settings))
    assert client.get("/v1/jobs", headers={"Authorization": f"Bearer {first[-1]}"}).status_code == 200


def test_logs_are_json_lines_with_request_and_job_ids_and_no_payload(tmp_path: Path) -> None:
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(JsonFormatter())
    logger = logging.getLogger("services")
    logger.addHandler(handler)
    try:
        settings, client = _app(tmp_path)
        key = {"Authorization": f"Bearer {make_key(settings)}"}
        payload = spine_payload()
        job = client.post("/v1/jobs", json=payload, headers={**key, "X-Request-ID": "req-log-1"}).json()
        client.get(f"/v1/jobs/{job['id']}", headers={**key, "X-Request-ID": "req-log-2"})
        client.post("/v1/jobs", content=b"{oops", headers={**key, "content-type": "application/json"})
    finally:
        logger.removeHandler(handler)
    lines = [json.loads(line) for line in stream.getvalue().splitlines()]  # every line one JSON object
    access = [e for e in lines if e["logger"] == "services.access"]
    assert {"req-log-1", "req-log-2"} <= {e["request_id"] for e in access}
    created = next(e for e in access if e["request_id"] == "req-log-1")
    assert created["job_id"] == job["id"] and created["status"] == 202 and created["path"] == "/v1/jobs"
    assert "key_id" in created and "ts" in created and created["level"] == "INFO"
    text = stream.getvalue()
    assert "landmarks" not in text and "boundary" not in text and "oops" not in text


def test_an_unexpected_error_is_a_500_problem_with_every_header_and_a_logged_request_id(tmp_path: Path) -> None:
    """A route that raises (added here, not in the product): the 500 problem+json carries the
    request id, the security headers and CORS like every other answer, and its ERROR line the id."""
    settings, client = _app(tmp_path, cors_origins="https://pacs.example", hsts_max_age_s=600)

    def explode() -> None:
        raise RuntimeError("secret internals")

    client.app.add_api_route("/v1/explode", explode)  # type: ignore[attr-defined]
    client.app.add_api_route("/explode", explode)  # type: ignore[attr-defined]
    client = TestClient(client.app, raise_server_exceptions=False)
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(JsonFormatter())
    logger = logging.getLogger("services")
    logger.addHandler(handler)
    key = make_key(settings)
    try:
        for path, headers in (("/explode", {}), ("/v1/explode", {"Authorization": f"Bearer {key}"})):
            request_id = f"boom-{path.count('/')}"
            response = client.get(path, headers={**headers, "X-Request-ID": request_id, "Origin": "https://pacs.example"})
            assert response.status_code == 500, path
            problem = problem_of(response)
            assert problem["type"] == PROBLEM_BASE + "internal-error" and problem["instance"] == path
            assert "secret" not in response.text and "Traceback" not in response.text
            h = response.headers
            assert h["x-request-id"] == request_id
            assert h["x-content-type-options"] == "nosniff" and h["x-frame-options"] == "DENY"
            assert h["referrer-policy"] == "no-referrer" and h["cache-control"] == "no-store"
            assert h["content-security-policy"].startswith("default-src 'none'")
            assert h["strict-transport-security"] == "max-age=600; includeSubDomains"
            assert h["access-control-allow-origin"] == "https://pacs.example"
    finally:
        logger.removeHandler(handler)
    lines = [json.loads(line) for line in stream.getvalue().splitlines()]
    errors = [e for e in lines if e["level"] == "ERROR" and e["msg"].startswith("unhandled error")]
    assert [e.get("request_id") for e in errors] == ["boom-1", "boom-2"]
    assert all(e["exc_type"] == "RuntimeError" for e in errors)
    access = {e["request_id"]: e["status"] for e in lines if e["logger"] == "services.access"}
    assert access == {"boom-1": 500, "boom-2": 500}


def test_readyz_and_v1_on_a_database_not_migrated(tmp_path: Path, database_url: str | None) -> None:
    """Not migrated: /readyz is 503 naming the revision found and the one expected, and a /v1 request
    is a 503 problem saying to run `spine migrate` (not a 500); migrated, both answer."""
    settings = Settings(data_dir=tmp_path, api_key_cache_s=0, DATABASE_URL=database_url)
    client = TestClient(create_app(settings), raise_server_exceptions=False)
    ready = client.get("/readyz")
    assert ready.status_code == 503
    problem = problem_of(ready)
    assert problem["type"] == PROBLEM_BASE + "service-unavailable"
    assert "not migrated" in problem["detail"] and "spine migrate" in problem["detail"]
    scripts = ScriptDirectory.from_config(alembic_config(settings, quiet=True))
    head = scripts.get_current_head()
    previous = scripts.get_revision(head).down_revision
    assert head is not None and isinstance(previous, str)
    assert head in problem["checks"]["database"]  # the code's head, expected
    for path in ("/v1/jobs", "/v1/jobs/" + str(uuid.uuid4())):
        answer = client.get(path, headers={"Authorization": "Bearer spine_0123456789ab_" + "x" * 43})
        assert answer.status_code == 503, (path, answer.text)
        assert problem_of(answer)["detail"] == "the database schema is not migrated: run `spine migrate`"
        assert answer.headers["retry-after"] and answer.headers["x-request-id"]
    upgrade(settings, previous, quiet=True)  # one revision behind the code
    behind = problem_of(client.get("/readyz"))
    assert previous in behind["checks"]["database"] and head in behind["detail"]
    upgrade(settings, quiet=True)
    ready = client.get("/readyz")
    assert ready.status_code == 200 and ready.json()["checks"] == {"database": "ok", "broker": "ok"}
    assert client.get("/v1/jobs", headers={"Authorization": f"Bearer {make_key(settings)}"}).status_code == 200
    # a table gone under a route (the key is trusted from the cache): a 503, not a 500
    cached = Settings(data_dir=tmp_path, api_key_cache_s=60, DATABASE_URL=database_url)
    client = TestClient(create_app(cached), raise_server_exceptions=False)
    key = {"Authorization": f"Bearer {make_key(cached)}"}
    assert client.get("/v1/jobs", headers=key).status_code == 200
    with session_factory(cached)() as session:
        session.execute(text("DROP TABLE jobs CASCADE" if database_url else "DROP TABLE jobs"))
        session.commit()
    answer = client.get("/v1/jobs", headers=key)
    assert answer.status_code == 503 and "spine migrate" in problem_of(answer)["detail"]
