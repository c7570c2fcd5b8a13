"""Shared fixtures of the service tests: payloads, real databases, brokers and worker processes.

Integration fixtures use the real PostgreSQL and Redis on 127.0.0.1 (override with
SPINE_TEST_POSTGRES / SPINE_TEST_REDIS) and skip, saying why, when they are unreachable. Each
test session gets its own PostgreSQL database and queue name, dropped at the end.

In CI (``CI=true``, as ``.ci/run`` runs) or with ``SPINE_REQUIRE_BACKENDS=1``, a skip is a failure:
a test that needs PostgreSQL, Redis, Chromium or Orthanc and does not find it fails, so that a
green run cannot hide a missing back end.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager, redirect_stderr, redirect_stdout
from io import StringIO
from pathlib import Path
from typing import Any
from unittest import mock

import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from services.cli import main as spine_main
from services.core.config import Settings, get_settings
from services.db import jobs as jobs_repo
from services.db.engine import session_scope
from services.db.migrate import upgrade
from spine_engine.levels import LEVELS
from tests import stopping
from tools.dicom.orthanc import OrthancServer, orthanc_missing, running_orthanc
from tools.loadbench import OwnRedis

PG_ADMIN_URL = os.environ.get("SPINE_TEST_POSTGRES", "postgresql://postgres@127.0.0.1:5432/test")
REDIS_URL = os.environ.get("SPINE_TEST_REDIS", "redis://127.0.0.1:6379/0")
IDENTITY_LPS = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]  # rows d1, d2, d3
FINAL = {"succeeded", "failed", "cancelled"}


pytest_plugins = ["pytester"]  # tests/arch/test_ci_rules.py runs pytest on a probe file in process


def require_backends() -> bool:
    """Whether every skip fails (CI): set by ``.ci/run`` (CI=true) or SPINE_REQUIRE_BACKENDS=1, read from
    the environment of the run."""
    return os.environ.get("CI", "").lower() in ("true", "1") or os.environ.get("SPINE_REQUIRE_BACKENDS") == "1"


def pytest_sessionstart(session: pytest.Session) -> None:
    stopping.claim(session)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """Before the session's fixtures are torn down (no next test), tell every service process they
    started to stop, so that they stop together (tests/stopping.py)."""
    if nextitem is None and stopping.owns(item.session):
        stopping.signal_all()
    yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[None]:
    """In CI, turn every skipped test (a missing back end, browser, tool) into a failure naming why."""
    outcome = yield
    report = outcome.get_result()  # type: ignore[attr-defined]
    if report.skipped and not hasattr(report, "wasxfail") and require_backends():
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        report.outcome = "failed"
        report.longrepr = (
            f"skipped where every back end must be present (CI=true or SPINE_REQUIRE_BACKENDS=1): {reason}"
        )


def spine_payload(
    curve_mm: float = 15.0, length_mm: float = 420.0, *, spacing_mm: float | None = None
) -> dict[str, Any]:
    """A plausible PA payload: 17 endplate midpoints on a C-curve (image mm, or px of ``spacing_mm``
    mm when it is given), T1 and L5 given (LPS, mm)."""
    landmarks = []
    for i, level in enumerate(LEVELS):
        t = i / (len(LEVELS) - 1)
        col, row = 100.0 + curve_mm * math.sin(math.pi * t), 50.0 + length_mm * t
        if spacing_mm:
            col, row = col / spacing_mm, row / spacing_mm
        landmarks.append({"level": level, "point": [round(col, 3), round(row, 3)]})
    pa: dict[str, Any] = {"landmarks": landmarks}
    if spacing_mm:
        pa["units"] = "px"
    payload = {
        "pa": pa,
        "boundary": {
            "T1": {"position": [0.0, 0.0, 0.0], "directors": IDENTITY_LPS},
            "L5": {"position": [0.0, 0.0, -length_mm], "directors": IDENTITY_LPS},
        },
    }
    copy: dict[str, Any] = json.loads(json.dumps(payload))  # no shared lists
    return copy


def engine_refused_payload() -> dict[str, Any]:
    """A payload the API takes and the engine refuses, for a job that fails in the worker: a lateral
    film whose levels lie 2 mm above and below the PA's in turn, which no spine's heights do, under a
    stated landmark SD of 0.001 mm (``landmark_sd_contradicted``)."""
    payload = spine_payload()
    payload["lateral"] = {"landmarks": [
        {"level": lm["level"], "point": [60.0, lm["point"][1] + (2.0 if i % 2 else -2.0)]}
        for i, lm in enumerate(payload["pa"]["landmarks"])
    ]}  # fmt: skip
    for view in ("pa", "lateral"):
        payload[view]["landmark_sd_mm"] = 0.001
    return payload


@pytest.fixture
def payload() -> dict[str, Any]:
    return spine_payload()


# ------------------------------------------------------------------ real back ends


@contextmanager
def _postgres_database(purpose: str) -> Iterator[str]:
    """Create a uniquely named PostgreSQL database; yield its SQLAlchemy URL; drop it after."""
    import psycopg

    try:
        admin = psycopg.connect(PG_ADMIN_URL, connect_timeout=3, autocommit=True)
    except Exception as exc:
        pytest.skip(f"PostgreSQL unreachable at {PG_ADMIN_URL}: {exc}")
    name = f"spine_test_{purpose}_{uuid.uuid4().hex[:10]}"
    admin.execute(f'CREATE DATABASE "{name}"')
    base = PG_ADMIN_URL.rsplit("/", 1)[0].replace("postgresql://", "postgresql+psycopg://", 1)
    try:
        yield f"{base}/{name}"
    finally:
        from services.db.engine import dispose_engines

        dispose_engines()
        admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        admin.close()


@pytest.fixture(scope="session")
def postgres_url() -> Iterator[str]:
    """A fresh PostgreSQL database for the distributed service of this test session."""
    with _postgres_database("service") as url:
        yield url


@pytest.fixture(scope="session")
def postgres_store_url() -> Iterator[str]:
    """Another fresh PostgreSQL database, with no worker on it, for tests of the jobs table."""
    with _postgres_database("store") as url:
        yield url


@pytest.fixture
def fresh_postgres_url() -> Iterator[str]:
    """An empty PostgreSQL database of its own, for one test (e.g. of the migrations)."""
    with _postgres_database("fresh") as url:
        yield url


@pytest.fixture(scope="session")
def orthanc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[OrthancServer]:
    """One throwaway Orthanc (DICOMweb) on a free loopback port for the session's DICOM and page tests;
    each test stores studies of its own UIDs."""
    reason = orthanc_missing()
    if reason:
        pytest.skip(reason)
    with running_orthanc(tmp_path_factory.mktemp("orthanc")) as server:
        yield server


@pytest.fixture(scope="session")
def redis_url() -> str:
    import redis

    try:
        redis.Redis.from_url(REDIS_URL, socket_connect_timeout=3).ping()
    except Exception as exc:
        pytest.skip(f"Redis unreachable at {REDIS_URL}: {exc}")
    return REDIS_URL


# ------------------------------------------------------------------ a running service


class Service:
    """The API in process (TestClient) and a real `spine worker` subprocess on one back end."""

    def __init__(self, name: str, env: dict[str, str], data_dir: Path):
        self.name = name
        self.env = env
        self.data_dir = data_dir
        self.settings = Settings(**_settings_kwargs(env))
        upgrade(self.settings, quiet=True)
        self.client = TestClient(create_app(self.settings))
        self.api_key = make_key(self.settings, f"{name}-admin", "admin")  # sees every job, stored ones too
        self.client.headers["Authorization"] = f"Bearer {self.api_key}"
        self.worker: subprocess.Popen[bytes] | None = None
        self.log_path = data_dir / "worker.log"

    # -- worker process
    def start_worker(self, timeout: float = 60.0) -> None:
        assert self.worker is None
        offset = self.log_path.stat().st_size if self.log_path.exists() else 0
        log = self.log_path.open("ab")
        self.worker = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "worker"],
            env={**os.environ, **self.env},
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        stopping.started(self.worker)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            text = self.log_path.read_bytes()[offset:].decode(errors="replace")
            if " ready." in text:
                return
            if self.worker.poll() is not None:
                break
            time.sleep(0.1)
        self.stop_worker()
        raise RuntimeError(f"the {self.name} worker did not start:\n{self.worker_log()[-4000:]}")

    def stop_worker(self) -> None:
        if self.worker is None:
            return
        proc, self.worker = self.worker, None
        stopping.stop(proc, grace_s=20)

    def worker_log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    # -- API helpers
    def submit(self, payload: Any, **headers: str) -> dict[str, Any]:
        response = self.client.post("/v1/jobs", json=payload, headers=headers)
        assert response.status_code == 202, response.text
        body: dict[str, Any] = response.json()
        return body

    def job(self, job_id: str) -> dict[str, Any]:
        response = self.client.get(f"/v1/jobs/{job_id}")
        assert response.status_code == 200, response.text
        body: dict[str, Any] = response.json()
        return body

    def wait(self, job_id: str, timeout: float = 60.0, statuses: set[str] = FINAL) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while True:
            job = self.job(job_id)
            if job["status"] in statuses:
                return job
            if time.monotonic() > deadline:
                raise AssertionError(
                    f"job {job_id} still {job['status']} after {timeout} s; worker log:\n{self.worker_log()[-3000:]}"
                )
            time.sleep(0.1)

    def wait_all(self, job_ids: list[str], timeout: float = 90.0) -> list[dict[str, Any]]:
        deadline = time.monotonic() + timeout
        return [self.wait(j, max(1.0, deadline - time.monotonic())) for j in job_ids]


def _settings_kwargs(env: dict[str, str]) -> dict[str, Any]:
    """Settings(**kwargs) equal to what the worker reads from ``env``."""
    kwargs: dict[str, Any] = {}
    for key, value in env.items():
        if key in ("DATABASE_URL", "CELERY_BROKER_URL"):
            kwargs[key] = value
        elif key.startswith("SPINE_"):
            kwargs[key.removeprefix("SPINE_").lower()] = value
    return kwargs


def service_env(data_dir: Path, **extra: str) -> dict[str, str]:
    return {
        "SPINE_DATA_DIR": str(data_dir),
        "SPINE_QUEUE_NAME": f"spine-test-{uuid.uuid4().hex[:8]}",
        "SPINE_RECONCILE_INTERVAL_S": "1",
        "SPINE_WORKER_CONCURRENCY": "2",
        "SPINE_MAX_ATTEMPTS": "2",
        "SPINE_LOG_LEVEL": "INFO",
        **extra,
    }


@contextmanager
def spawned_service(
    name: str, data_dir: Path, *, postgres_url: str | None = None, redis_url: str | None = None, **env: str
) -> Iterator[Service]:
    """A ``Service`` on ``service_env(data_dir, **env)`` with its worker subprocess started: embedded
    (SQLite, kombu's SQLAlchemy broker) unless ``postgres_url`` and ``redis_url`` are given; on exit
    the worker is stopped and the test queue's Redis keys are deleted."""
    backends = {"DATABASE_URL": postgres_url, "CELERY_BROKER_URL": redis_url}
    service = Service(name, service_env(data_dir, **{k: v for k, v in backends.items() if v}, **env), data_dir)
    service.start_worker()
    try:
        yield service
    finally:
        service.stop_worker()
        if redis_url:
            _purge_queue(redis_url, service.env["SPINE_QUEUE_NAME"])


@pytest.fixture(scope="session")
def embedded_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    """The embedded default: SQLite, kombu's SQLAlchemy broker on SQLite, a worker subprocess."""
    with spawned_service("embedded", tmp_path_factory.mktemp("embedded")) as service:
        yield service


@pytest.fixture(scope="session")
def distributed_service(
    tmp_path_factory: pytest.TempPathFactory, postgres_url: str, redis_url: str
) -> Iterator[Service]:
    """Distributed mode: PostgreSQL, Redis broker, a worker subprocess."""
    data_dir = tmp_path_factory.mktemp("distributed")
    with spawned_service("distributed", data_dir, postgres_url=postgres_url, redis_url=redis_url) as service:
        yield service


def _purge_queue(url: str, queue: str) -> None:
    """Delete a test queue's keys from Redis: the queue, its priority lists, kombu's binding keys and
    the messages a killed worker left unacknowledged for it (kombu's ``unacked`` hash and
    ``unacked_index``: any later consumer on the same database would restore them into the queue,
    which then outlives the test)."""
    import redis

    client = redis.Redis.from_url(url)
    client.delete(queue, *client.keys(f"{queue}*"), *client.keys(f"_kombu.binding*.{queue}*"))
    for tag, raw in client.hgetall("unacked").items():
        routing_key = json.loads(raw)[2]
        if routing_key == queue or routing_key.startswith(f"{queue}."):
            client.hdel("unacked", tag)
            client.zrem("unacked_index", tag)


@pytest.fixture(params=["embedded", "distributed"])
def service(request: pytest.FixtureRequest) -> Service:
    """Each end-to-end test runs on both modes."""
    svc: Service = request.getfixturevalue(f"{request.param}_service")
    return svc


def make_key(settings: Settings, name: str = "test-client", role: str = "client") -> str:
    """A new API key (``spine keys create``'s store) in the database of ``settings``."""
    from services.db.engine import session_factory
    from services.db.keys import create_key

    with session_factory(settings)() as session:
        return create_key(session, name, role)[1]


@pytest.fixture
def api(tmp_path: Path) -> Iterator[TestClient]:
    """The API alone on a fresh embedded database (no worker): jobs stay queued. It sends the API key
    of a client named ``test-client``."""
    settings = Settings(data_dir=tmp_path)
    upgrade(settings, quiet=True)
    with TestClient(create_app(settings)) as client:
        client.headers["Authorization"] = f"Bearer {make_key(settings)}"
        yield client


@pytest.fixture
def own_client(db_settings: Settings) -> Iterator[TestClient]:
    """The API on ``db_settings``' database, with the key of a client of its own (the PostgreSQL
    database is the session's, shared with other tests)."""
    with TestClient(create_app(db_settings)) as c:
        c.headers["Authorization"] = f"Bearer {make_key(db_settings, f'own-{uuid.uuid4().hex[:8]}')}"
        yield c


@pytest.fixture
def db_settings(request: pytest.FixtureRequest, tmp_path: Path) -> Settings:
    """Settings of a migrated database, SQLite or PostgreSQL (parametrize indirectly)."""
    kind = getattr(request, "param", "sqlite")
    if kind == "postgresql":
        url: str = request.getfixturevalue("postgres_store_url")
        settings = Settings(DATABASE_URL=url, data_dir=tmp_path)
    else:
        settings = Settings(data_dir=tmp_path)
    upgrade(settings, quiet=True)
    return settings


def queued_job(settings: Settings, callback_url: str | None = None) -> uuid.UUID:
    """A job stored through the API's data access (``services.db.jobs.create_job``), queued and never
    published: ``spine_payload()``, calling back ``callback_url`` when given."""
    payload = spine_payload()
    if callback_url:
        payload["callback_url"] = callback_url
    with session_scope(settings) as session:
        job, _ = jobs_repo.create_job(session, payload)
    return job.id


def fresh_settings(request: pytest.FixtureRequest, tmp_path: Path, **fields: Any) -> Settings:
    """Settings (``fields`` on top) of a migrated database of the test's own, by the fixture's parameter:
    an SQLite file in ``tmp_path`` ("sqlite"), or a new PostgreSQL database ("postgresql")."""
    if request.param == "postgresql":
        fields["DATABASE_URL"] = request.getfixturevalue("fresh_postgres_url")
    made = Settings(data_dir=tmp_path, **fields)
    upgrade(made, quiet=True)
    return made


@pytest.fixture(params=["sqlite", "postgresql"])
def fresh_db_settings(request: pytest.FixtureRequest, tmp_path: Path) -> Settings:
    """Settings of a migrated database of the test's own: an SQLite file, then a new PostgreSQL
    database (for tests whose state no other test may share, e.g. clocks and reconciles)."""
    return fresh_settings(request, tmp_path)


def start_own_redis(log_dir: Path) -> OwnRedis:
    """A throwaway redis-server of the test's own on a free loopback port, started (no persistence: a
    restart loses every message); the test is skipped, saying why, when none can start (a failure in CI)."""
    own = OwnRedis(log_dir)
    try:
        own.start()
    except (SystemExit, OSError) as exc:
        pytest.skip(f"no throwaway redis-server: {exc}")
    return own


def problem_of(response: Any) -> dict[str, Any]:
    assert response.headers["content-type"].startswith("application/problem+json"), response.text
    body: dict[str, Any] = response.json()
    assert {"type", "title", "status", "detail"} <= body.keys()
    assert body["status"] == response.status_code
    return body


def dumps(payload: Any) -> bytes:
    return json.dumps(payload).encode()


Wait = Callable[..., dict[str, Any]]


def spine_cli(*args: str, data_dir: Path) -> subprocess.CompletedProcess[str]:
    """``spine <args>`` on the embedded store of ``data_dir``, run by the CLI's own ``main`` in this
    process: the code a shell runs, without a second interpreter's imports (about 2 s each)."""
    env = {k: v for k, v in os.environ.items() if k not in ("DATABASE_URL", "CELERY_BROKER_URL")}
    env["SPINE_DATA_DIR"] = str(data_dir)
    out, err = StringIO(), StringIO()
    with mock.patch.dict(os.environ, env, clear=True), redirect_stdout(out), redirect_stderr(err):
        get_settings.cache_clear()
        try:
            code = spine_main(list(args))
        except SystemExit as exc:  # argparse refusing the arguments
            code = exc.code if isinstance(exc.code, int) else 1
        finally:
            get_settings.cache_clear()
    return subprocess.CompletedProcess(["spine", *args], code, out.getvalue(), err.getvalue())
