"""Fault-injection harness of the reliability tests (tests/integration/test_reliability.py).

- ``OwnPostgres``: a throwaway PostgreSQL cluster (``initdb`` + ``pg_ctl`` from
  /usr/lib/postgresql/*/bin, as the ``postgres`` user when run as root) on a free port, in a temp
  dir, so that stopping it never touches the server the rest of the suite uses.
- ``LiveService``: the real service as processes: ``spine serve --no-worker`` (uvicorn) on a free
  port and ``spine worker`` processes, on the given database and broker, with an API key.
- ``Load``: single ``POST /v1/jobs`` at a fixed rate in a thread, bounded in count and time,
  recording every answer (status, content type, problem type, job id).
- ``settle`` / ``outcome_figures``: wait until every accepted job is final, then count jobs lost
  (accepted but not final, or missing) and jobs with two outcomes (state changed between two reads
  a few seconds apart, more than one stored outcome in the worker logs, a cancelled job with a
  result or measures, a succeeded job without exactly one measures row).

Traffic goes only to 127.0.0.1; every wait is bounded.
"""

from __future__ import annotations

import contextlib
import glob
import json
import os
import pwd
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any, TypeVar

import httpx
import pytest
from sqlalchemy import func, select
from sqlalchemy.exc import OperationalError

from services.core.config import Settings
from services.db.clock import db_now
from services.db.engine import dispose_engines, session_scope
from services.db.migrate import upgrade
from services.db.models import Job, JobMeasures
from tests.conftest import _settings_kwargs, make_key, spine_payload
from tests.interop_helpers import wait_until
from tools.processes import stop_processes

FINAL = {"succeeded", "failed", "cancelled"}
JOB_EVENT = re.compile(r"^job ([0-9a-f-]{36}) (succeeded|failed|skipped|superseded)\b")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# ------------------------------------------------------------------ throwaway servers


