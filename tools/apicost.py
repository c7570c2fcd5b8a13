"""The API's CPU cost per request, in process (docs/performance.md): POST /v1/jobs, and GET
/v1/jobs/{id} of a queued job and of a succeeded one with a real result, through FastAPI's
TestClient on a fresh embedded SQLite database; ``time.process_time`` (every thread of the
process, the test client's included), best of 3 rounds. ``python -m tools.apicost [N]``.
"""

from __future__ import annotations

import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from fastapi.testclient import TestClient
from sqlalchemy import update

from services.api.app import create_app
from services.core.config import Settings
from services.db.engine import session_factory, session_scope
from services.db.keys import create_key
from services.db.migrate import upgrade
from services.db.models import Job
from spine_engine import register
from tools.hops import payload


def cpu_us_per_call(fn: Callable[[], object], n: int, rounds: int = 3) -> float:
    """Best over ``rounds`` of the mean CPU time of ``n`` calls, microseconds."""
    best = float("inf")
    for _ in range(rounds):
        start = time.process_time()
        for _ in range(n):
            fn()
        best = min(best, (time.process_time() - start) / n * 1e6)
    return best


def main(argv: list[str]) -> int:
    n = int(argv[0]) if argv else 300
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp))
        upgrade(settings, quiet=True)
        with session_factory(settings)() as session:
            key = create_key(session, "apicost", "client")[1]
        body = payload()
        with TestClient(create_app(settings)) as api:
            api.headers["Authorization"] = f"Bearer {key}"
            queued = api.post("/v1/jobs", json=body).json()["id"]
            done = api.post("/v1/jobs", json=body).json()["id"]
            with session_scope(settings) as session:
                session.execute(update(Job).where(Job.id == uuid.UUID(done)).values(
                    status="succeeded", result=register(body), started_at=datetime.now(UTC),
                    finished_at=datetime.now(UTC), attempts=1, engine_version="apicost"))  # fmt: skip
            rows = [
                ("POST /v1/jobs", lambda: api.post("/v1/jobs", json=body)),
                ("GET /v1/jobs/{id}, queued", lambda: api.get(f"/v1/jobs/{queued}")),
                ("GET /v1/jobs/{id}, succeeded", lambda: api.get(f"/v1/jobs/{done}")),
                ("GET /healthz (test client floor)", lambda: api.get("/healthz")),
            ]
            print("| request | CPU µs per request |\n| --- | ---: |")
            for label, call in rows:
                print(f"| {label} | {cpu_us_per_call(call, n):.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
