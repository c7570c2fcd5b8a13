"""The worker's CPU cost per job through Celery, and Celery's share of it (docs/performance.md).

Starts a real ``spine worker`` (supervisor, Celery main process and its prefork pool, as the load
bench does, without beat) on the database and broker given, stores N jobs, publishes their
messages at once and waits until every job is final; reports the CPU time (user + system, from
``/proc``) of the worker's processes and of this database's PostgreSQL backends per job. Then runs
the same number of jobs in this process with ``execute_job`` (no Celery, as ``tools.workercost``):
the difference is what Celery (and the pool's processes) add per job.

With ``--idle S``, no job: the worker as ``spine worker`` runs it (beat and its reconciler every
``--reconcile-interval`` s) sits idle for S s after it is ready; reports its CPU by process and the
connections the broker accepted meanwhile (Redis ``INFO stats`` ``total_connections_received``).

``python -m tools.celerycost [N] --database-url postgresql+psycopg://…/empty_db
--broker-url redis://127.0.0.1:6379/5 [--concurrency 2] [--payload loadbench|hops] [--idle S]``

The queue is a fresh name (``celerycost-…``), deleted at the end; the database should be empty.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import redis
from sqlalchemy import func, select

from services.core.config import Settings
from services.core.jobqueue import enqueue, make_celery
from services.db import jobs as jobs_repo
from services.db.engine import session_scope
from services.db.migrate import upgrade
from services.db.models import Job
from tools.loadbench import cpu_seconds_of, ensure_database, worker_pids
from tools.processes import run_tool, stop_processes
from tools.workercost import PAYLOADS, Server, measure

WARMUP = 40
APPLICATION_NAME = "spine-celerycost-worker"


def _unfinished(settings: Settings) -> int:
    with session_scope(settings) as session:
        return int(session.execute(select(func.count()).where(Job.status.in_(("queued", "running")))).scalar_one())


def _wait_final(settings: Settings, left: int, timeout_s: float) -> None:
    """Until at most ``left`` jobs of the database are queued or running."""
    deadline = time.monotonic() + timeout_s
    while _unfinished(settings) > left:
        if time.monotonic() > deadline:
            raise SystemExit(f"jobs not final after {timeout_s:.0f} s")
        time.sleep(0.2)


def connections_received(broker_url: str) -> int:
    """Connections the Redis server accepted since it started (``INFO stats``), this one included."""
    with redis.Redis.from_url(broker_url) as client:
        return int(client.info("stats")["total_connections_received"])


def _purge(broker_url: str, queue: str) -> None:
    """Delete the run's queues (jobs, ``.webhooks``, ``.dicom``) and kombu's bindings of them from Redis."""
    with redis.Redis.from_url(broker_url) as client:
        client.delete(queue, *client.keys(f"{queue}*"), *client.keys(f"_kombu.binding*.{queue}*"))


def _wait_ready(worker: subprocess.Popen[bytes], log_path: Path, timeout_s: float = 120) -> None:
    """Until Celery's main process logs that it is ready (``celery@… ready.``)."""
    deadline = time.monotonic() + timeout_s
    while b" ready." not in log_path.read_bytes():
        if worker.poll() is not None or time.monotonic() > deadline:
            raise SystemExit(f"the worker did not start:\n{log_path.read_text(errors='replace')[-2000:]}")
        time.sleep(0.1)


