"""The worker's CPU cost per job, in process (docs/performance.md): claim, fit and finish of N jobs,
CPU time from ``getrusage``, and the fit alone (``spine_engine.register`` of the same payload N
times) for comparison. On a fresh embedded SQLite database, or with ``--database-url`` on a
database given (PostgreSQL: an empty database, migrated here).

``python -m tools.workercost [N] [--database-url URL]``
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import spine_engine
from services.core.config import Settings
from services.db import jobs as jobs_repo
from services.db.engine import session_scope
from services.db.migrate import upgrade
from services.worker.tasks import execute_job
from tools.hops import payload

WARMUP = 20


def _cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def measure(settings: Settings, n: int) -> tuple[float, float, float, set[str]]:
    """(worker CPU ms per job, wall ms per job, register() CPU ms per call, outcomes)."""
    upgrade(settings, quiet=True)
    with session_scope(settings) as session:
        ids = [jobs_repo.create_job(session, payload())[0].id for _ in range(n + WARMUP)]
    for job_id in ids[:WARMUP]:
        execute_job(settings, job_id)
    cpu, started = _cpu_s(), time.perf_counter()
    outcomes = {execute_job(settings, job_id) for job_id in ids[WARMUP:]}
    worker_ms, wall_ms = (_cpu_s() - cpu) * 1000 / n, (time.perf_counter() - started) * 1000 / n
    fit_payload, cpu = payload(), _cpu_s()
    for _ in range(n):
        spine_engine.register(fit_payload)
    return worker_ms, wall_ms, (_cpu_s() - cpu) * 1000 / n, outcomes


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("n", type=int, nargs="?", default=300)
    parser.add_argument("--database-url", default=None, help="e.g. postgresql+psycopg://postgres@127.0.0.1/empty_db")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp), database_url=args.database_url)
        worker_ms, wall_ms, fit_ms, outcomes = measure(settings, args.n)
    print(
        f"{args.n} jobs {sorted(outcomes)}: CPU {worker_ms:.2f} ms/job, wall {wall_ms:.2f} ms/job; "
        f"register() alone {fit_ms:.2f} ms CPU/call, the rest {worker_ms - fit_ms:.2f} ms/job"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
