"""The load benchmark command: its CPU accounting, its exit status, and real runs with a fault
against a spawned distributed service (PostgreSQL + Redis + a `spine worker`)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import psycopg
import pytest

from services.core.jobqueue import make_celery
from tests.conftest import PG_ADMIN_URL, Service, _purge_queue
from tools import loadbench


def test_cpu_per_job_is_the_difference_of_two_readings_divided_by_jobs() -> None:
    before = {"api": 1.0, "worker": 2.0}
    after = {"api": 1.5, "worker": 4.0}
    assert loadbench.cpu_ms_per_job(before, after, 100) == {"api": 5.0, "worker": 20.0, "total": 25.0}
    assert loadbench.cpu_ms_per_job({}, after, 100) == {}


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="no /proc on this machine: CPU by role is not read")
def test_cpu_reading_counts_the_load_generator_itself() -> None:
    first = loadbench.cpu_seconds_by_role()
    start = time.process_time()
    while time.process_time() - start < 0.1:  # 0.1 s of CPU in this process: ten clock ticks
        sum(i * i for i in range(10_000))
    second = loadbench.cpu_seconds_by_role()
    assert set(first) == {"api", "worker", "postgres", "redis", "load generator"}
    assert second["load generator"] > first["load generator"]


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="no /proc on this machine: CPU by process is not read")
def test_the_cpu_of_a_process_is_read_before_it_is_killed() -> None:
    """A fault's killed processes leave /proc with their CPU time: the bench reads it just before the
    kill (``Fault.cpu_s_of_killed``), else a worker killed early made the phase's worker CPU negative."""
    burner = subprocess.Popen([sys.executable, "-c", "import time\nt = time.process_time()\n"
                               "while time.process_time() - t < 0.2: pass\ntime.sleep(60)"])  # fmt: skip
    try:
        deadline = time.monotonic() + 30
        while loadbench.cpu_seconds_of([burner.pid]) < 0.2 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert loadbench.cpu_seconds_of([burner.pid, os.getpid()]) >= 0.2
    finally:
        burner.kill()
        burner.wait()
    assert loadbench.cpu_seconds_of([burner.pid]) == 0.0


def test_exit_status_flags_lost_jobs_and_two_outcomes() -> None:
    fine = {"jobs_lost": 0, "jobs_with_two_outcomes": 0}
    assert loadbench.exit_code({"throughput": fine}) == 0
    assert loadbench.exit_code({"throughput": {**fine, "jobs_lost": 1}}) == 1
    assert loadbench.exit_code({"latency": fine, "throughput": {**fine, "jobs_with_two_outcomes": 2}}) == 1
    assert loadbench.exit_code({}) == 1


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.fixture
def bench_env(tmp_path: Path, postgres_store_url: str, redis_url: str) -> Iterator[dict[str, str]]:
    """The environment of a bench that spawns the distributed service: a database and a queue of its
    own, dropped and purged afterwards."""
    database = postgres_store_url.rsplit("/", 1)[0] + f"/spine_test_loadbench_{uuid.uuid4().hex[:8]}"
    queue = f"spine-test-{uuid.uuid4().hex[:8]}"
    yield {**os.environ, "DATABASE_URL": database, "CELERY_BROKER_URL": redis_url, "SPINE_QUEUE_NAME": queue,
           "SPINE_DATA_DIR": str(tmp_path / "data")}  # fmt: skip
    _purge_queue(redis_url, queue)
    with psycopg.connect(PG_ADMIN_URL, autocommit=True) as admin:
        admin.execute(f'DROP DATABASE IF EXISTS "{database.rsplit("/", 1)[1]}" WITH (FORCE)')


