"""The worker's CPU cost per job, in process (docs/performance.md): claim, fit and finish of N jobs,
CPU time from ``getrusage``, and the fit alone (``spine_engine.register`` of the same payload N
times) for comparison. On a fresh embedded SQLite database, or with ``--database-url`` on a
database given (PostgreSQL: an empty database, migrated here).

It also counts the SQL statements the worker sent per job (SQLAlchemy's ``before_cursor_execute``),
and on PostgreSQL the transactions the server counted (``pg_stat_database``) and the CPU time of
the server processes that served them (``/proc/<pid>/stat`` of this database's backends).

``python -m tools.workercost [N] [--database-url URL] [--payload hops|loadbench]``
(``loadbench``: the load bench's payloads, ``tools.loadbench.payload(i)``, whose curve varies by job)
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, create_engine, event, text
from sqlalchemy.pool import NullPool

import spine_engine
from services.core.config import Settings
from services.db import jobs as jobs_repo
from services.db.engine import session_scope
from services.db.migrate import upgrade
from services.worker.tasks import execute_job
from tools import hops, loadbench

WARMUP = 20
PAYLOADS: dict[str, Callable[[int], dict[str, Any]]] = {
    "hops": lambda _i: hops.payload(),
    "loadbench": loadbench.payload,
}


def _cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _process_cpu_s(pids: list[int]) -> float:
    """User + system CPU time (s) of the processes ``pids`` so far (those that exist)."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for pid in pids:
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rfind(")") + 2 :].split()
        total += (int(fields[11]) + int(fields[12])) / tick
    return total


class Server:
    """What PostgreSQL did for this process: its backends' CPU and the database's transactions."""

    def __init__(self, settings: Settings, application_name: str | None = None):
        # its own connection, outside the pools the worker uses (whose backends it measures)
        self.engine = create_engine(settings.sqlalchemy_url, poolclass=NullPool)
        self.application_name = application_name
        self.postgres = self.engine.dialect.name == "postgresql"

    def reading(self) -> tuple[float, int]:
        """(CPU s of this database's other backends, or only those of ``application_name``; transactions
        committed or rolled back so far)."""
        if not self.postgres:
            return 0.0, 0
        time.sleep(1.2)  # backends publish their transaction counts at most once a second
        with self.engine.connect() as conn:
            pids = conn.execute(
                text(
                    "SELECT pid FROM pg_stat_activity WHERE datname = current_database() AND pid <> pg_backend_pid()"
                    " AND (CAST(:name AS text) IS NULL OR application_name = :name)"
                ),
                {"name": self.application_name},
            ).scalars()
            conn.execute(text("SELECT pg_stat_clear_snapshot()"))
            xacts = conn.execute(
                text("SELECT xact_commit + xact_rollback FROM pg_stat_database WHERE datname = current_database()")
            ).scalar_one()
            cpu = _process_cpu_s(list(pids))
            conn.rollback()
        return cpu, int(xacts)


def measure(settings: Settings, n: int, make_payload: Callable[[int], dict[str, Any]]) -> dict[str, Any]:
    """Worker CPU ms per job, wall ms per job, register() CPU ms per call, statements, transactions
    and PostgreSQL CPU ms per job, outcomes."""
    upgrade(settings, quiet=True)
    with session_scope(settings) as session:
        ids = [jobs_repo.create_job(session, make_payload(i))[0].id for i in range(n + WARMUP)]
    for job_id in ids[:WARMUP]:
        execute_job(settings, job_id)
    statements = [0]

    def count(*_: Any) -> None:
        statements[0] += 1

    server = Server(settings)
    pg_cpu, xacts = server.reading()
    event.listen(Engine, "before_cursor_execute", count)
    cpu, started = _cpu_s(), time.perf_counter()
    try:
        outcomes = {execute_job(settings, job_id) for job_id in ids[WARMUP:]}
        worker_ms, wall_ms = (_cpu_s() - cpu) * 1000 / n, (time.perf_counter() - started) * 1000 / n
    finally:
        event.remove(Engine, "before_cursor_execute", count)
    pg_cpu_after, xacts_after = server.reading()
    fit_payload, cpu = make_payload(WARMUP), _cpu_s()
    for _ in range(n):
        spine_engine.register(fit_payload)
    return {
        "worker_ms": worker_ms,
        "wall_ms": wall_ms,
        "fit_ms": (_cpu_s() - cpu) * 1000 / n,
        "statements": statements[0] / n,
        # minus the two readings' own transactions (pg_stat_clear_snapshot's and the count's)
        "transactions": (xacts_after - xacts - 2) / n if server.postgres else None,
        "postgres_ms": (pg_cpu_after - pg_cpu) * 1000 / n if server.postgres else None,
        "outcomes": outcomes,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("n", type=int, nargs="?", default=300)
    parser.add_argument("--database-url", default=None, help="e.g. postgresql+psycopg://postgres@127.0.0.1/empty_db")
    parser.add_argument("--payload", choices=sorted(PAYLOADS), default="hops")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp), database_url=args.database_url)
        m = measure(settings, args.n, PAYLOADS[args.payload])
    server = ""
    if m["postgres_ms"] is not None:
        server = f"; PostgreSQL {m['transactions']:.2f} transactions/job, {m['postgres_ms']:.2f} ms CPU/job"
    print(
        f"{args.n} jobs {sorted(m['outcomes'])} ({args.payload} payload): CPU {m['worker_ms']:.2f} ms/job, "
        f"wall {m['wall_ms']:.2f} ms/job; register() alone {m['fit_ms']:.2f} ms CPU/call, "
        f"the rest {m['worker_ms'] - m['fit_ms']:.2f} ms/job; {m['statements']:.2f} SQL statements/job{server}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
