"""Prometheus metrics of the API: HTTP traffic (in process) and job state (read at scrape time).

Job counts, queue depth and duration quantiles come from the database and the broker when
/metrics is scraped, so every API replica reports the state of the whole service, whichever
worker ran the jobs. Those reads are dependency checks, bounded as /readyz's are (``start_check``,
``answer_by``): a dependency that has not answered within ``SPINE_READY_TIMEOUT_S`` is reported
down (``spine_dependency_up`` 0) and the scrape is answered without it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, TypeVar

from celery import Celery
from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.core.config import Settings
from services.core.jobqueue import queue_depth
from services.db import stats
from services.db.clock import db_now_plus_s
from services.db.engine import session_scope

log = logging.getLogger(__name__)

QUANTILES = (0.5, 0.9, 0.99)

T = TypeVar("T")


def start_check(check: Callable[[], T], slots: threading.BoundedSemaphore) -> Future[T]:
    """Run ``check`` in a daemon thread of its own (never one that delays the process's exit) and
    return its future, to be waited for with ``answer_by``. A check stuck on a dependency holds one of
    ``slots`` until the dependency's own timeout ends it (SPINE_DB_CONNECT_TIMEOUT_S,
    SPINE_DB_TCP_TIMEOUT_S, SPINE_DB_STATEMENT_TIMEOUT_S, SPINE_BROKER_TIMEOUT_S); with every slot
    held, the check is not started and its future never resolves, so that it answers "no answer" in
    time and the threads stuck at once stay bounded."""
    future: Future[T] = Future()
    if not slots.acquire(blocking=False):
        return future

    def run() -> None:
        try:
            future.set_result(check())
        except Exception as exc:
            future.set_exception(exc)
        finally:
            slots.release()

    threading.Thread(target=run, name="dependency-check", daemon=True).start()
    return future


def answer_by(check: Future[T], deadline: float) -> T:
    """What ``check`` answered, waiting at most until ``deadline`` (``time.monotonic()``, s); its
    exception, or ``TimeoutError`` when it has not answered by then."""
    return check.result(timeout=max(0.0, deadline - time.monotonic()))


_SCRAPE_SLOTS = threading.BoundedSemaphore(4)
"""Dependency reads of /metrics running at once per process (two per scrape), apart from /readyz's."""


@dataclass(frozen=True)
class _DatabaseReading:
    counts: dict[str, int]
    durations: list[tuple[float, float]]
    """(run time, end-to-end time) of each job finished in the window, s."""


def _quantile(sorted_values: list[float], q: float) -> float:
    if not sorted_values:
        return float("nan")
    index = min(len(sorted_values) - 1, max(0, round(q * (len(sorted_values) - 1))))
    return sorted_values[index]


class JobStateCollector(Collector):
    """Reads job counts, queue depth and recent durations when scraped."""

    def __init__(self, settings: Settings, celery: Celery):
        self.settings = settings
        self.celery = celery

    def _read_database(self) -> _DatabaseReading:
        with session_scope(self.settings) as session:
            counts = stats.count_by_status(session)
            # the window ends at the database's clock, on which no API replica's own clock has a say
            since = db_now_plus_s(-self.settings.metrics_window_s)
            return _DatabaseReading(counts, list(stats.recent_durations(session, since)))

    def _read_broker(self) -> int:
        return queue_depth(self.celery, self.settings.queue_name)

    def _answer(self, name: str, check: Future[T], deadline: float) -> T | None:
        """What the dependency ``name`` answered by ``deadline``, or None (logged) when it did not."""
        try:
            return answer_by(check, deadline)
        except TimeoutError:
            log.warning("metrics: %s: no answer within %g s (SPINE_READY_TIMEOUT_S)", name,
                        self.settings.ready_timeout_s)  # fmt: skip
        except Exception as exc:
            log.warning("metrics: %s unreachable: %s", name, exc)
        return None

    def collect(self) -> Iterable[Metric]:
        # Both reads run at once, each in a thread of its own, and the scrape waits for neither more
        # than SPINE_READY_TIMEOUT_S, as /readyz: a dependency that accepts connections and does not
        # answer is reported down in time, not a scrape that waits for its timeouts.
        deadline = time.monotonic() + self.settings.ready_timeout_s
        database = start_check(self._read_database, _SCRAPE_SLOTS)
        broker = start_check(self._read_broker, _SCRAPE_SLOTS)
        reading = self._answer("database", database, deadline)
        waiting = self._answer("broker", broker, deadline)
        up = GaugeMetricFamily("spine_dependency_up", "Whether a dependency answered this scrape.", labels=["name"])
        up.add_metric(["database"], int(reading is not None))
        up.add_metric(["broker"], int(waiting is not None))
        counts, durations = (reading.counts, reading.durations) if reading is not None else ({}, [])
        jobs = GaugeMetricFamily("spine_jobs", "Jobs in the database by status.", labels=["status"])
        for status, n in counts.items():
            jobs.add_metric([status], n)
        yield jobs
        if waiting is not None:
            depth = GaugeMetricFamily(
                "spine_queue_depth", "Messages waiting in the job queue on the broker: job runs and reconciler passes."
            )
            depth.add_metric([], waiting)
            yield depth
        yield up
        window = f"{self.settings.metrics_window_s:g}"
        for index, name, doc in (
            (0, "spine_fit_duration_seconds", "Run time of a job (started to finished)"),
            (1, "spine_job_duration_seconds", "End-to-end time of a job (created to finished)"),
        ):
            values = sorted(d[index] for d in durations)
            gauge = GaugeMetricFamily(
                name, f"{doc}, quantiles over the jobs finished in the last {window} s.", labels=["quantile"]
            )
            for q in QUANTILES:
                gauge.add_metric([f"{q:g}"], _quantile(values, q))
            yield gauge
        finished = GaugeMetricFamily("spine_jobs_finished_recent", f"Jobs succeeded or failed in the last {window} s.")
        finished.add_metric([], len(durations))
        yield finished


class HTTPMetrics:
    """Pure ASGI middleware counting requests and timing them by route template."""

    def __init__(self, app: ASGIApp, registry: CollectorRegistry):
        self.app = app
        self.requests = Counter(
            "spine_http_requests", "HTTP requests answered.", ["method", "route", "status"], registry=registry
        )
        self.latency = Histogram(
            "spine_http_request_duration_seconds",
            "Time to answer an HTTP request.",
            ["method", "route"],
            registry=registry,
            buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 10.0),
        )

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = [500]

        async def send_wrapper(message: Message) -> None:
            if message["type"] == "http.response.start":
                status[0] = int(message["status"])
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route: Any = scope.get("route")
            template = getattr(route, "path", None) or "unmatched"
            self.requests.labels(scope["method"], template, str(status[0])).inc()
            self.latency.labels(scope["method"], template).observe(time.perf_counter() - started)
