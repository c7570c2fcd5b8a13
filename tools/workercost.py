"""The worker's CPU cost per job, in process (docs/performance.md): claim, fit and finish of N jobs,
CPU time from ``getrusage``, and the fit alone (``spine_engine.register`` of the same payload N
times) for comparison. On a fresh embedded SQLite database, or with ``--database-url`` on a
database given (PostgreSQL: an empty database, migrated here).

It also counts the SQL statements the worker sent per job (SQLAlchemy's ``before_cursor_execute``)
and on PostgreSQL the CPU time of the server processes that ran them (``/proc/<pid>/stat`` of this
database's backends). The jobs are stored first as POST /v1/jobs/batch stores them (``create_jobs``
of 100 payloads and their audit rows, one transaction), and that insert's CPU is given too: this
process's and, on PostgreSQL, the backends'.

``python -m tools.workercost [N] [--database-url URL] [--payload hops|loadbench] [--without-fit]
[--insert-only]`` (``loadbench``: the load bench's payloads, ``tools.loadbench.payload(i)``, whose
curve varies by job; ``--without-fit``: the claim, the validation and the finish only, with one
fixed result; ``--insert-only``: the insert of N jobs and nothing else)
"""

from __future__ import annotations

import argparse
import json
import resource
import tempfile
import time
import uuid
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, create_engine, event, text
from sqlalchemy.pool import NullPool

import spine_engine
from services.core.config import Settings
from services.db import jobs as jobs_repo
from services.db import runs
from services.db.engine import session_scope, worker_connection
from services.db.keys import Caller, audit
from services.db.migrate import upgrade
from services.worker.tasks import execute_job
from spine_engine.reconstruction import register_model
from spine_engine.validation import validate_payload
from tools import hops, loadbench

WARMUP = 20
BATCH = 100
"""Payloads per insert, as the load bench's batches."""
PAYLOADS: dict[str, Callable[[int], dict[str, Any]]] = {
    "hops": lambda _i: hops.payload(),
    "loadbench": loadbench.payload,
}


def _cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


class Server:
    """The CPU time of the PostgreSQL backends serving this database (all but the reading's own, or
    only those of ``application_name``)."""

    def __init__(self, settings: Settings, application_name: str | None = None):
        # its own connection, outside the pools the worker uses (whose backends it measures)
        self.engine = create_engine(settings.sqlalchemy_url, poolclass=NullPool)
        self.application_name = application_name
        self.postgres = self.engine.dialect.name == "postgresql"

    def reading(self) -> float:
        """CPU s so far of the backends (0 on SQLite)."""
        if not self.postgres:
            return 0.0
        with self.engine.connect() as conn:
            pids = conn.execute(
                text(
                    "SELECT pid FROM pg_stat_activity WHERE datname = current_database() AND pid <> pg_backend_pid()"
                    " AND (CAST(:name AS text) IS NULL OR application_name = :name)"
                ),
                {"name": self.application_name},
            ).scalars()
            return loadbench.cpu_seconds_of(list(pids))


def run_without_fit(settings: Settings) -> Callable[[uuid.UUID], str]:
    """``execute_job`` without its fit: the claim, the payload's validation and the finish with
    one fixed result (the fit of the load bench's first payload), on the worker's connections."""
    result = register_model(validate_payload(loadbench.payload(0)))

    def run(job_id: uuid.UUID) -> str:
        with worker_connection(settings, durable=False) as connection:
            claim = runs.claim_job(connection, job_id, result.engine.version, timedelta(seconds=settings.lease_s))
        if claim is None:
            return "skipped"
        validate_payload(claim.payload)
        with worker_connection(settings) as connection:
            stored = runs.finish_job(connection, claim, result=result, engine_version=result.engine.version)
        return "succeeded" if stored else "superseded"

    return run


def insert_jobs(settings: Settings, payloads: list[dict[str, Any]]) -> list[uuid.UUID]:
    """Store the payloads as queued jobs of one client as the batch endpoint does (``create_jobs``
    of ``BATCH`` at a time with their ``create`` audit rows, one transaction each)."""
    caller = Caller(key_id="workercost", name="workercost", role="client")
    ids: list[uuid.UUID] = []
    for start in range(0, len(payloads), BATCH):
        with session_scope(settings) as session:
            jobs = jobs_repo.create_jobs(
                session,
                payloads[start : start + BATCH],
                owner=caller.owner,
                on_insert=lambda s, job_ids: audit(s, caller, "create", job_ids, None),
            )
        ids.extend(job.id for job in jobs)
    return ids


