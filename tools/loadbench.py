"""Load benchmark of a running spine service on this machine (``python -m tools.loadbench``).

Two phases, both bounded in count and time, traffic only to a loopback address:

1. ``latency``: single POST /v1/jobs at a fixed rate (open loop), POST latency p50/p99.
2. ``throughput``: N jobs submitted as fast as the API takes them (single POSTs with C in flight,
   or batches), then waits until every job is final: submitted/s, completed/s, POST→result.

Afterwards it reads every job back twice, a few seconds apart: a job not final (or missing) is
*lost*; a job whose outcome changed between the reads has *two outcomes*. Each phase also gives
the CPU time per job of each role on this machine (API, workers, PostgreSQL, Redis, the load
generator itself). Exit status 1 when a job was lost or had two outcomes.

``--spawn`` starts the service itself (migrate, ``spine serve --no-worker`` and W ``spine worker``
processes) from the environment's DATABASE_URL / CELERY_BROKER_URL, measures once the API answers
/readyz and every worker a ping (the report's ``spawned``), and stops it at the end;
``--own-redis`` starts a throwaway ``redis-server`` on a free loopback port as the broker.

``--fault`` injects one fault into the throughput phase once ``--fault-at`` of its jobs were
submitted: ``kill-worker`` sends SIGKILL to the first worker's Celery process group (its
supervisor starts it again), ``restart-redis`` stops the own Redis (its messages are lost with
it) and starts it again ``--fault-seconds`` later. The report then gives the jobs in flight
(queued or running, from /metrics) when the fault hit, and, as for every throughput phase, the
time from the last submission to the last job final.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import ipaddress
import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import aiohttp
import httpx
from celery import Celery

from services.cli.service_commands import worker_node_pid
from services.core.config import Settings
from services.core.jobqueue import make_celery
from spine_client.landmarks import LEVELS  # the contract's level names (a client's view)
from tools.processes import run_tool, stop_processes

FINAL = {"succeeded", "failed", "cancelled"}
SPAWN_READY_S = 60.0
"""How long ``--spawn`` waits for its API to answer /readyz and every worker to answer a ping."""
IDENTITY = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]


def payload(i: int) -> dict[str, Any]:
    """A plausible PA payload whose curve varies with ``i`` (17 endplate midpoints, T1/L5 poses)."""
    curve = 5.0 + (i % 30)
    landmarks = [
        {"level": lv, "point": [round(100 + curve * math.sin(math.pi * k / 16), 3), round(50 + 420 * k / 16, 3)]}
        for k, lv in enumerate(LEVELS)
    ]
    return {
        "pa": {"landmarks": landmarks},
        "boundary": {
            "T1": {"position": [0.0, 0.0, 0.0], "directors": IDENTITY},
            "L5": {"position": [0.0, 0.0, -420.0], "directors": IDENTITY},
        },
    }


def pct(values: Sequence[float], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, math.ceil(q * len(ordered)) - 1))]


def check_loopback(url: str) -> None:
    host = urlparse(url).hostname or ""
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if not loopback:
        raise SystemExit(f"refusing to load {url}: the benchmark only targets loopback addresses")


@dataclass
class Phase:
    name: str
    sent_at: dict[str, float] = field(default_factory=dict)  # job id -> wall time the POST was sent
    latencies_ms: list[float] = field(default_factory=list)
    errors: int = 0
    error_kinds: dict[str, int] = field(default_factory=dict)  # why: an exception's name or "HTTP <status>"
    started: float = 0.0
    submitted_by: float = 0.0


CLIENT_ERRORS = (aiohttp.ClientError, asyncio.TimeoutError)
"""What a request of the load generator can fail with (refused, reset, timed out)."""


def count_error(phase: Phase, kind: str, jobs: int) -> None:
    phase.errors += jobs
    phase.error_kinds[kind] = phase.error_kinds.get(kind, 0) + jobs


async def post_one(client: aiohttp.ClientSession, phase: Phase, i: int) -> None:
    sent = time.time()
    t0 = time.perf_counter()
    try:
        async with client.post("/v1/jobs", json=payload(i)) as response:
            status = response.status
            body = await response.json() if status == 202 else None
    except CLIENT_ERRORS as exc:
        count_error(phase, type(exc).__name__, 1)
        return
    phase.latencies_ms.append((time.perf_counter() - t0) * 1000)
    if body is not None:
        phase.sent_at[body["id"]] = sent
    else:
        count_error(phase, f"HTTP {status}", 1)


async def post_batch(client: aiohttp.ClientSession, phase: Phase, start: int, size: int) -> None:
    sent = time.time()
    t0 = time.perf_counter()
    try:
        async with client.post("/v1/jobs/batch", json={"jobs": [payload(start + k) for k in range(size)]}) as response:
            status = response.status
            body = await response.json() if status == 200 else {}
    except CLIENT_ERRORS as exc:
        count_error(phase, type(exc).__name__, size)
        return
    phase.latencies_ms.append((time.perf_counter() - t0) * 1000)
    if status != 200:
        count_error(phase, f"HTTP {status}", size)
    for entry in body.get("results", []):
        if entry.get("job"):
            phase.sent_at[entry["job"]["id"]] = sent
        else:
            count_error(phase, f"entry {entry.get('status')}", 1)


async def fixed_rate(client: aiohttp.ClientSession, rate: float, seconds: float) -> Phase:
    phase = Phase("latency", started=time.time())
    count = int(rate * seconds)
    t0 = time.perf_counter()
    tasks = []
    for i in range(count):
        delay = t0 + i / rate - time.perf_counter()
        if delay > 0:
            await asyncio.sleep(delay)
        tasks.append(asyncio.create_task(post_one(client, phase, i)))
    await asyncio.gather(*tasks)
    phase.submitted_by = time.time()
    return phase


async def flood(
    client: aiohttp.ClientSession, jobs: int, concurrency: int, batch: int, deadline: float, fault: Fault | None = None
) -> Phase:
    phase = Phase("throughput", started=time.time())
    next_index = 0

    async def lane() -> None:
        nonlocal next_index
        while next_index < jobs and time.monotonic() < deadline:
            if fault is not None and not fault.started and next_index >= fault.at_job:
                fault.started = True
                fault.task = asyncio.ensure_future(fault.inject(client))
            start = next_index
            size = min(batch, jobs - start)
            next_index += size
            if batch == 1:
                await post_one(client, phase, start)
            else:
                await post_batch(client, phase, start, size)

    await asyncio.gather(*(lane() for _ in range(concurrency)))
    phase.submitted_by = time.time()
    if fault is not None and fault.task is not None:
        await fault.task
    return phase


async def get_text(client: aiohttp.ClientSession, path: str) -> str:
    async with client.get(path) as response:
        return await response.text()


async def jobs_in_flight(client: aiohttp.ClientSession) -> dict[str, int]:
    """Queued and running jobs now, from the API's /metrics (``spine_jobs{status=...}``)."""
    counts = {"queued": 0, "running": 0}
    for line in (await get_text(client, "/metrics")).splitlines():
        for status in counts:
            if line.startswith(f'spine_jobs{{status="{status}"}}'):
                counts[status] = int(float(line.rsplit(" ", 1)[1]))
    return counts


