"""The per-client queued-job cap holds under concurrent submissions: a burst of POSTs by one client
near its cap, sent at once over HTTP to a real uvicorn serving the app on PostgreSQL (and on the
embedded SQLite), never leaves more than the cap queued; the others get the 429 problem.

The count-then-insert window is widened in the test, not in the product: ``stats.count_queued`` is
wrapped to sleep ``WINDOW_S`` after counting whenever its count would admit the request (so that on
code without the lock every request of the burst counts before any inserts, deterministically; with
the lock, the sleeps run one after another while the others wait)."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
import uvicorn
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from services.api.app import create_app
from services.core.config import Settings
from services.core.problems import PROBLEM_BASE
from services.db import stats
from services.db.engine import session_factory
from services.db.migrate import upgrade
from services.db.models import Job
from tests.conftest import make_key, spine_payload

CAP = 2
BURST = 6
"""Submissions sent at once: three times the cap, half single POSTs, half batches of one job."""
WINDOW_S = 0.25
"""Sleep between the count and the insert of a request the count admits (CAP of them with the lock:
0.5 s of the test's time)."""


@pytest.fixture(params=["sqlite", "postgresql"])
def settings(request: pytest.FixtureRequest, tmp_path: Path) -> Settings:
    url = request.getfixturevalue("fresh_postgres_url") if request.param == "postgresql" else None
    s = Settings(data_dir=tmp_path, api_key_cache_s=0, max_queued_per_client=CAP, DATABASE_URL=url)
    upgrade(s, quiet=True)
    return s


@contextmanager
def served(settings: Settings) -> Iterator[str]:
    """The app under uvicorn in a thread, on a free loopback port; its base URL."""
    sock = socket.create_server(("127.0.0.1", 0))
    server = uvicorn.Server(uvicorn.Config(create_app(settings), log_level="warning"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{sock.getsockname()[1]}"
    finally:
        server.should_exit = True
        thread.join(10)
        sock.close()


def test_a_burst_near_the_cap_never_queues_more_than_the_cap(
    settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    counted = stats.count_queued

    def slow_count(session: Session, owner: str, limit: int) -> int:
        n = counted(session, owner, limit)
        if n < CAP:  # this request would be admitted: widen the window before its insert
            time.sleep(WINDOW_S)
        return n

    monkeypatch.setattr(stats, "count_queued", slow_count)
    headers = {"Authorization": f"Bearer {make_key(settings, 'clinic-burst')}"}
    answers: list[httpx.Response | None] = [None] * BURST
    start = threading.Barrier(BURST)

    with served(settings) as url:

        def submit(i: int) -> None:
            with httpx.Client(base_url=url, headers=headers, timeout=30) as client:
                start.wait(10)
                if i % 2:
                    body: Any = {"jobs": [spine_payload()]}
                    answers[i] = client.post("/v1/jobs/batch", json=body, headers={"Idempotency-Key": f"b{i}"})
                else:
                    answers[i] = client.post("/v1/jobs", json=spine_payload())

        threads = [threading.Thread(target=submit, args=(i,)) for i in range(BURST)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)

    with session_factory(settings)() as session:
        queued = session.scalar(select(func.count()).select_from(Job).where(Job.owner == "clinic-burst"))
    got = [a.status_code if a is not None else None for a in answers]
    accepted = [a for a in answers if a is not None and a.status_code in (200, 202)]
    refused = [a for a in answers if a is not None and a.status_code == 429]
    assert queued == CAP, f"{queued} jobs queued under a cap of {CAP}; answers {got}"
    assert len(accepted) == CAP and len(refused) == BURST - CAP, got
    for answer in accepted:
        if answer.status_code == 200:  # a batch of one: its one entry accepted
            assert answer.json()["accepted"] == 1, answer.text
    for answer in refused:
        assert answer.headers["content-type"].startswith("application/problem+json")
        problem = answer.json()
        assert problem["type"] == PROBLEM_BASE + "too-many-queued-jobs" and problem["limit"] == CAP
        assert int(answer.headers["retry-after"]) > 0
