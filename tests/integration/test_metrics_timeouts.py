"""GET /metrics reads the database and the broker at scrape time, bounded as /readyz is: a dependency that
accepts connections and never answers is reported down (``spine_dependency_up`` 0) within
SPINE_READY_TIMEOUT_S, not after its own timeouts (SPINE_DB_CONNECT_TIMEOUT_S, SPINE_BROKER_TIMEOUT_S,
5 s each by default). The black hole is a listening socket on a free loopback port that never accepts
(the kernel completes the TCP handshake into its backlog, then nothing answers); the other dependency is
real (a PostgreSQL database of the test's own, the machine's Redis)."""

from __future__ import annotations

import socket
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from services.api.app import create_app
from services.core.config import Settings
from services.db.migrate import upgrade
from tests.integration.test_dependency_timeouts import MACHINE_SLACK_S, READY_TIMEOUT_S, finishes_within
from tests.interop_helpers import wait_until

DEPENDENCY_TIMEOUT_S = 5.0
"""SPINE_DB_CONNECT_TIMEOUT_S and SPINE_BROKER_TIMEOUT_S at their defaults: what a scrape waited for a
black-holed dependency when nothing else bounded it."""
CHECKS_END_S = 2 * (2 * DEPENDENCY_TIMEOUT_S) + MACHINE_SLACK_S
"""The longest wait, after a test, for its checks stuck on the black hole to end, so that no later test finds
the scrape's check slots held: a broker read is kombu's connection attempts (bounded in all by the app's
broker_connection_timeout, 5 s) and one command (SPINE_BROKER_TIMEOUT_S), a database read one connection
(SPINE_DB_CONNECT_TIMEOUT_S); twice that for a loaded machine. The wait ends as soon as they have."""


@pytest.fixture
def black_hole() -> Iterator[int]:
    """A port that accepts TCP connections (into the listen backlog) and never answers."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(16)
        yield int(listener.getsockname()[1])
        wait_until(_no_check_running, CHECKS_END_S, "the scrape's dependency checks to end")


def _no_check_running() -> bool:
    return not any(thread.name == "dependency-check" for thread in threading.enumerate())


def _scrape(settings: Settings) -> tuple[dict[str, float], set[str], float]:
    """(spine_dependency_up by name, the metric families answered, seconds the scrape took)."""
    client = TestClient(create_app(settings), raise_server_exceptions=False)
    answer, took = finishes_within(DEPENDENCY_TIMEOUT_S * 4, lambda: client.get("/metrics"))
    assert not isinstance(answer, Exception), answer
    assert answer.status_code == 200, answer.text
    families = list(text_string_to_metric_families(answer.text))
    up = {s.labels["name"]: s.value for f in families if f.name == "spine_dependency_up" for s in f.samples}
    return up, {f.name for f in families}, took


def test_a_black_holed_database_is_reported_down_within_the_ready_timeout(
    tmp_path: Path, black_hole: int, redis_url: str
) -> None:
    settings = Settings(data_dir=tmp_path, DATABASE_URL=f"postgresql+psycopg://postgres@127.0.0.1:{black_hole}/none",
                        CELERY_BROKER_URL=redis_url, queue_name=f"metrics-{uuid.uuid4().hex[:8]}",
                        ready_timeout_s=READY_TIMEOUT_S)  # fmt: skip
    for _ in range(2):  # the second while the first's check still waits on the black hole
        up, families, took = _scrape(settings)
        assert up == {"database": 0, "broker": 1}, up
        assert "spine_queue_depth" in families
        assert took < READY_TIMEOUT_S + MACHINE_SLACK_S, took


def test_a_black_holed_broker_is_reported_down_within_the_ready_timeout(
    tmp_path: Path, black_hole: int, fresh_postgres_url: str
) -> None:
    broker = f"redis://127.0.0.1:{black_hole}/0"
    settings = Settings(data_dir=tmp_path, DATABASE_URL=fresh_postgres_url, CELERY_BROKER_URL=broker,
                        ready_timeout_s=READY_TIMEOUT_S)  # fmt: skip
    upgrade(settings, quiet=True)
    up, families, took = _scrape(settings)
    assert up == {"database": 1, "broker": 0}, up
    assert "spine_jobs" in families and "spine_queue_depth" not in families
    assert took < READY_TIMEOUT_S + MACHINE_SLACK_S, took