@dataclass
class Fault:
    """One fault injected into the throughput phase (``--fault``)."""

    kind: str
    at_job: int
    seconds: float
    worker: subprocess.Popen[bytes] | None = None
    redis: OwnRedis | None = None
    started: bool = False
    task: asyncio.Future[None] | None = None
    report: dict[str, Any] = field(default_factory=dict)
    cpu_s_of_killed: dict[str, float] = field(default_factory=dict)
    """CPU seconds, by role, of the processes the fault killed, read just before: a dead process
    leaves ``/proc`` with its time, which the phase's CPU figures must still count."""

    async def inject(self, client: aiohttp.ClientSession) -> None:
        self.report["in_flight_at_fault"] = await jobs_in_flight(client)
        self.report["at"] = time.time()
        if self.kind == "kill-worker":
            assert self.worker is not None
            killed = worker_pids(self.worker.pid)
            self.cpu_s_of_killed["worker"] = cpu_seconds_of(killed)
            for pid in killed:  # the Celery process and its pool: the supervisor starts it again
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            self.report["killed_pids"] = len(killed)
        elif self.kind == "restart-redis":
            assert self.redis is not None
            if self.redis.proc is not None:
                self.cpu_s_of_killed["redis"] = cpu_seconds_of([self.redis.proc.pid])
            self.redis.stop()
            await asyncio.sleep(self.seconds)
            self.redis.start()
        self.report["done"] = time.time()