@pytest.mark.integration
@pytest.mark.parametrize(
    ("fault", "submission"),
    [("kill-worker", ["--concurrency", "8"]), ("restart-redis", ["--batch", "20", "--concurrency", "2"])],
    ids=["kill-worker", "restart-redis-batches"],
)
def test_a_run_with_a_fault_recovers_in_seconds(tmp_path: Path, bench_env: dict[str, str], fault: str,
                                                submission: list[str]) -> None:  # fmt: skip
    """The bench against a spawned distributed service (PostgreSQL + Redis + a `spine worker`), with
    its fault injection: a worker killed by SIGKILL while single POSTs come, or the
    bench's own Redis restarted for 3 s while batches come; every job ends once, within 30 s of
    the last submission (the target of docs/reliability.md, "Recovery time under faults"), and the
    report carries the rates and CPU figures docs/performance.md quotes."""
    out = tmp_path / "report.json"
    cmd = [sys.executable, "-m", "tools.loadbench", "--spawn", "--url", f"http://127.0.0.1:{_free_port()}",
           "--phases", "throughput", "--jobs", "200", *submission, "--warmup-seconds", "0",
           "--recheck-seconds", "0.5", "--max-seconds", "150", "--log-dir", str(tmp_path / "logs"),
           "--output", str(out), "--fault", fault, "--fault-at", "0.3",
           *(["--own-redis"] if fault == "restart-redis" else [])]  # fmt: skip
    done = subprocess.run(cmd, env=bench_env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    report = json.loads(out.read_text())
    assert report["spawned"]["workers_answering"] == 1  # measured once the worker answered, not after a guess
    run = report["throughput"]
    in_flight = run["fault"]["in_flight_at_fault"]
    assert in_flight["queued"] + in_flight["running"] > 0, run["fault"]  # the fault hit jobs in flight
    if fault == "kill-worker":
        assert run["fault"]["killed_pids"] >= 2  # the Celery process and its pool
    assert run["jobs_submitted"] == 200 and run["submit_errors"] == 0  # every POST, during the fault too, got 202
    assert run["statuses"] == {"succeeded": 200}
    assert run["jobs_lost"] == 0 and run["jobs_with_two_outcomes"] == 0
    assert run["last_submission_to_last_final_s"] <= 30, (run, _warnings_logged(tmp_path / "logs"))
    assert run["completed_per_s"] > 0
    assert run["cpu_ms_per_job"]["worker"] > 0 and run["cpu_ms_per_job"]["api"] > 0


@pytest.mark.integration
def test_a_spawned_worker_is_ready_when_its_own_node_answers_a_ping(distributed_service: Service) -> None:
    """``--spawn`` measures once each worker it started answers a ping; another service's workers on
    the same broker (the parallel tests' here) answer too and are not counted."""
    assert distributed_service.worker is not None
    app = make_celery(distributed_service.settings)
    try:
        assert loadbench.workers_answering(app, [distributed_service.worker.pid], timeout_s=2.0) == 1
        assert loadbench.workers_answering(app, [os.getpid()], timeout_s=1.0) == 0  # no worker in this session
    finally:
        app.close()


def _warnings_logged(log_dir: Path, limit: int = 6000) -> str:
    """The spawned service's log lines above INFO (the fault's trace: reconnections, restarts, the
    reconciler's passes), each cut to 300 characters, the last ``limit`` characters of them: what a
    slow recovery in CI is read from."""
    lines = []
    for log in sorted(log_dir.glob("*.log")):
        lines += [f"{log.name}: {line[:300]}" for line in log.read_text(errors="replace").splitlines()
                  if line.strip() and '"level": "INFO"' not in line]  # fmt: skip
    return "\n".join(lines)[-limit:]


def _session_members(session_ids: set[int]) -> set[int]:
    """Live processes whose session is one of ``session_ids`` (the bench starts each service process
    in its own session, so a session holds that process and its children: a worker's pool)."""
    return {pid for pid, fields in loadbench.proc_stats().items() if fields[0] != "Z" and int(fields[3]) in session_ids}


def _jobs_succeeded(database_url: str) -> int:
    """Succeeded jobs in the bench's database (0 while its migration has not made the table yet)."""
    try:
        with psycopg.connect(database_url.replace("postgresql+psycopg://", "postgresql://", 1),
                             connect_timeout=3) as conn:  # fmt: skip
            row = conn.execute("SELECT count(*) FROM jobs WHERE status = 'succeeded'").fetchone()
    except psycopg.Error:
        return 0
    return int(row[0]) if row else 0


@pytest.mark.parametrize("stop_signal", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_interrupts_a_pending_asyncio_gather(stop_signal: signal.Signals) -> None:
    """``run_tool``: SIGTERM or SIGINT raises KeyboardInterrupt out of ``asyncio.run`` even
    while a ``gather`` is pending (the load bench's phases), so the tool's ``finally`` runs. Without
    it SIGTERM kills the process at once, and SIGINT only cancels the main task (seen absorbed)."""
    script = f"""
import asyncio, os, signal
from tools.processes import run_tool
async def phase():
    asyncio.get_running_loop().call_later(0.2, os.kill, os.getpid(), signal.{stop_signal.name})
    await asyncio.gather(*(asyncio.sleep(30) for _ in range(3)))
def main():
    try:
        asyncio.run(phase())
    finally:
        print("finally ran")
    return 0
run_tool(main, "tool")
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=20)
    assert (done.returncode, done.stdout.strip()) == (130, "finally ran"), done.stderr
    assert f"tool: stopped by {stop_signal.name}" in done.stderr


def test_a_signal_lost_in_a_finaliser_is_raised_again() -> None:
    """Python drops an exception raised while a finaliser runs ("Exception ignored in ..."): a
    SIGTERM handled inside ``__del__`` is lost (seen: the load bench ran on after one SIGTERM).
    ``run_tool`` interrupts the main thread again until the tool stops: here within about a second,
    where the tool would otherwise sleep 20 s."""
    script = """
import os, signal, time
from tools.processes import run_tool
class Finaliser:
    def __del__(self):
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(100_000):  # the handler runs in here: its KeyboardInterrupt is dropped
            pass
def main():
    try:
        Finaliser()
        time.sleep(20)
    finally:
        print("finally ran")
    return 0
run_tool(main, "tool")
"""
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=30)
    assert (done.returncode, done.stdout.strip()) == (130, "finally ran"), done.stderr
    assert "Exception ignored" in done.stderr  # the first interrupt was indeed lost
    assert time.monotonic() - started < 10


@pytest.mark.integration
def test_a_terminated_bench_stops_the_service_it_spawned(tmp_path: Path, bench_env: dict[str, str]) -> None:
    """SIGTERM (a QA script's timeout) in the middle of a phase: the bench exits with 130 and stops
    the API and the worker with its pool. Before, they kept running after the bench had gone."""
    url = f"http://127.0.0.1:{_free_port()}"
    cmd = [sys.executable, "-m", "tools.loadbench", "--spawn", "--url", url, "--phases", "latency",
           "--rate", "5", "--rate-seconds", "600", "--warmup-seconds", "0", "--max-seconds", "700",
           "--log-dir", str(tmp_path / "logs")]  # fmt: skip
    sessions: set[int] = set()
    bench = subprocess.Popen(cmd, env=bench_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and len(sessions) < 2:  # the API and the worker
            time.sleep(0.5)
            sessions = {pid for pid, fields in loadbench.proc_stats().items() if int(fields[1]) == bench.pid}
        assert len(sessions) == 2, "the bench did not start the API and a worker"
        deadline = time.monotonic() + 90  # the phase runs and the worker's pool fits its jobs; POSTs in flight
        while time.monotonic() < deadline and bench.poll() is None and not _jobs_succeeded(bench_env["DATABASE_URL"]):
            time.sleep(0.2)
        assert _jobs_succeeded(bench_env["DATABASE_URL"]), "no job of the bench's phase succeeded"
        started = _session_members(sessions)
        assert len(started) >= 3, started  # API, the worker's main process and at least one pool process
        bench.send_signal(signal.SIGTERM)
        _, err = bench.communicate(timeout=60)
        assert bench.returncode == 130, err[-2000:]
        assert "stopped by" in err
        deadline = time.monotonic() + 10  # a pool process may end just after its parent
        while _session_members(sessions) and time.monotonic() < deadline:
            time.sleep(0.2)
        left = {pid: Path(f"/proc/{pid}/cmdline").read_bytes() for pid in _session_members(sessions)}
        assert left == {}
    finally:
        if bench.poll() is None:
            bench.kill()
            bench.wait()
        for pid in _session_members(sessions):  # what a failed stop left behind
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
