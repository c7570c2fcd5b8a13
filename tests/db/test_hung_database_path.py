"""A path to PostgreSQL that acknowledges and never forwards (a hung connection pooler or proxy) holds
no request and no worker write past ``services.db.engine.answer_timeout_s`` (SPINE_DB_STATEMENT_TIMEOUT_S
+ SPINE_DB_TCP_TIMEOUT_S): the statement on an already open connection fails as a transient fault (the
API's 503 ``service-unavailable`` with Retry-After; an ``OperationalError``, which the worker retries),
the connection is closed rather than pooled again, and once the path forwards again the same engines
answer, no restart.

Real PostgreSQL (the session's store database) behind the test's own TCP relay
(``tests.faults.PortRelay``), hung the way such a proxy hangs: it keeps reading what the
service sends (its kernel acknowledges every byte, so neither ``tcp_user_timeout`` nor the keepalives
see anything wrong) and forwards nothing until it is told to. Each call that could hang runs in a thread
joined with a bound (``finishes_within``): on code without the bound the test fails there instead of
hanging, and the relay forwards again before the test ends."""

from __future__ import annotations

import socket
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import make_url, text

from services.api.app import create_app
from services.core.config import Settings
from services.core.problems import PROBLEM_MEDIA_TYPE
from services.core.retry import TRANSIENT
from services.db import runs
from services.db.engine import dispose_engines, get_engine, worker_connection
from services.db.migrate import upgrade
from tests.conftest import make_key, queued_job
from tests.faults import PortRelay
from tests.integration.test_dependency_timeouts import MACHINE_SLACK_S, finishes_within

STATEMENT_TIMEOUT_S = 0.5
TCP_TIMEOUT_S = 1.0  # SPINE_DB_TCP_TIMEOUT_S's least is 1 s
ANSWER_BOUND_S = STATEMENT_TIMEOUT_S + TCP_TIMEOUT_S
"""The wait the service allows for an answer (``services.db.engine.answer_timeout_s``, docs/reliability.md):
the settings' statement timeout plus their TCP timeout, 1.5 s here."""


class _Held:
    """The sending side of a relayed connection whose sends wait until ``forwarding`` is set."""

    def __init__(self, sock: socket.socket, forwarding: threading.Event):
        self.sock = sock
        self.forwarding = forwarding

    def sendall(self, data: bytes) -> None:
        self.forwarding.wait()
        self.sock.sendall(data)

    def shutdown(self, how: int) -> None:
        self.sock.shutdown(how)


class HangingRelay(PortRelay):
    """``PortRelay`` that can be hung: it still accepts and reads every byte each way (the kernel
    acknowledges them) and holds them until ``forward()``, which sends on what it held."""

    def __init__(self, target: tuple[str, int]):
        super().__init__(target)
        self._forwarding = threading.Event()
        self._forwarding.set()

    def hang(self) -> None:
        self._forwarding.clear()

    def forward(self) -> None:
        self._forwarding.set()

    def _pump(self, source: socket.socket, sink: socket.socket) -> None:  # type: ignore[override]
        PortRelay._pump(source, cast(socket.socket, _Held(sink, self._forwarding)))

    def close(self) -> None:
        self.forward()
        super().close()


@pytest.fixture
def relayed(tmp_path: Path, postgres_store_url: str) -> Iterator[tuple[Settings, HangingRelay]]:
    """Settings of the migrated store database reached through a ``HangingRelay`` (forwarding), with a
    pool of one connection, the small timeouts above and API keys trusted for a minute (a request's key
    is read once). Every engine of the process, the relay's among them, is disposed of at the end (as
    ``tests.faults.own_postgres`` does): the next test's engines are made again."""
    upgrade(Settings(data_dir=tmp_path, DATABASE_URL=postgres_store_url), quiet=True)
    server = make_url(postgres_store_url)
    relay = HangingRelay((server.host or "127.0.0.1", server.port or 5432))
    relay.open()
    url = server.set(host="127.0.0.1", port=relay.port).render_as_string(hide_password=False)
    settings = Settings(data_dir=tmp_path, DATABASE_URL=url, db_pool_size=1, db_statement_timeout_s=STATEMENT_TIMEOUT_S,
                        db_tcp_timeout_s=TCP_TIMEOUT_S, api_key_cache_s=60)  # fmt: skip
    try:
        yield settings, relay
    finally:
        relay.close()
        dispose_engines()