def proc_stat(pid: int) -> list[str] | None:
    """The fields of ``/proc/<pid>/stat`` after the command name (proc(5): state, parent, process
    group, session, …, utime and stime at 11 and 12); None when the process is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat[stat.rfind(")") + 2 :].split()


def proc_stats() -> dict[int, list[str]]:
    """``proc_stat`` of every process of this machine."""
    stats = {int(entry.name): proc_stat(int(entry.name)) for entry in Path("/proc").iterdir() if entry.name.isdigit()}
    return {pid: fields for pid, fields in stats.items() if fields is not None}


def worker_pids(supervisor: int) -> list[int]:
    """The processes under a ``spine worker`` supervisor (its Celery child and that child's pool)."""
    children: dict[int, list[int]] = {}
    for pid, fields in proc_stats().items():
        children.setdefault(int(fields[1]), []).append(pid)
    found, todo = [], list(children.get(supervisor, []))
    while todo:
        pid = todo.pop()
        found.append(pid)
        todo.extend(children.get(pid, []))
    return found


class OwnRedis:
    """A throwaway redis-server on a free loopback port (no persistence: a restart loses every message)."""

    def __init__(self, log_dir: Path):
        self.port = free_port()
        self.log_dir = log_dir
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        cmd = ["redis-server", "--bind", "127.0.0.1", "--port", str(self.port), "--save", "", "--appendonly", "no"]
        self.proc = _start(cmd, dict(os.environ), self.log_dir / "redis.log")
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", self.port), timeout=0.2):
                return
            time.sleep(0.05)
        raise SystemExit("the throwaway redis-server did not start; see " + str(self.log_dir / "redis.log"))

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


async def wait_final(client: aiohttp.ClientSession, since: datetime, deadline: float) -> None:
    params = [("status", "queued"), ("status", "running"), ("created_after", since.isoformat()), ("limit", "1")]
    while time.monotonic() < deadline:
        async with client.get("/v1/jobs", params=params) as response:
            if response.status == 200 and not (await response.json())["jobs"]:
                return
        await asyncio.sleep(1.0)


async def read_back(client: aiohttp.ClientSession, since: datetime) -> dict[str, tuple[str, str | None, str | None]]:
    """id -> (status, started_at, finished_at) of every job created since ``since``."""
    seen: dict[str, tuple[str, str | None, str | None]] = {}
    cursor = None
    while True:
        params: dict[str, str | int] = {"created_after": since.isoformat(), "limit": 500}
        if cursor:
            params["cursor"] = cursor
        async with client.get("/v1/jobs", params=params, timeout=aiohttp.ClientTimeout(total=60)) as response:
            page = await response.json()
        for job in page["jobs"]:
            seen[job["id"]] = (job["status"], job["started_at"], job["finished_at"])
        cursor = page["next_cursor"]
        if not cursor:
            return seen


def summarize(phase: Phase, first: dict[str, Any], second: dict[str, Any]) -> dict[str, Any]:
    ids = list(phase.sent_at)
    lost = [i for i in ids if i not in first or first[i][0] not in FINAL]
    changed = [i for i in ids if i in first and i in second and first[i] != second[i]]
    finished = {i: datetime.fromisoformat(first[i][2]).timestamp() for i in ids if i not in lost and first[i][2]}
    e2e = [finished[i] - phase.sent_at[i] for i in finished]
    statuses: dict[str, int] = {}
    for i in ids:
        status = first.get(i, ("missing",))[0]
        statuses[status] = statuses.get(status, 0) + 1
    submit_span = max(phase.submitted_by - phase.started, 1e-9)
    out: dict[str, Any] = {
        "jobs_submitted": len(ids),
        "submit_errors": phase.errors,
        "submit_errors_by_kind": phase.error_kinds,
        "submitted_per_s": round(len(ids) / submit_span, 1),
        "post_latency_ms_p50": round(pct(phase.latencies_ms, 0.5), 2),
        "post_latency_ms_p99": round(pct(phase.latencies_ms, 0.99), 2),
        "statuses": statuses,
        "jobs_lost": len(lost),
        "jobs_with_two_outcomes": len(changed),
        "post_to_result_s_p50": round(pct(e2e, 0.5), 3),
        "post_to_result_s_p99": round(pct(e2e, 0.99), 3),
    }
    if finished:
        times = sorted(finished.values())
        out["last_submission_to_last_final_s"] = round(times[-1] - phase.submitted_by, 2)
        out["completed_per_s"] = round(len(times) / max(times[-1] - phase.started, 1e-9), 1)
        lo, hi = times[len(times) // 10], times[(len(times) * 9) // 10]
        out["completed_per_s_steady_p10_p90"] = round(0.8 * len(times) / max(hi - lo, 1e-9), 1)
    return out


ROLES = (("api", "services.cli serve"), ("worker", "services.cli worker"), ("postgres", "postgres:"),
         ("redis", "redis-server"))  # fmt: skip
"""Which process does what, by a piece of its command line (this machine's processes only)."""


SPAWNED_ROLES = ("api", "worker")
"""Roles whose processes a ``--spawn`` run started itself (each in its own session)."""


def cpu_seconds_by_role(sessions: Collection[int] = ()) -> dict[str, float]:
    """CPU time (user + system, s) used so far by this machine's processes of each role.

    Read from ``/proc/<pid>/stat``; the load generator is this process. With ``sessions`` (the
    session ids of the processes a ``--spawn`` run started) the API and worker roles count only the
    processes of those sessions: another service on the machine (a test running beside the bench)
    neither adds its time nor, by exiting, takes it away. Processes that exit between two readings
    take their time with them (none should during a phase). Empty where there is no ``/proc``.
    """
    proc = Path("/proc")
    if not proc.is_dir():
        return {}
    totals = {role: 0.0 for role, _ in ROLES}
    for entry in proc.iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        role = next((r for r, marker in ROLES if marker in cmdline), None)
        if role is None:
            continue
        fields = proc_stat(int(entry.name))
        if fields is None or (role in SPAWNED_ROLES and sessions and int(fields[3]) not in sessions):
            continue
        totals[role] += cpu_seconds_in(fields)
    mine = os.times()
    totals["load generator"] = mine.user + mine.system
    return totals


def cpu_seconds_of(pids: Sequence[int]) -> float:
    """CPU time (user + system, s) used so far by these processes (``/proc/<pid>/stat`` fields 14
    and 15, in clock ticks); a process already gone counts 0."""
    return sum(cpu_seconds_in(fields) for fields in map(proc_stat, pids) if fields is not None)


def cpu_seconds_in(fields: list[str]) -> float:
    """CPU time (user + system, s) of one ``proc_stat`` reading (fields 14 and 15, clock ticks)."""
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def cpu_ms_per_job(before: dict[str, float], after: dict[str, float], jobs: int) -> dict[str, float]:
    """CPU milliseconds per job of each role between two ``cpu_seconds_by_role`` readings."""
    if not before or jobs <= 0:
        return {}
    per_job = {role: round(1000 * (after[role] - before[role]) / jobs, 2) for role in after}
    per_job["total"] = round(sum(per_job.values()), 2)
    return per_job


async def run(args: argparse.Namespace) -> dict[str, Any]:
    deadline = time.monotonic() + args.max_seconds
    # Open loop: enough connections that a slow answer never makes the next request wait for one.
    pool = max(args.concurrency, int(args.rate)) + 4
    report: dict[str, Any] = {"url": args.url}
    headers = {"Authorization": f"Bearer {args.api_key}"} if args.api_key else {}
    # aiohttp, not httpx: the generator shares the service's cores, and httpx took about 3 times its
    # CPU per POST (4.3-4.5 against 1.2-1.5 ms here, docs/performance.md).
    # Idle connections closed after 2 s, before uvicorn closes its side (timeout_keep_alive, 5 s): aiohttp
    # does not send a POST again on a kept-alive connection the server has closed meanwhile
    # (ServerDisconnectedError; 100-800 jobs of 3,000 were lost that way before).
    connector = aiohttp.TCPConnector(limit=pool, keepalive_timeout=2.0)
    async with aiohttp.ClientSession(base_url=args.url, timeout=aiohttp.ClientTimeout(total=30), headers=headers,
                                     connector=connector) as client:  # fmt: skip
        if args.warmup_seconds > 0:  # connections, caches and workers warm; not counted
            warm = await fixed_rate(client, args.rate, args.warmup_seconds)
            await wait_final(client, datetime.fromtimestamp(warm.started).astimezone(), deadline)
        for phase_name in args.phases:
            histogram_before = await server_histogram(client)
            load_before = os.getloadavg()
            cpu_before = cpu_seconds_by_role(args.service_sessions)
            since = datetime.now().astimezone()
            fault: Fault | None = None
            if phase_name == "latency":
                phase = await fixed_rate(client, args.rate, args.rate_seconds)
            else:
                if args.fault != "none":
                    worker = args.worker_procs[0] if args.worker_procs else None
                    fault = Fault(args.fault, int(args.jobs * args.fault_at), args.fault_seconds, worker=worker,
                                  redis=args.own_redis_server)  # fmt: skip
                phase = await flood(client, args.jobs, args.concurrency, args.batch, deadline, fault)
            await wait_final(client, since, deadline)
            cpu_after = cpu_seconds_by_role(args.service_sessions)  # before the read-back (not the service's load)
            for role, seconds in fault.cpu_s_of_killed.items() if fault is not None else ():
                cpu_after[role] += seconds
            first = await read_back(client, since)
            await asyncio.sleep(args.recheck_seconds)
            second = await read_back(client, since)
            report[phase_name] = summarize(phase, first, second)
            if phase_name == "throughput" and args.fault != "none" and fault is not None:
                report[phase_name]["fault"] = {"kind": args.fault, **fault.report}
            report[phase_name]["cpu_ms_per_job"] = cpu_ms_per_job(cpu_before, cpu_after, len(phase.sent_at))
            server = diff_histogram(await server_histogram(client), histogram_before)
            report[phase_name]["server_post_ms_p50_bucket"] = bucket_quantile(server, 0.5)
            report[phase_name]["server_post_ms_p99_bucket"] = bucket_quantile(server, 0.99)
            report[phase_name]["loadavg_1m_before_after"] = [round(load_before[0], 2), round(os.getloadavg()[0], 2)]
            print(json.dumps({phase_name: report[phase_name]}, indent=2), flush=True)
    return report


async def server_histogram(client: aiohttp.ClientSession) -> dict[float, float]:
    """Cumulative bucket counts of the API's own POST /v1/jobs and /batch timings (from /metrics)."""
    text = await get_text(client, "/metrics")
    buckets: dict[float, float] = {}
    for line in text.splitlines():
        if line.startswith("spine_http_request_duration_seconds_bucket") and 'method="POST"' in line:
            if 'route="/v1/jobs"' not in line and 'route="/v1/jobs/batch"' not in line:
                continue
            le = line.split('le="', 1)[1].split('"', 1)[0]
            bound = float("inf") if le == "+Inf" else float(le)
            buckets[bound] = buckets.get(bound, 0.0) + float(line.rsplit(" ", 1)[1])
    return buckets


def diff_histogram(after: dict[float, float], before: dict[float, float]) -> dict[float, float]:
    return {le: n - before.get(le, 0.0) for le, n in after.items()}


def bucket_quantile(buckets: dict[float, float], q: float) -> str:
    """The upper bound (ms) of the histogram bucket holding the q-quantile, e.g. '<= 25 ms'."""
    total = buckets.get(float("inf"), 0.0)
    if total <= 0:
        return "n/a"
    for le in sorted(buckets):
        if buckets[le] >= q * total:
            return "> 10000 ms" if le == float("inf") else f"<= {le * 1000:g} ms"
    return "n/a"


# ------------------------------------------------------------------ spawning the service


def ensure_database(url: str) -> None:
    """Create the PostgreSQL database of ``url`` if it does not exist yet."""
    if not url.startswith("postgresql"):
        return
    import psycopg
    from sqlalchemy.engine import make_url

    target = make_url(url)
    conninfo = target.set(drivername="postgresql", database="postgres").render_as_string(hide_password=False)
    with psycopg.connect(conninfo, autocommit=True) as conn:
        if conn.execute("SELECT 1 FROM pg_database WHERE datname = %s", (target.database,)).fetchone() is None:
            conn.execute(f'CREATE DATABASE "{target.database}"')


def api_ready(url: str) -> bool:
    """Whether the API at ``url`` answers ``/readyz`` with 200."""
    try:
        return httpx.get(url + "/readyz", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def spawn(args: argparse.Namespace, log_dir: Path, procs: list[subprocess.Popen[bytes]]) -> None:
    """Start the API and the workers, appending each process to ``procs`` as it starts (so that the
    caller stops them whenever this is interrupted), and wait until the API is ready."""
    env = dict(os.environ)
    if "DATABASE_URL" not in env or "CELERY_BROKER_URL" not in env:
        raise SystemExit("--spawn measures the distributed service: set DATABASE_URL and CELERY_BROKER_URL")
    ensure_database(env["DATABASE_URL"])
    spine = [sys.executable, "-m", "services.cli"]
    subprocess.run([*spine, "migrate"], env=env, check=True, capture_output=True)
    if not args.api_key:  # an admin key (not capped), printed alone on the last line
        created = subprocess.run([*spine, "keys", "create", "--name", "loadbench", "--role", "admin"], env=env,
                                 check=True, capture_output=True, text=True)  # fmt: skip
        args.api_key = created.stdout.strip().splitlines()[-1]
    port = urlparse(args.url).port or 80
    log_dir.mkdir(parents=True, exist_ok=True)
    api_cmd = [*spine, "serve", "--no-worker", "--host", "127.0.0.1", "--port", str(port),
               "--workers", str(args.api_processes)]  # fmt: skip
    procs.append(_start(api_cmd, env, log_dir / "api.log"))
    args.worker_procs = []
    for w in range(args.workers):
        cmd = [*spine, "worker", "--concurrency", str(args.worker_concurrency), "--loglevel", "WARNING"]
        if args.worker_nice:
            cmd = ["nice", "-n", str(args.worker_nice), *cmd]
        if w > 0:
            cmd.append("--no-beat")
        procs.append(_start(cmd, env, log_dir / f"worker-{w}.log"))
        args.worker_procs.append(procs[-1])
    args.service_sessions = [p.pid for p in procs]  # each started its own session (``_start``)
    started = time.monotonic()
    deadline = started + SPAWN_READY_S
    while not api_ready(args.url):
        if time.monotonic() > deadline:
            raise SystemExit(f"the spawned API did not answer /readyz within {SPAWN_READY_S:g} s; see {log_dir}")
        time.sleep(0.5)
    app = make_celery(Settings())
    try:
        workers = [p.pid for p in args.worker_procs]
        while (answering := workers_answering(app, workers)) < len(workers):
            if time.monotonic() > deadline:
                raise SystemExit(f"{answering} of the {len(workers)} spawned workers answered a ping within "
                                 f"{SPAWN_READY_S:g} s; see {log_dir}")  # fmt: skip
    finally:
        app.close()
    args.spawned = {"workers_answering": answering, "ready_after_s": round(time.monotonic() - started, 2)}


def workers_answering(app: Celery, supervisors: Sequence[int], timeout_s: float = 1.0) -> int:
    """How many of the ``spine worker`` processes ``supervisors`` have a Celery node that answers a
    ping on the broker (Celery's remote control): a worker consuming its queue. Other services' workers
    on the same broker answer too; a node counts when its name's process
    (``services.cli.service_commands.worker_node_pid``) is in a supervisor's session (``_start`` gives each
    its own)."""
    sessions = {pid: int(fields[3]) for pid, fields in proc_stats().items()}
    answered = set()
    for reply in app.control.ping(timeout=timeout_s) or []:
        for node in reply:
            pid = worker_node_pid(node)
            session = sessions.get(pid) if pid is not None else None
            if session is not None and session in supervisors:
                answered.add(session)
    return len(answered)


def _start(cmd: list[str], env: dict[str, str], log: Path) -> subprocess.Popen[bytes]:
    with log.open("wb") as out:
        return subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.loadbench", description=__doc__.splitlines()[0])
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="base URL (loopback only)")
    parser.add_argument("--api-key", default=os.environ.get("SPINE_API_KEY"),
                        help="API key (default $SPINE_API_KEY; --spawn makes an admin key when unset)")  # fmt: skip
    parser.add_argument("--phases", nargs="+", choices=["latency", "throughput"], default=["latency", "throughput"])
    parser.add_argument("--rate", type=float, default=100.0, help="POSTs per second in the latency phase")
    parser.add_argument("--rate-seconds", type=float, default=30.0, help="length of the latency phase")
    parser.add_argument("--jobs", type=int, default=10_000, help="jobs in the throughput phase")
    parser.add_argument("--concurrency", type=int, default=16, help="requests in flight in the throughput phase")
    parser.add_argument("--batch", type=int, default=1, help="payloads per request (>1: POST /v1/jobs/batch)")
    parser.add_argument("--max-seconds", type=float, default=900.0, help="hard bound of the whole run")
    parser.add_argument("--warmup-seconds", type=float, default=3.0, help="uncounted traffic at --rate first")
    parser.add_argument("--recheck-seconds", type=float, default=3.0)
    parser.add_argument("--spawn", action="store_true", help="start API and workers here, stop them after")
    parser.add_argument("--workers", type=int, default=1, help="with --spawn: `spine worker` processes")
    parser.add_argument("--worker-concurrency", type=int, default=2, help="with --spawn: pool size of each")
    parser.add_argument(
        "--worker-nice",
        type=int,
        default=0,
        help="with --spawn: run workers at this niceness, so that fits yield the CPU to the API",
    )
    parser.add_argument("--api-processes", type=int, default=1, help="with --spawn: uvicorn processes")
    parser.add_argument("--log-dir", type=Path, default=Path("bench-out/loadbench"))
    parser.add_argument("--output", type=Path, help="write the JSON report here")
    parser.add_argument("--own-redis", action="store_true",
                        help="with --spawn: a throwaway redis-server on a free port is the broker")  # fmt: skip
    parser.add_argument("--fault", choices=["none", "kill-worker", "restart-redis"], default="none",
                        help="fault in the throughput phase (--spawn; restart-redis: --own-redis)")  # fmt: skip
    parser.add_argument("--fault-at", type=float, default=0.5, help="fraction of the jobs submitted before the fault")
    parser.add_argument("--fault-seconds", type=float, default=3.0, help="how long the restarted Redis stays down")
    args = parser.parse_args(argv)
    args.jobs = min(args.jobs, 100_000)
    args.worker_procs = []
    args.service_sessions = []
    args.spawned = None
    args.own_redis_server = None
    check_loopback(args.url)
    if args.fault != "none" and not args.spawn:
        parser.error("--fault needs --spawn (the bench injects faults into processes it started)")
    if args.fault == "restart-redis" and not args.own_redis:
        parser.error("--fault restart-redis needs --own-redis (never restart a shared Redis)")
    if args.own_redis:
        args.own_redis_server = OwnRedis(args.log_dir)
        args.own_redis_server.start()
        os.environ["CELERY_BROKER_URL"] = args.own_redis_server.url
    procs: list[subprocess.Popen[bytes]] = []
    try:
        try:
            if args.spawn:
                spawn(args, args.log_dir, procs)
            report = asyncio.run(asyncio.wait_for(run(args), timeout=args.max_seconds + 120))
        finally:
            stop_processes(procs)
    finally:
        if args.own_redis_server is not None:
            args.own_redis_server.stop()
    hidden = ("api_key", "worker_procs", "service_sessions", "own_redis_server", "spawned")  # no secret nor process
    report["settings"] = {k: str(v) for k, v in vars(args).items() if k not in hidden}
    if args.spawned is not None:
        report["spawned"] = args.spawned
    if args.output:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(report, indent=2))
    return exit_code(report)


def exit_code(report: dict[str, Any]) -> int:
    """0 when every phase ran with no job lost and none with two outcomes, else 1 (for QA scripts)."""
    phases = [report[name] for name in ("latency", "throughput") if name in report]
    broken = any(p["jobs_lost"] or p["jobs_with_two_outcomes"] for p in phases)
    return 1 if broken or not phases else 0


if __name__ == "__main__":
    run_tool(main, "loadbench")
