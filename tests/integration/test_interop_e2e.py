"""The Python client, the `spine` client commands, the FHIR export and webhooks against a real running
service: `spine serve` (API and a real Celery worker, embedded default) on a free port of 127.0.0.1,
a webhook receiver and a lossy proxy started here on 127.0.0.1, and an API without worker for jobs
that must stay queued. Nothing is mocked."""

from __future__ import annotations

import base64
import contextlib
import csv
import io
import json
import os
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from standardwebhooks import Webhook

from services.core.jobqueue import make_celery
from services.db import jobs as jobs_repo
from services.db.deliveries import job_ended, message_id
from services.db.engine import session_scope
from services.fhir.export import LOCAL_CODE_SYSTEM
from spine_client import (
    IdempotencyConflict,
    InvalidRequest,
    JobFailed,
    JobHasNoResult,
    NotFound,
    ServerError,
    ServiceUnreachable,
    SpineClient,
    WaitTimeout,
)
from spine_client import cli as client_cli
from spine_client.models import RegistrationResult
from tests.conftest import _postgres_database, _purge_queue, engine_refused_payload, spine_payload
from tests.interop_helpers import ApiOnly, FlakyProxy, Receiver, Rule, Served, free_port, wait_until

pytestmark = pytest.mark.integration

SECRET = "whsec_" + base64.b64encode(b"interop-test-signing-key-0123456789").decode()
STUDY = {
    "study_instance_uid": "1.2.826.0.1.3680043.8.498.1",
    "series_instance_uid": "1.2.826.0.1.3680043.8.498.2",
    "pa_sop_instance_uid": "1.2.826.0.1.3680043.8.498.3",
}


@pytest.fixture(scope="module")
def receiver() -> Iterator[Receiver]:
    r = Receiver()
    yield r
    r.close()


@pytest.fixture(scope="module", params=["embedded", "distributed"])
def served(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory,
           receiver: Receiver) -> Iterator[Served]:  # fmt: skip
    """`spine serve` on the embedded default, then on PostgreSQL + Redis: the client, webhook and FHIR
    tests run on both."""
    env = {
        "SPINE_WEBHOOK_ALLOWED_URLS": receiver.url("/hooks"),
        "SPINE_WEBHOOK_SECRET": SECRET,
        "SPINE_WEBHOOK_RETRY_BASE_S": "0.2",
        "SPINE_WEBHOOK_MAX_ATTEMPTS": "3",
        "SPINE_RECONCILE_INTERVAL_S": "1",
        "SPINE_WEBHOOK_SWEEP_AFTER_S": "0.5",
    }
    with contextlib.ExitStack() as stack:
        if request.param == "distributed":
            redis_url: str = request.getfixturevalue("redis_url")
            queue = f"spine-interop-{uuid.uuid4().hex[:8]}"
            env.update(DATABASE_URL=stack.enter_context(_postgres_database("interop")), CELERY_BROKER_URL=redis_url,
                       SPINE_QUEUE_NAME=queue, SPINE_SERVE_WORKER="true")  # fmt: skip
            stack.callback(_purge_queue, redis_url, queue)
        service = Served(tmp_path_factory.mktemp(f"interop-{request.param}"), **env)
        stack.callback(service.stop)
        yield service


@pytest.fixture(scope="module")
def api_only(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiOnly]:
    service = ApiOnly(tmp_path_factory.mktemp("api-only"))
    yield service
    service.stop()


@pytest.fixture
def client(served: Served) -> Iterator[SpineClient]:
    with SpineClient(served.url, served.api_key, backoff=0.05) as c:
        yield c


def run_cli(served: Served | ApiOnly, *args: str, **env: str) -> subprocess.CompletedProcess[str]:
    """`spine <args>` as a script runs it: a subprocess, with SPINE_URL / SPINE_API_KEY in its environment."""
    full = {k: v for k, v in os.environ.items() if k not in ("SPINE_URL", "SPINE_API_KEY")}
    full["SPINE_URL"] = served.url
    if served.api_key:
        full["SPINE_API_KEY"] = served.api_key
    full.update(env)
    return subprocess.run([sys.executable, "-m", "services.cli", *args], capture_output=True, text=True, env=full,
                          timeout=120)  # fmt: skip