def measure(
    settings: Settings, n: int, make_payload: Callable[[int], dict[str, Any]], fit: bool = True,
    insert_only: bool = False,
) -> dict[str, Any]:
    """Worker CPU ms per job, wall ms per job, register() CPU ms per call (None without the fit), SQL
    statements and PostgreSQL backends' CPU ms per job (None on SQLite), outcomes; the insert's CPU
    ms per job, this process's and the backends' (None on SQLite)."""
    upgrade(settings, quiet=True)
    server = Server(settings)
    payloads = [make_payload(i) for i in range(n + WARMUP)]
    insert_jobs(settings, payloads[:BATCH])  # warm-up: connections, statement caches (not run)
    pg_cpu, cpu = server.reading(), _cpu_s()
    ids = insert_jobs(settings, payloads)
    insert_ms, insert_pg_ms = (_cpu_s() - cpu) * 1000 / len(ids), (server.reading() - pg_cpu) * 1000 / len(ids)
    inserted = {"insert_ms": insert_ms, "insert_postgres_ms": insert_pg_ms if server.postgres else None}
    if insert_only:
        return inserted
    run = (lambda job_id: execute_job(settings, job_id)) if fit else run_without_fit(settings)
    for job_id in ids[:WARMUP]:
        run(job_id)
    statements = [0]

    def count(*_: Any) -> None:
        statements[0] += 1

    pg_cpu = server.reading()
    event.listen(Engine, "before_cursor_execute", count)
    cpu, started = _cpu_s(), time.perf_counter()
    try:
        outcomes = {run(job_id) for job_id in ids[WARMUP:]}
        worker_ms, wall_ms = (_cpu_s() - cpu) * 1000 / n, (time.perf_counter() - started) * 1000 / n
    finally:
        event.remove(Engine, "before_cursor_execute", count)
    pg_cpu = server.reading() - pg_cpu
    fit_ms = None
    if fit:
        fit_payload, cpu = make_payload(WARMUP), _cpu_s()
        for _ in range(n):
            spine_engine.register(fit_payload)
        fit_ms = (_cpu_s() - cpu) * 1000 / n
    return {
        "worker_ms": worker_ms,
        "wall_ms": wall_ms,
        "fit_ms": fit_ms,
        "statements": statements[0] / n,
        "postgres_ms": pg_cpu * 1000 / n if server.postgres else None,
        "outcomes": outcomes,
        **inserted,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("n", type=int, nargs="?", default=300)
    parser.add_argument("--database-url", default=None, help="e.g. postgresql+psycopg://postgres@127.0.0.1/empty_db")
    parser.add_argument("--payload", choices=sorted(PAYLOADS), default="hops")
    parser.add_argument("--without-fit", action="store_true",
                        help="claim, validation and finish only (one fixed result), no register()")  # fmt: skip
    parser.add_argument("--insert-only", action="store_true", help="the insert of N jobs only, no run")
    parser.add_argument("--out", type=Path, help="also write the figures as JSON to this file")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp), database_url=args.database_url)
        m = measure(settings, args.n, PAYLOADS[args.payload], fit=not args.without_fit, insert_only=args.insert_only)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        settings_out = {"n": args.n, "payload": args.payload, "without_fit": args.without_fit,
                        "insert_only": args.insert_only, "postgresql": args.database_url is not None}  # fmt: skip
        args.out.write_text(json.dumps({"settings": settings_out, **m}, indent=2, default=sorted) + "\n")
    pg_insert = m["insert_postgres_ms"]
    insert = "" if pg_insert is None else f", PostgreSQL backends {pg_insert:.2f} ms CPU/job"
    inserted = f"the insert (batches of {BATCH} with audit rows): CPU {m['insert_ms']:.2f} ms/job{insert}"
    if args.insert_only:
        print(f"{args.n} jobs ({args.payload} payload) {inserted}")
        return 0
    fit = (
        ""
        if m["fit_ms"] is None
        else (f"; register() alone {m['fit_ms']:.2f} ms CPU/call, the rest {m['worker_ms'] - m['fit_ms']:.2f} ms/job")
    )
    server = "" if m["postgres_ms"] is None else f", PostgreSQL backends {m['postgres_ms']:.2f} ms CPU/job"
    print(
        f"{args.n} jobs {sorted(m['outcomes'])} ({args.payload} payload{', without the fit' * args.without_fit}): "
        f"CPU {m['worker_ms']:.2f} ms/job, wall {m['wall_ms']:.2f} ms/job{fit}; "
        f"{m['statements']:.2f} SQL statements/job{server}; "
        f"{inserted}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