def hung_while(relay: HangingRelay, call: Any) -> tuple[Any, float]:
    """``finishes_within`` of ``call`` while the relay is hung; it forwards again afterwards."""
    relay.hang()
    try:
        return finishes_within(ANSWER_BOUND_S + MACHINE_SLACK_S + 10, call)
    finally:
        relay.forward()


def test_an_api_request_on_a_hung_path_is_a_503_within_the_bound_and_its_connection_is_not_pooled_again(
    relayed: tuple[Settings, HangingRelay],
) -> None:
    """``GET /v1/jobs/{id}`` (its key already trusted: the job's read is its one statement) on the pool's
    one connection, opened before the path hung: a 503 problem after the bound, the connection closed;
    the next request, the path forwarding again, is answered on a new connection."""
    settings, relay = relayed
    client = TestClient(create_app(settings), headers={"Authorization": f"Bearer {make_key(settings)}"})
    job = f"/v1/jobs/{uuid.uuid4()}"
    assert client.get(job).status_code == 404  # the key and the job read: the pool's one connection is open
    engine = get_engine(settings)
    with engine.connect() as connection:
        pooled = connection.connection.dbapi_connection
        pid = connection.execute(text("SELECT pg_backend_pid()")).scalar()

    answer, took = hung_while(relay, lambda: client.get(job))

    assert not isinstance(answer, Exception), answer
    assert answer.status_code == 503, answer.text
    assert answer.headers["content-type"] == PROBLEM_MEDIA_TYPE and answer.headers["retry-after"]
    assert answer.json()["type"].endswith("/service-unavailable"), answer.json()
    # no sooner than the bound (the server never got the statement: nothing else ends it), and no later
    # than the bound plus what a request takes beside it on this machine (MACHINE_SLACK_S)
    assert ANSWER_BOUND_S <= took < ANSWER_BOUND_S + MACHINE_SLACK_S, took
    assert pooled is not None and pooled.closed  # closed by the bound, not checked in again
    assert client.get(job).status_code == 404  # the path forwards again: the same app answers
    with engine.connect() as connection:
        assert connection.connection.dbapi_connection is not pooled
        assert connection.execute(text("SELECT pg_backend_pid()")).scalar() != pid


def test_a_worker_claim_on_a_hung_path_is_a_transient_fault_within_the_bound(
    relayed: tuple[Settings, HangingRelay],
) -> None:
    """The claims' own engine (``worker_connection(durable=False)``): the claim's statement ends as a
    fault the worker retries (``services.core.retry.TRANSIENT``); the next claim, on a new connection,
    claims the job once the path forwards again. (The hung claim names no job: the relay sends it on
    when it forwards again, as a proxy that recovers would.)"""
    settings, relay = relayed
    job_id = queued_job(settings)
    with worker_connection(settings, durable=False) as connection:
        pooled = connection.connection.dbapi_connection

    def claim(job: uuid.UUID) -> runs.Claim | None:
        with worker_connection(settings, durable=False) as connection:
            return runs.claim_job(connection, job, None)

    outcome, took = hung_while(relay, lambda: claim(uuid.uuid4()))

    assert isinstance(outcome, TRANSIENT) and "no answer from the database" in str(outcome), outcome
    assert ANSWER_BOUND_S <= took < ANSWER_BOUND_S + MACHINE_SLACK_S, took  # as the request's above
    assert pooled is not None and pooled.closed
    claimed = claim(job_id)
    assert claimed is not None and claimed.job_id == job_id
