"""Every wait on PostgreSQL and Redis is bounded (SPINE_DB_*_TIMEOUT_S, SPINE_BROKER_TIMEOUT_S,
SPINE_READY_TIMEOUT_S): a dependency that accepts connections but does not answer makes an error or a
503 in seconds, not a request or a task that hangs. Real servers only: the test's own redis-server
stopped with SIGSTOP (its connections stay open, nothing comes back), a listening socket that never
accepts (a PostgreSQL that does not answer), a row lock held by the test (a statement that waits).

Each call that could hang runs in a thread joined with a bound (``finishes_within``): on code without
the timeouts the test fails at that bound instead of hanging, and the fault is lifted afterwards."""

from __future__ import annotations

import os
import signal
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select, text
from sqlalchemy.exc import OperationalError

from services.api.app import create_app
from services.core.config import Settings
from services.core.jobqueue import make_celery, queue_depth
from services.db import runs
from services.db.engine import get_engine, session_scope, worker_connection
from services.db.jobs import create_job
from services.db.migrate import upgrade
from services.db.models import Job
from services.worker.tasks import reconcile_once
from tests.conftest import make_key, spine_payload, start_own_redis
from tools.loadbench import OwnRedis

BROKER_TIMEOUT_S = 0.5
READY_TIMEOUT_S = 0.5
MACHINE_SLACK_S = 1.5
"""What a request takes beside the waits under test on this 2-core machine (the API's own work, a thread
start): the bounds below are the waits the settings allow plus this."""


def finishes_within(limit: float, call: Callable[[], Any]) -> tuple[Any, float]:
    """(what ``call`` returned or raised, seconds it took); an AssertionError when it is still running
    after ``limit`` (it is left to end in its daemon thread once the fault is lifted)."""
    outcome: list[Any] = []

    def run() -> None:
        try:
            outcome.append(call())
        except Exception as exc:
            outcome.append(exc)

    started = time.monotonic()
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(limit)
    assert not thread.is_alive(), f"still waiting after {limit:g} s"
    return outcome[0], time.monotonic() - started


@pytest.fixture
def stalled_redis(tmp_path: Path) -> Iterator[OwnRedis]:
    """A redis-server of the test's own on a free port, to be stopped with SIGSTOP; continued and
    killed at the end."""
    redis = start_own_redis(tmp_path / "redis")
    yield redis
    assert redis.proc is not None
    os.kill(redis.proc.pid, signal.SIGCONT)
    redis.stop()


@pytest.fixture
def silent_server() -> Iterator[int]:
    """A port that accepts TCP connections (the kernel completes the handshake into the listen backlog)
    and never answers: a server process that hangs."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(16)
        yield int(listener.getsockname()[1])


def test_a_stalled_broker_leaves_a_submission_queued_for_the_reconciler_and_readyz_503(
    tmp_path: Path, fresh_postgres_url: str, stalled_redis: OwnRedis
) -> None:
    """POST /v1/jobs while Redis does not answer: 202, the job marked unpublished (``enqueued_at`` NULL),
    and the reconciler publishes it once Redis answers again; /readyz is a 503 naming the broker."""
    settings = Settings(data_dir=tmp_path, DATABASE_URL=fresh_postgres_url, CELERY_BROKER_URL=stalled_redis.url,
                        queue_name=f"timeouts-{uuid.uuid4().hex[:8]}", broker_timeout_s=BROKER_TIMEOUT_S,
                        ready_timeout_s=READY_TIMEOUT_S)  # fmt: skip
    upgrade(settings, quiet=True)
    client = TestClient(create_app(settings), headers={"Authorization": f"Bearer {make_key(settings)}"})
    assert client.post("/v1/jobs", json=spine_payload()).status_code == 202  # the API's broker connection is open
    assert stalled_redis.proc is not None
    os.kill(stalled_redis.proc.pid, signal.SIGSTOP)

    # the publish retry policy (services.core.jobqueue): 3 tries, each waiting at most one socket timeout
    # for its command and one for a new connection's PING, and 0.5 s of waits between them
    publish_bound = 3 * 2 * BROKER_TIMEOUT_S + 0.5
    answer, took = finishes_within(publish_bound + MACHINE_SLACK_S + 10, lambda: client.post(
        "/v1/jobs", json=spine_payload(curve_mm=21.0)))  # fmt: skip
    assert not isinstance(answer, Exception), answer
    assert answer.status_code == 202, answer.text
    assert took < publish_bound + MACHINE_SLACK_S, took
    job_id = uuid.UUID(answer.json()["id"])
    with session_scope(settings) as session:
        assert session.scalar(select(Job.enqueued_at).where(Job.id == job_id)) is None  # for the reconciler

    ready, took = finishes_within(READY_TIMEOUT_S + MACHINE_SLACK_S + 10, lambda: client.get("/readyz"))
    assert not isinstance(ready, Exception), ready
    assert ready.status_code == 503 and took < READY_TIMEOUT_S + MACHINE_SLACK_S, (ready.status_code, took)
    checks = ready.json()["checks"]
    assert checks["database"] == "ok" and checks["broker"].startswith("no answer within 0.5 s"), checks
    assert "broker: no answer" in ready.json()["detail"]

    os.kill(stalled_redis.proc.pid, signal.SIGCONT)
    app = make_celery(settings)
    reconcile_once(settings, app)
    with session_scope(settings) as session:
        assert session.scalar(select(Job.enqueued_at).where(Job.id == job_id)) is not None
    # the first job's message, the one published again, and any copy of the stalled publish that Redis
    # read from its socket buffer once continued (its connection was closed by then)
    assert queue_depth(app, settings.queue_name) >= 2
    assert client.get("/readyz").status_code == 200


def test_database_connections_carry_the_timeouts(tmp_path: Path, fresh_postgres_url: str) -> None:
    """The API's and the worker's connections to a real PostgreSQL: TCP keepalives and TCP_USER_TIMEOUT on
    their sockets (read back from the kernel), statement_timeout in their sessions. (A database of the
    test's own: engines are kept per URL and process, so these settings reach no other test.)"""
    settings = Settings(data_dir=tmp_path, DATABASE_URL=fresh_postgres_url, db_tcp_timeout_s=3,
                        db_statement_timeout_s=1.5)  # fmt: skip
    api = get_engine(settings).connect()
    with api, worker_connection(settings, durable=False) as claims, worker_connection(settings) as finishes:
        for connection in (api, claims, finishes):
            fd = connection.connection.dbapi_connection.pgconn.socket  # type: ignore[union-attr]
            with socket.socket(fileno=os.dup(fd)) as sock:
                assert sock.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE) == 1
                assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT) == 3000
                # T = 3 s: first probe after T/3, then every T/6 (1 s at least), 2 unanswered → dropped at 3 s
                assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE) == 1
                assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL) == 1
                assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT) == 2
            assert connection.execute(text("SHOW statement_timeout")).scalar() == "1500ms"
        assert claims.execute(text("SHOW synchronous_commit")).scalar() == "off"  # the claims' own setting kept