class OwnPostgres:
    """A PostgreSQL cluster of our own (initdb) on a free loopback port, in a temp dir."""

    def __init__(self, bindir: Path):
        self.bindir = bindir
        self.port = free_port()
        self.root = Path(tempfile.mkdtemp(prefix="spine-pg-"))
        self.data = self.root / "data"
        self.log = self.root / "postgres.log"
        self.as_postgres: list[str] = []
        if os.geteuid() == 0:  # initdb refuses root: the cluster belongs to the postgres user
            user = pwd.getpwnam("postgres")
            os.chown(self.root, user.pw_uid, user.pw_gid)
            self.as_postgres = ["runuser", "-u", "postgres", "--"]
        self.url = f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/postgres"

    def _run(self, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
        return subprocess.run([*self.as_postgres, *args], capture_output=True, text=True, timeout=timeout,
                              check=False, cwd=self.root)  # fmt: skip

    def init(self) -> None:
        out = self._run(str(self.bindir / "initdb"), "-D", str(self.data), "-A", "trust", "-U", "postgres",
                        "--no-sync", "-E", "UTF8", "--locale=C")  # fmt: skip
        if out.returncode != 0:
            raise RuntimeError(f"initdb failed: {out.stderr[-2000:]}")

    def start(self) -> None:
        options = (f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 -c fsync=off "
                   "-c full_page_writes=off -c max_connections=100")  # fmt: skip
        out = self._run(str(self.bindir / "pg_ctl"), "-D", str(self.data), "-l", str(self.log), "-w", "-t", "30",
                        "-o", options, "start")  # fmt: skip
        if out.returncode != 0:
            raise RuntimeError(f"pg_ctl start failed: {out.stderr[-2000:]}\n{self.log_text()[-2000:]}")

    def stop(self, mode: str = "immediate") -> None:
        self._run(str(self.bindir / "pg_ctl"), "-D", str(self.data), "-m", mode, "-w", "-t", "30", "stop")

    def log_text(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def remove(self) -> None:
        self.stop("immediate")
        shutil.rmtree(self.root, ignore_errors=True)


@contextlib.contextmanager
def own_postgres() -> Iterator[OwnPostgres]:
    bins = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
    if not bins:
        pytest.skip("no initdb under /usr/lib/postgresql/*/bin: the PostgreSQL outage test needs its own cluster")
    if os.geteuid() == 0 and shutil.which("runuser") is None:
        pytest.skip("running as root without runuser: cannot run initdb as the postgres user")
    server = OwnPostgres(Path(bins[-1]).parent)
    try:
        try:
            server.init()
            server.start()
        except (RuntimeError, subprocess.TimeoutExpired, OSError) as exc:
            pytest.skip(f"could not start a throwaway PostgreSQL cluster: {exc}")
        yield server
    finally:
        dispose_engines()
        server.remove()


# ------------------------------------------------------------------ the service as processes


def reliability_env(workdir: Path, database_url: str, broker_url: str, **extra: str) -> dict[str, str]:
    """Settings of a fault test: short timeouts, so that the reconciler acts within seconds."""
    return {
        "SPINE_DATA_DIR": str(workdir),
        "DATABASE_URL": database_url,
        "CELERY_BROKER_URL": broker_url,
        "SPINE_QUEUE_NAME": f"spine-fault-{uuid.uuid4().hex[:8]}",
        "SPINE_WORKER_CONCURRENCY": "2",
        "SPINE_RECONCILE_INTERVAL_S": "1",
        "SPINE_QUEUED_TIMEOUT_S": "3",
        "SPINE_FIT_TIME_LIMIT_S": "5",
        "SPINE_MAX_ATTEMPTS": "3",
        "SPINE_MAX_QUEUED_PER_CLIENT": "0",
        "SPINE_API_KEY_CACHE_S": "2",
        "SPINE_LOG_LEVEL": "INFO",
        **extra,
    }


class LiveService:
    """``spine serve --no-worker`` and ``spine worker`` processes on one database and broker."""

    def __init__(self, workdir: Path, env: dict[str, str]):
        self.workdir = workdir
        self.env = {k: v for k, v in os.environ.items() if k not in ("DATABASE_URL", "CELERY_BROKER_URL")}
        self.env.update(env)
        self.settings = Settings(**_settings_kwargs(env))
        upgrade(self.settings, quiet=True)
        self.api_key = make_key(self.settings, "reliability", "client")
        self.port = free_port()
        self.base_url = f"http://127.0.0.1:{self.port}"
        self.api: subprocess.Popen[bytes] | None = None
        self.workers: list[subprocess.Popen[bytes]] = []
        self.logs: list[Path] = []

    def _spawn(self, args: list[str], log_name: str) -> subprocess.Popen[bytes]:
        log = self.workdir / log_name
        self.logs.append(log)
        with log.open("ab") as out:
            return subprocess.Popen([sys.executable, "-m", "services.cli", *args], env=self.env, stdout=out,
                                    stderr=subprocess.STDOUT, start_new_session=True)  # fmt: skip

    def start_worker(self) -> subprocess.Popen[bytes]:
        proc, name = self._spawn_worker()
        self._wait_worker(proc, name)
        return proc

    def start(self) -> None:
        """The API and one worker, started together (each takes seconds to import), ready both."""
        api = self._spawn_api()
        worker, name = self._spawn_worker()
        self._wait_api(api)
        self._wait_worker(worker, name)

    def _spawn_api(self) -> subprocess.Popen[bytes]:
        self.api = self._spawn(["serve", "--no-worker", "--host", "127.0.0.1", "--port", str(self.port)], "api.log")
        return self.api

    def _wait_api(self, api: subprocess.Popen[bytes]) -> None:
        def up() -> bool:
            assert api.poll() is None, self.text("api.log")[-3000:]
            try:
                return httpx.get(self.base_url + "/healthz", timeout=1).status_code == 200
            except httpx.TransportError:
                return False

        wait_until(up, 60, "the API to answer /healthz", 0.2)

    def _spawn_worker(self) -> tuple[subprocess.Popen[bytes], str]:
        name = f"worker-{len(self.workers)}.log"
        proc = self._spawn(["worker"], name)
        self.workers.append(proc)
        return proc, name

    def _wait_worker(self, proc: subprocess.Popen[bytes], name: str) -> None:
        def ready() -> bool:
            assert proc.poll() is None, self.text(name)[-3000:]
            return " ready." in self.text(name)

        wait_until(ready, 60, "the worker to be ready", 0.2)

    def kill_worker(self, proc: subprocess.Popen[bytes]) -> None:
        """SIGKILL the worker's whole process group: main process, pool processes and beat."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)

    def stop(self) -> None:
        stop_processes([p for p in [self.api, *self.workers] if p is not None], grace_s=20)

    def client(self, timeout: float = 10) -> httpx.Client:
        return httpx.Client(base_url=self.base_url, timeout=timeout,
                            headers={"Authorization": f"Bearer {self.api_key}"})  # fmt: skip

    def text(self, name: str) -> str:
        path = self.workdir / name
        return path.read_text(errors="replace") if path.exists() else ""

    def log_lines(self) -> list[str]:
        return [line for log in self.logs for line in self.text(log.name).splitlines()]

    def stored_outcomes(self) -> Counter[str]:
        """Per job id, the outcomes the workers logged as stored (succeeded or failed)."""
        stored: Counter[str] = Counter()
        for line in self.log_lines():
            if not line.startswith("{"):
                continue
            try:
                msg = str(json.loads(line).get("msg", ""))
            except json.JSONDecodeError:
                continue
            match = JOB_EVENT.match(msg)
            if match and match.group(2) in ("succeeded", "failed"):
                stored[match.group(1)] += 1
        return stored

    def submit_batch(self, n: int, curve0: float = 0.0) -> list[str]:
        with self.client(60) as client:
            body = client.post("/v1/jobs/batch", json={"jobs": [spine_payload(curve_mm=curve0 + i % 40)
                                                                 for i in range(n)]})  # fmt: skip
        assert body.status_code == 200, body.text
        return [e["job"]["id"] for e in body.json()["results"]]

    def _rows(self, query: Any) -> list[Any]:
        """Rows of ``query``; a connection the database dropped (outage test) is retried."""
        for attempt in range(3):
            try:
                with session_scope(self.settings) as s:
                    return list(s.execute(query).all())
            except OperationalError:
                if attempt == 2:
                    raise
                time.sleep(0.5)
        return []

    def statuses(self, ids: list[str]) -> dict[str, tuple[str, int, Any, bool]]:
        """id -> (status, attempts, finished_at, has result), read from the database."""
        wanted = [uuid.UUID(i) for i in ids]
        rows = self._rows(
            select(Job.id, Job.status, Job.attempts, Job.finished_at, Job.result.is_not(None)).where(Job.id.in_(wanted))
        )
        return {str(r[0]): (r[1], r[2], r[3], bool(r[4])) for r in rows}

    def count(self, ids: list[str], status: str) -> int:
        return sum(1 for v in self.statuses(ids).values() if v[0] == status)

    def measures_rows(self, ids: list[str]) -> dict[str, int]:
        wanted = [uuid.UUID(i) for i in ids]
        rows = self._rows(
            select(JobMeasures.job_id, func.count()).where(JobMeasures.job_id.in_(wanted)).group_by(JobMeasures.job_id)
        )
        return {str(job_id): int(n) for job_id, n in rows}


# ------------------------------------------------------------------ load and outcomes


@dataclass
class Answer:
    at: float
    status: int
    content_type: str
    problem_type: str | None
    job_id: str | None
    latency_ms: float


class Load(threading.Thread):
    """POST /v1/jobs at ``rate`` per second until stopped, at most ``max_s`` seconds."""

    def __init__(self, service: LiveService, rate: float, max_s: float):
        super().__init__(daemon=True)
        self.service = service
        self.rate = rate
        self.max_s = max_s
        self.answers: list[Answer] = []
        self.transport_errors = 0
        self._halt = threading.Event()

    def run(self) -> None:
        started = time.monotonic()
        with self.service.client(timeout=15) as client:
            i = 0
            while not self._halt.is_set() and time.monotonic() - started < self.max_s:
                delay = started + i / self.rate - time.monotonic()
                if delay > 0 and self._halt.wait(delay):
                    break
                t0 = time.monotonic()
                try:
                    response = client.post("/v1/jobs", json=spine_payload(curve_mm=10.0 + i % 25))
                except httpx.TransportError:
                    self.transport_errors += 1
                    i += 1
                    continue
                ctype = response.headers.get("content-type", "")
                body = response.json() if "json" in ctype else {}
                self.answers.append(Answer(t0, response.status_code, ctype, body.get("type") if response.status_code
                                           >= 400 else None, body.get("id") if response.status_code == 202 else None,
                                           (time.monotonic() - t0) * 1000))  # fmt: skip
                i += 1

    def stop(self) -> None:
        self._halt.set()
        if self.ident is not None:  # started
            self.join(30)

    def accepted(self) -> list[str]:
        return [a.job_id for a in self.answers if a.status == 202 and a.job_id]

    def latency(self, since: float, until: float) -> str:
        """POST latency (p50 and max) of the answers sent in [since, until)."""
        values = sorted(a.latency_ms for a in self.answers if since <= a.at < until)
        if not values:
            return "no answer"
        return f"POST latency p50 {values[len(values) // 2]:.0f} ms, max {values[-1]:.0f} ms"

    def statuses(self, since: float | None = None, until: float | None = None) -> dict[str, int]:
        picked = [a for a in self.answers if (since is None or a.at >= since) and (until is None or a.at < until)]
        return dict(sorted(Counter(str(a.status) for a in picked).items()))


def settle(service: LiveService, ids: list[str], timeout: float) -> None:
    """Wait until every job of ``ids`` is final (bounded)."""

    def done() -> bool:
        states = service.statuses(ids)
        return len(states) == len(ids) and all(v[0] in FINAL for v in states.values())

    try:
        wait_until(done, timeout, f"{len(ids)} jobs to be final", 0.5)
    except AssertionError:
        states = service.statuses(ids)
        stuck = Counter(v[0] for v in states.values())
        raise AssertionError(f"jobs not final after {timeout} s: {dict(stuck)}, missing {len(ids) - len(states)}; "
                             f"worker log:\n{service.text('worker-0.log')[-3000:]}") from None  # fmt: skip


@dataclass
class FaultFigures:
    test: str
    fault: str
    jobs_submitted: int
    jobs_completed: int
    jobs_lost: int
    jobs_with_two_outcomes: int
    load: str
    answers_during_fault: dict[str, int] = field(default_factory=dict)
    fault_seconds: float = 0.0
    test_seconds: float = 0.0
    notes: str = ""


def outcome_figures(service: LiveService, ids: list[str], recheck_s: float = 2.0) -> dict[str, Any]:
    """Read every job twice, ``recheck_s`` apart; count completed, lost and two-outcome jobs."""
    first = service.statuses(ids)
    time.sleep(recheck_s)
    second = service.statuses(ids)
    measures = service.measures_rows(ids)
    stored = service.stored_outcomes()
    lost = [i for i in ids if i not in first or first[i][0] not in FINAL]
    two = set()
    for i in ids:
        if i in first and i in second and first[i] != second[i]:
            two.add(i)  # changed after it was read as final
        if stored.get(i, 0) > 1:
            two.add(i)  # two runs stored an outcome
        state = first.get(i)
        if state is None:
            continue
        if state[0] == "cancelled" and (state[3] or measures.get(i, 0)):
            two.add(i)  # cancelled, and yet a result
        if state[0] == "succeeded" and (not state[3] or measures.get(i, 0) != 1):
            two.add(i)
    counts = Counter(v[0] for v in first.values())
    return {
        "submitted": len(ids),
        "completed": counts.get("succeeded", 0),
        "statuses": dict(counts),
        "lost": len(lost),
        "two_outcomes": len(two),
        "lost_ids": lost[:5],
        "two_outcome_ids": sorted(two)[:5],
    }


def report(figures: FaultFigures, capsys: pytest.CaptureFixture[str]) -> None:
    """Print the figures (and append them to $SPINE_RELIABILITY_OUT, JSON lines, when set)."""
    line = json.dumps(asdict(figures))
    out = os.environ.get("SPINE_RELIABILITY_OUT")
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        with Path(out).open("a") as f:
            f.write(line + "\n")
    with capsys.disabled():
        print(f"\nreliability: {line}")


def payload_in_logs(service: LiveService) -> list[str]:
    """Log lines that carry payload content (landmarks or boundary poses): must be none."""
    return [line for line in service.log_lines() if '"landmarks"' in line or "landmarks" in line
            or '"boundary"' in line or "directors" in line]  # fmt: skip


class SkewedClock:
    """A process's ``utcnow`` whose clock is ``offset`` away from the host's: patched into the modules of
    the process that acts, to inject a clock skew while the database stays real (and keeps its clock)."""

    def __init__(self) -> None:
        self.offset = timedelta(0)

    def __call__(self) -> datetime:
        return datetime.now(UTC) + self.offset


def db_clock(settings: Settings) -> datetime:
    """The database's clock (``services.db.clock``), on which leases and due times are written."""
    with session_scope(settings) as session:
        now = session.scalar(select(db_now()))
    assert now is not None
    return now


Window = tuple[datetime, datetime]
"""The database's clock just before and just after an action (``on_db_clock``)."""
_T = TypeVar("_T")


def on_db_clock(settings: Settings, clock: SkewedClock, offset: timedelta, act: Callable[[], _T]) -> tuple[_T, Window]:
    """``act()`` run by a process whose clock is ``offset`` from the host's; its outcome, and the database's
    clock just before and just after it."""
    before = db_clock(settings)
    clock.offset = offset
    try:
        outcome = act()
    finally:
        clock.offset = timedelta(0)
    return outcome, (before, db_clock(settings))


def assert_within(value: datetime | None, window: Window, what: str) -> None:
    """``value`` (a time the database stored) lies in ``window`` (``on_db_clock``)."""
    assert value is not None and window[0] <= value <= window[1], f"{what} {value} is not within {window}"


class PortRelay:
    """A TCP relay from a free loopback port to ``target`` (host, port), listening only once ``open``:
    before, a connection to the port is refused, as to a PACS that is down."""

    def __init__(self, target: tuple[str, int]):
        self.port = free_port()
        self.target = target
        self._server: socket.socket | None = None
        self._sockets: list[socket.socket] = []

    def open(self) -> None:
        self._server = socket.create_server(("127.0.0.1", self.port))
        threading.Thread(target=self._accept, args=(self._server,), daemon=True).start()

    def _accept(self, server: socket.socket) -> None:
        while True:
            try:
                near, _ = server.accept()
            except OSError:  # closed
                return
            far = socket.create_connection(self.target)
            self._sockets += [near, far]
            for source, sink in ((near, far), (far, near)):
                threading.Thread(target=self._pump, args=(source, sink), daemon=True).start()

    @staticmethod
    def _pump(source: socket.socket, sink: socket.socket) -> None:
        try:
            while data := source.recv(65536):
                sink.sendall(data)
        except OSError:
            pass
        with contextlib.suppress(OSError):
            sink.shutdown(socket.SHUT_WR)

    def close(self) -> None:
        for sock in [*([self._server] if self._server else []), *self._sockets]:
            with contextlib.suppress(OSError):
                sock.close()