def cli(service: Served | ApiOnly, capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """The same commands in process (faster): exit code, stdout, stderr."""
    capsys.readouterr()
    key = ["--api-key", service.api_key] if service.api_key else []
    code = client_cli.main([*args, "--url", service.url, *key])
    out, err = capsys.readouterr()
    return code, out, err


# ------------------------------------------------------------------ client


def test_client_submits_waits_and_reads_typed_results(client: SpineClient) -> None:
    payload = spine_payload(curve_mm=25.0)
    payload["study"] = STUDY
    job = client.submit(payload)
    assert job.status == "queued" and job.study is not None and job.study.model_dump(exclude_none=True) == STUDY
    done = client.wait(job.id, timeout=60).raise_for_status()
    assert isinstance(done.result, RegistrationResult)
    assert done.result.vertebrae[0].level == "T1" and len(done.result.vertebrae) == 17
    assert done.result.measures.cobb and done.study == job.study and done.deliveries == []
    assert done.payload is not None and done.payload["study"] == STUDY  # carried unchanged
    assert job.id in {j.id for j in client.list(status="succeeded", limit=500).jobs}
    assert any(j.id == job.id for j in client.iter_jobs(page_size=2, status=["succeeded"]))
    with pytest.raises(NotFound) as missing:
        client.get(uuid.uuid4())
    assert missing.value.status == 404 and missing.value.kind == "not-found"


def test_client_errors_carry_the_problem(client: SpineClient) -> None:
    bad = spine_payload()
    bad["pa"]["landmarks"][2]["level"] = "T13"
    bad["study"] = {"study_instance_uid": "1.2.abc", "pa_sop_instance_uid": "1." + "2" * 70}
    with pytest.raises(InvalidRequest) as refused:
        client.submit(bad)
    paths = {e.path for e in refused.value.problem.errors or []}
    assert paths == {"pa.landmarks[2].level", "study.study_instance_uid", "study.pa_sop_instance_uid"}
    key = f"key-{uuid.uuid4()}"
    client.submit(spine_payload(), idempotency_key=key)
    with pytest.raises(IdempotencyConflict):
        client.submit(spine_payload(curve_mm=3.0), idempotency_key=key)
    failing = engine_refused_payload()  # passes the API, refused by the engine
    with pytest.raises(JobFailed) as failed:
        client.wait(client.submit(failing).id, timeout=60).raise_for_status()
    assert failed.value.job.status == "failed" and failed.value.job.error is not None


def test_retried_posts_never_make_two_jobs(served: Served) -> None:
    """The proxy forwards a submission, then loses the answer (502/503): the client retries with the same
    Idempotency-Key and gets the job the service made; a 429 with Retry-After is waited out."""
    proxy = FlakyProxy(served.url)
    try:
        with SpineClient(proxy.url, served.api_key, backoff=0.05) as client:
            before = sum(1 for _ in client.iter_jobs(page_size=500))
            proxy.log.clear()
            proxy.rules = [Rule("POST", "/v1/jobs", "lose", 503)]
            job = client.submit(spine_payload(curve_mm=11.0))
            assert [(m, s, f) for m, _, s, f in proxy.log] == [("POST", 503, True), ("POST", 202, True)]
            proxy.rules = [Rule("POST", "/v1/jobs/batch", "lose", 502, times=2)]
            batch = client.submit_batch([spine_payload(curve_mm=12.0 + i) for i in range(3)] + [{"pa": {}}])
            assert (batch.accepted, batch.rejected) == (3, 1) and batch.results[3].problem is not None
            proxy.rules = [Rule("GET", f"/v1/jobs/{job.id}", "refuse", 429, headers={"Retry-After": "1"})]
            started = time.monotonic()
            assert client.get(job.id).id == job.id
            assert time.monotonic() - started >= 1.0
            after = list(client.iter_jobs(page_size=500))
            assert len(after) == before + 4  # one job per payload, not one per attempt
            assert {job.id, *(e.job.id for e in batch.results if e.job)} <= {j.id for j in after}
            proxy.rules = [Rule("GET", "/v1/jobs", "refuse", 503, times=10)]
            with pytest.raises(ServerError) as down:  # still 503 after the retries
                SpineClient(proxy.url, served.api_key, retries=2, backoff=0.01).list()
            assert down.value.status == 503 and down.value.problem.title == "flaky proxy"
            assert sum(1 for m, p, _, _ in proxy.log if (m, p) == ("GET", "/v1/jobs")) >= 3
    finally:
        proxy.close()
    with pytest.raises(ServiceUnreachable):
        SpineClient(f"http://127.0.0.1:{free_port()}", retries=1, backoff=0.01).list()


# ------------------------------------------------------------------ command line


def test_cli_submit_get_list_cancel(served: Served, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "payload.json"
    path.write_text(json.dumps(spine_payload(curve_mm=18.0)))
    run = run_cli(served, "submit", str(path), "--wait", "--timeout", "60")  # a real console process
    assert run.returncode == 0, run.stderr
    job = json.loads(run.stdout)
    assert job["status"] == "succeeded"

    code, out, _ = cli(served, capsys, "get", job["id"], "--format", "csv")
    rows = list(csv.DictReader(io.StringIO(out)))
    assert code == 0 and [r["level"] for r in rows][:2] == ["T1", "T2"] and len(rows) == 17
    assert rows[0]["u1_rad_per_mm"] and rows[-1]["u1_rad_per_mm"] == ""  # L5 has no segment
    assert float(rows[5]["twist_deg"]) == pytest.approx(job["result"]["vertebrae"][5]["twist_deg"])
    code, out, _ = cli(served, capsys, "get", job["id"], "--measures")
    measures = {r["measure"]: r for r in csv.DictReader(io.StringIO(out))}
    assert code == 0 and {"cobb_angle", "thoracic_kyphosis_t4_t12", "lumbar_lordosis_l1_l5"} <= measures.keys()
    assert float(measures["lumbar_lordosis_l1_l5"]["value"]) == pytest.approx(
        job["result"]["measures"]["lumbar_lordosis_l1_l5_deg"]
    )
    code, out, _ = cli(served, capsys, "list", "--format", "json", "--status", "succeeded", "--limit", "500")
    assert code == 0 and job["id"] in {j["id"] for j in json.loads(out)["jobs"]}
    code, out, _ = cli(served, capsys, "list", "--limit", "3")
    assert code == 0 and "status" in out
    code, _, err = cli(served, capsys, "cancel", job["id"])
    assert code == 7 and "already" in err  # a finished job cannot be cancelled
    code, _, err = cli(served, capsys, "get", str(uuid.uuid4()))
    assert code == 5 and "404" in err

    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    code, _, err = cli(served, capsys, "submit", str(bad))
    assert code == 2 and "not valid JSON" in err
    invalid = tmp_path / "invalid.json"
    invalid.write_text(json.dumps({"pa": {"landmarks": [{"level": "T13", "point": [0, 0]}]}}))
    run = run_cli(served, "submit", str(invalid))
    assert run.returncode == 2 and "pa.landmarks[0].level" in run.stderr
    run = run_cli(served, "list", "--retries", "0", SPINE_URL=f"http://127.0.0.1:{free_port()}")
    assert run.returncode == 4 and "ConnectError" in run.stderr


def test_cli_timeout_and_jobs_without_result(api_only: ApiOnly, tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    """On an API without worker jobs stay queued: --timeout ends with 3, CSV / FHIR of them with 7."""
    path = tmp_path / "payload.json"
    path.write_text(json.dumps(spine_payload()))
    code, out, err = cli(api_only, capsys, "submit", str(path), "--timeout", "0.5")
    assert code == 3 and "still queued" in err
    job_id = json.loads(out)["id"]
    code, _, err = cli(api_only, capsys, "get", job_id, "--format", "csv")
    assert code == 7 and "queued" in err
    code, _, err = cli(api_only, capsys, "fhir", job_id)
    assert code == 7 and "job-has-no-result" not in err and "409" in err
    with SpineClient(api_only.url, api_only.api_key) as client, pytest.raises(JobHasNoResult):
        client.fhir(job_id)
    code, out, _ = cli(api_only, capsys, "cancel", job_id)
    assert code == 0 and json.loads(out)["status"] == "cancelled"
    code, _, err = cli(api_only, capsys, "get", job_id, "--measures")
    assert code == 1 and "cancelled" in err
    with SpineClient(api_only.url, api_only.api_key) as client:
        with pytest.raises(WaitTimeout):
            client.wait(client.submit(spine_payload()).id, timeout=0.2)
        payload = spine_payload()
        payload["callback_url"] = "http://127.0.0.1:9/hooks"
        with pytest.raises(InvalidRequest) as refused:  # no allow-list, no secret: webhooks are off
            client.submit(payload)
        assert [e.path for e in refused.value.problem.errors or []] == ["callback_url"]


def test_submit_dir_submits_waits_and_summarises(served: Served, tmp_path: Path) -> None:
    folder = tmp_path / "cases"
    folder.mkdir()
    for i in range(6):
        (folder / f"case{i}.json").write_text(json.dumps(spine_payload(curve_mm=4.0 * i)))
    (folder / "notes.txt").write_text("not a payload")
    run = run_cli(served, "submit-dir", str(folder), "--timeout", "90", "--batch-size", "4")
    assert run.returncode == 0, run.stderr
    assert "6 succeeded" in run.stdout and "submitting" in run.stderr and "waiting" in run.stderr
    rows = list(csv.DictReader((folder / "summary.csv").open()))
    assert [r["file"] for r in rows] == [f"case{i}.json" for i in range(6)]
    assert {r["status"] for r in rows} == {"succeeded"} and all(r["thoracic_kyphosis_t4_t12_deg"] for r in rows)
    assert float(rows[-1]["major_cobb_deg"]) > 5 and rows[-1]["job_id"]

    (folder / "broken.json").write_text("[1, 2")
    (folder / "invalid.json").write_text(json.dumps({"pa": {"landmarks": []}}))
    summary = tmp_path / "again.csv"
    code = client_cli.main(["submit-dir", str(folder), "--summary", str(summary), "--no-progress", "--url", served.url,
                            *(["--api-key", served.api_key] if served.api_key else [])])  # fmt: skip
    assert code == 2  # some files were refused
    by_file = {r["file"]: r for r in csv.DictReader(summary.open())}
    assert by_file["broken.json"]["status"] == "rejected" and by_file["broken.json"]["problem_type"] == "malformed-json"
    assert by_file["invalid.json"]["status"] == "rejected"
    assert by_file["invalid.json"]["problem_type"] == "validation-error"
    assert by_file["case3.json"]["status"] == "succeeded"

    as_json = run_cli(served, "submit-dir", str(folder), "--summary", str(tmp_path / "third.csv"), "--no-progress",
                      "--json")  # fmt: skip
    assert as_json.returncode == 2, as_json.stderr
    outcome = json.loads(as_json.stdout)  # the whole standard output is one JSON document
    assert outcome["counts"] == {"rejected": 2, "succeeded": 6} and outcome["summary"] == str(tmp_path / "third.csv")
    files = {f["file"]: f for f in outcome["files"]}
    assert files["broken.json"]["problem_type"] == "malformed-json" and files["case5.json"]["job_id"]


# ------------------------------------------------------------------ FHIR


def test_fhir_bundle_of_a_succeeded_job(client: SpineClient) -> None:
    from fhir.resources.R4B.bundle import Bundle

    payload = spine_payload(curve_mm=30.0)
    payload["study"] = STUDY
    job = client.wait(client.submit(payload).id, timeout=60).raise_for_status()
    bundle = client.fhir(job.id)
    Bundle.model_validate(bundle)  # valid FHIR (R4B models; R4-identical for these elements)
    assert bundle["resourceType"] == "Bundle" and bundle["type"] == "collection"
    observations = [e["resource"] for e in bundle["entry"]]
    assert all(e["fullUrl"] == f"urn:uuid:{e['resource']['id']}" for e in bundle["entry"])
    assert job.result is not None
    curves = job.result.measures.cobb
    assert len(observations) == len(curves) + 3 + 1  # curves, 2 kyphoses, lordosis, apical rotation
    for obs in observations:
        assert obs["status"] == "final"
        assert obs["category"][0]["coding"][0]["code"] == "imaging"
        assert obs["code"]["text"] and len(obs["code"]["coding"]) == 1  # coded, the text kept
        assert obs["code"]["coding"][0]["system"] in ("http://snomed.info/sct", LOCAL_CODE_SYSTEM)
        assert obs["valueQuantity"]["system"] == "http://unitsofmeasure.org"
        assert obs["valueQuantity"]["code"] == "deg"
        assert obs["derivedFrom"] == [{"type": "ImagingStudy", "display": f"DICOM study {STUDY['study_instance_uid']}",
                                       "identifier": {"system": "urn:dicom:uid",
                                                      "value": f"urn:oid:{STUDY['study_instance_uid']}"}}]  # fmt: skip
    major = next(c for c in curves if c.major)
    cobb = next(o for o in observations if o["code"]["text"] == "Cobb angle, frontal plane, major curve")
    assert cobb["valueQuantity"]["value"] == pytest.approx(major.angle_deg, abs=0.006)
    parts = {c["code"]["text"]: c for c in cobb["component"]}
    assert parts["Upper end vertebra"]["valueString"] == major.upper
    assert parts["Apex vertebra"]["valueString"] == major.apex
    lordosis = next(o for o in observations if o["code"]["text"].startswith("Lumbar lordosis L1–L5"))
    assert lordosis["valueQuantity"]["value"] == pytest.approx(job.result.measures.lumbar_lordosis_l1_l5_deg, abs=0.006)
    assert any(STUDY["pa_sop_instance_uid"] in n["text"] for n in lordosis["note"])
    with pytest.raises(NotFound):
        client.fhir(uuid.uuid4())


# ------------------------------------------------------------------ webhooks


def _deliveries(client: SpineClient, job_id: Any, n: int) -> list[Any]:
    def enough() -> list[Any] | None:
        found = client.get(job_id).deliveries or []
        return found if len(found) >= n and found[-1].next_attempt_at is None else None

    result: list[Any] = wait_until(enough, 60, f"{n} deliveries of job {job_id}", 0.2)
    return result


def test_webhook_is_signed_retried_and_visible_on_the_job(client: SpineClient, receiver: Receiver) -> None:
    path = f"/hooks/{uuid.uuid4().hex}"
    receiver.plan[path] = [500]  # the receiver fails once, then accepts
    payload = spine_payload(curve_mm=21.0)
    payload["callback_url"] = receiver.url(path)
    payload["study"] = STUDY
    job = client.wait(client.submit(payload).id, timeout=60).raise_for_status()
    deliveries = _deliveries(client, job.id, 2)
    assert [(d.attempt, d.status_code) for d in deliveries] == [(1, 500), (2, 204)]
    assert deliveries[0].error == "HTTP 500" and deliveries[1].error is None
    assert deliveries[0].next_attempt_at is not None and deliveries[0].event == "job.succeeded"
    got = receiver.at(path)
    assert [r.answered for r in got] == [500, 204]
    assert got[0].headers["webhook-id"] == got[1].headers["webhook-id"] == message_id(job.id, "succeeded")
    assert got[0].body == got[1].body
    body = Webhook(SECRET).verify(got[1].body, got[1].headers)  # the reference implementation's check
    assert body["type"] == "job.succeeded" and body["data"]["id"] == str(job.id)
    assert body["data"]["study"] == STUDY and body["data"]["result"]["measures"]["cobb"]
    tampered = dict(got[1].headers, **{"webhook-signature": "v1," + base64.b64encode(b"x" * 32).decode()})
    with pytest.raises(Exception, match="signature"):
        Webhook(SECRET).verify(got[1].body, tampered)


def test_a_webhook_that_could_not_be_published_is_sent_by_the_reconciler(
    served: Served, client: SpineClient, receiver: Receiver
) -> None:
    """The broker refuses the publish as the job ends; the running service's reconciler sends it."""
    path = f"/hooks/{uuid.uuid4().hex}"
    payload = spine_payload()
    payload["callback_url"] = receiver.url(path)
    with session_scope(served.settings) as session:  # stored, never enqueued, then cancelled here
        job, _ = jobs_repo.create_job(session, payload)
        jobs_repo.cancel_job(session, job.id)
    down = make_celery(served.settings.model_copy(update={"broker_url": "redis://127.0.0.1:1/0"}))
    assert not job_ended(served.settings, job.id, "cancelled", url=payload["callback_url"], celery=down)
    deliveries = _deliveries(client, job.id, 2)
    assert [(d.attempt, d.status_code) for d in deliveries] == [(0, None), (1, 204)]
    assert deliveries[0].error is not None and deliveries[0].error.startswith("not published")
    [got] = receiver.at(path)
    assert got.headers["webhook-id"] == message_id(job.id, "cancelled")
    assert Webhook(SECRET).verify(got.body, got.headers)["type"] == "job.cancelled"


def test_webhooks_on_cancel_and_failure_and_refused_destinations(
    served: Served, client: SpineClient, receiver: Receiver
) -> None:
    path = f"/hooks/{uuid.uuid4().hex}"
    payload = spine_payload()
    payload["callback_url"] = receiver.url(path)
    with session_scope(served.settings) as session:  # stored, never enqueued: it stays queued
        queued, _ = jobs_repo.create_job(session, payload)
    assert client.cancel(queued.id).status == "cancelled"
    client.cancel(queued.id)  # a second cancel sends nothing more
    failing = {**engine_refused_payload(), "callback_url": payload["callback_url"]}
    failed = client.wait(client.submit(failing).id, timeout=60)
    assert failed.status == "failed"
    _deliveries(client, queued.id, 1)
    _deliveries(client, failed.id, 1)
    events = sorted(r.json()["type"] for r in receiver.at(path))
    assert events == ["job.cancelled", "job.failed"]
    assert all(Webhook(SECRET).verify(r.body, r.headers) for r in receiver.at(path))

    allowed = receiver.url("/hooks")
    for url in (
        f"http://127.0.0.1:{receiver.port + 1 if receiver.port < 65535 else 1}/hooks/x",  # another port
        receiver.url("/hooks-admin"),  # not below the prefix at a / boundary
        receiver.url("/hooks/../admin"),  # climbs out of it
        receiver.url("/hooks/%2e%2e/admin"),
        allowed.replace("http://", "https://"),  # another scheme
        allowed.replace("http://", "http://user:pw@"),  # credentials
        allowed.replace("127.0.0.1", "127.0.0.1.nip.io"),  # a host that merely starts like an allowed one
        allowed.replace("http://", "ftp://"),
        "http://169.254.169.254/latest/meta-data/",
    ):
        with pytest.raises(InvalidRequest) as refused:
            client.submit(dict(payload, callback_url=url))
        assert [e.path for e in refused.value.problem.errors or []] == ["callback_url"], url