def test_a_statement_stuck_on_a_lock_ends_at_the_statement_timeout(tmp_path: Path, fresh_postgres_url: str) -> None:
    """A worker's claim of a job whose row another transaction holds locked is cancelled by the server
    after SPINE_DB_STATEMENT_TIMEOUT_S (a transient fault: the task is retried), not left waiting."""
    settings = Settings(data_dir=tmp_path, DATABASE_URL=fresh_postgres_url, db_statement_timeout_s=1)
    upgrade(settings, quiet=True)
    with session_scope(settings) as session:
        job, _ = create_job(session, spine_payload())
    holder = get_engine(settings).connect()
    try:
        holder.execute(text("SELECT id FROM jobs WHERE id = :id FOR UPDATE"), {"id": job.id})  # held until rollback

        def claim() -> Any:
            with worker_connection(settings, durable=False) as connection:
                return runs.claim_job(connection, job.id, None)

        outcome, took = finishes_within(1 + MACHINE_SLACK_S + 10, claim)
        assert isinstance(outcome, OperationalError) and "statement timeout" in str(outcome), outcome
        assert took < 1 + MACHINE_SLACK_S, took
    finally:
        holder.rollback()
        holder.close()


def test_a_database_that_does_not_answer_is_an_error_and_a_prompt_503(tmp_path: Path, silent_server: int) -> None:
    """A PostgreSQL that accepts the TCP connection and never answers: a connection is an error after
    SPINE_DB_CONNECT_TIMEOUT_S (2 s, libpq's least), and /readyz answers 503 after SPINE_READY_TIMEOUT_S."""
    url = f"postgresql+psycopg://postgres@127.0.0.1:{silent_server}/none"
    settings = Settings(data_dir=tmp_path, DATABASE_URL=url, db_connect_timeout_s=2, ready_timeout_s=READY_TIMEOUT_S)

    def connect() -> Any:
        with get_engine(settings).connect() as connection:
            return connection.execute(text("SELECT 1")).scalar()

    outcome, took = finishes_within(2 + MACHINE_SLACK_S + 10, connect)
    assert isinstance(outcome, OperationalError) and "timeout" in str(outcome).lower(), outcome
    assert took < 2 + MACHINE_SLACK_S, took

    client = TestClient(create_app(settings), raise_server_exceptions=False)
    ready, took = finishes_within(READY_TIMEOUT_S + MACHINE_SLACK_S + 10, lambda: client.get("/readyz"))
    assert not isinstance(ready, Exception), ready
    assert ready.status_code == 503 and took < READY_TIMEOUT_S + MACHINE_SLACK_S, (ready.status_code, took)
    assert ready.json()["checks"]["database"].startswith("no answer within 0.5 s (SPINE_READY_TIMEOUT_S)")