def idle(args: argparse.Namespace, env: dict[str, str], tmp: Path) -> dict[str, object]:
    """The idle worker's CPU by process and the broker connections over ``args.idle`` seconds."""
    env = {**env, "SPINE_RECONCILE_INTERVAL_S": str(args.reconcile_interval), "SPINE_LOG_LEVEL": "INFO"}
    cmd = [sys.executable, "-m", "services.cli", "worker", "--concurrency", str(args.concurrency)]
    log_path = tmp / "worker.log"
    with log_path.open("wb") as log:
        worker = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        _wait_ready(worker, log_path)
        pids = [worker.pid, *worker_pids(worker.pid)]
        by_pid, received = {pid: cpu_seconds_of([pid]) for pid in pids}, connections_received(args.broker_url)
        time.sleep(args.idle)
        by_pid = {pid: cpu_seconds_of([pid]) - cpu for pid, cpu in by_pid.items()}
        received = connections_received(args.broker_url) - received - 1  # not the second reading's own
    finally:
        stop_processes([worker])
        _purge(args.broker_url, env["SPINE_QUEUE_NAME"])
    cpu = sum(by_pid.values())
    print(f"idle worker, {args.idle:g} s, reconciler every {args.reconcile_interval:g} s: CPU {cpu:.2f} s "
          f"({cpu / args.idle:.1%} of a core); broker connections accepted: {received}")  # fmt: skip
    print(
        "  by process (supervisor, Celery main, its children: pool, beat), s: "
        + ", ".join(f"{c:.2f}" for c in by_pid.values())
    )
    return {
        "settings": {"idle_s": args.idle, "reconcile_interval_s": args.reconcile_interval,
                     "concurrency": args.concurrency},
        "cpu_s": cpu, "by_process_s": list(by_pid.values()), "broker_connections": received,
    }  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("n", type=int, nargs="?", default=1000)
    parser.add_argument("--database-url", required=True, help="an empty PostgreSQL database (created if missing)")
    parser.add_argument("--broker-url", required=True, help="e.g. redis://127.0.0.1:6379/5")
    parser.add_argument("--concurrency", type=int, default=2, help="pool processes of the worker")
    parser.add_argument("--payload", choices=sorted(PAYLOADS), default="loadbench")
    parser.add_argument("--no-in-process", action="store_true", help="skip the in-process comparison")
    parser.add_argument("--idle", type=float, metavar="S", help="no jobs: the idle worker's cost over S seconds")
    parser.add_argument(
        "--reconcile-interval",
        type=float,
        default=Settings.model_fields["reconcile_interval_s"].default,
        help="with --idle: SPINE_RECONCILE_INTERVAL_S of the worker (default: the setting's)",
    )
    parser.add_argument("--out", type=Path, help="also write the figures as JSON to this file")
    args = parser.parse_args(argv)
    make_payload = PAYLOADS[args.payload]
    queue = f"celerycost-{uuid.uuid4().hex[:8]}"
    ensure_database(args.database_url)
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp), database_url=args.database_url, CELERY_BROKER_URL=args.broker_url,
                            queue_name=queue)  # fmt: skip
        upgrade(settings, quiet=True)
        env = {**os.environ, "DATABASE_URL": args.database_url, "CELERY_BROKER_URL": args.broker_url,
               "SPINE_QUEUE_NAME": queue, "SPINE_DATA_DIR": tmp,
               "PGAPPNAME": APPLICATION_NAME}  # libpq's default application_name: the worker's backends  # fmt: skip
        if args.idle is not None:
            _write(args.out, idle(args, env, Path(tmp)))
            return 0
        with session_scope(settings) as session:
            ids = [jobs_repo.create_job(session, make_payload(i))[0].id for i in range(args.n + WARMUP)]
        cmd = [sys.executable, "-m", "services.cli", "worker", "--concurrency", str(args.concurrency),
               "--loglevel", "WARNING", "--no-beat"]  # fmt: skip
        app = make_celery(settings)
        with (Path(tmp) / "worker.log").open("wb") as log:
            worker = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            enqueue(app, ids[:WARMUP])
            _wait_final(settings, args.n, 120)
            server = Server(settings, APPLICATION_NAME)
            pids = [worker.pid, *worker_pids(worker.pid)]
            by_pid = {pid: cpu_seconds_of([pid]) for pid in pids}
            worker_cpu, pg_cpu = cpu_seconds_of(pids), server.reading()
            started = time.perf_counter()
            enqueue(app, ids[WARMUP:])
            _wait_final(settings, 0, 600)
            wall_s = time.perf_counter() - started
            by_pid = {pid: cpu_seconds_of([pid]) - cpu for pid, cpu in by_pid.items()}
            worker_cpu, pg_cpu = cpu_seconds_of(pids) - worker_cpu, server.reading() - pg_cpu
        finally:
            stop_processes([worker])
            _purge(args.broker_url, queue)
        worker_ms, pg_ms = worker_cpu * 1000 / args.n, pg_cpu * 1000 / args.n
        print(f"{args.n} jobs through Celery ({args.concurrency} pool processes, {args.payload} payload): "
              f"worker CPU {worker_ms:.2f} ms/job, PostgreSQL backends {pg_ms:.2f} ms/job, "
              f"{args.n / wall_s:.1f} jobs/s wall")  # fmt: skip
        print(
            "  by process (supervisor, Celery main, pool…), ms/job: "
            + ", ".join(f"{cpu * 1000 / args.n:.2f}" for cpu in by_pid.values())
        )
        figures: dict[str, object] = {
            "settings": {"n": args.n, "concurrency": args.concurrency, "payload": args.payload},
            "worker_ms": worker_ms, "postgres_ms": pg_ms, "jobs_per_s_wall": args.n / wall_s,
            "by_process_ms": [cpu * 1000 / args.n for cpu in by_pid.values()],
        }  # fmt: skip
        if not args.no_in_process:
            inproc = measure(settings, args.n, make_payload)
            print(f"in process (no Celery): worker CPU {inproc['worker_ms']:.2f} ms/job "
                  f"(register() {inproc['fit_ms']:.2f}), PostgreSQL backends {inproc['postgres_ms']:.2f} ms/job; "
                  f"Celery's share {worker_ms - inproc['worker_ms']:.2f} ms/job")  # fmt: skip
            figures["in_process"] = {k: inproc[k] for k in ("worker_ms", "fit_ms", "postgres_ms")}
            figures["celery_share_ms"] = worker_ms - inproc["worker_ms"]
    _write(args.out, figures)
    return 0


def _write(out: Path | None, figures: dict[str, object]) -> None:
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    run_tool(main, "celerycost")
