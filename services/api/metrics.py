"""Prometheus metrics of the API: HTTP traffic (in process) and job state (read at scrape time).

Job counts, queue depth and duration quantiles come from the database and the broker when
/metrics is scraped, so every API replica reports the state of the whole service, whichever
worker ran the jobs.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from datetime import timedelta
from typing import Any

from celery import Celery
from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.core.config import Settings
from services.core.jobqueue import queue_depth
from services.db import stats
from services.db.engine import session_scope
from services.db.models import utcnow

log = logging.getLogger(__name__)

QUANTILES = (0.5, 0.9, 0.99)


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

    def collect(self) -> Iterable[Metric]:
        up = GaugeMetricFamily("spine_dependency_up", "Whether a dependency answered this scrape.", labels=["name"])
        try:
            with session_scope(self.settings) as session:
                counts = stats.count_by_status(session)
                since = utcnow() - timedelta(seconds=self.settings.metrics_window_s)
                durations = stats.recent_durations(session, since)
            up.add_metric(["database"], 1)
        except Exception as exc:
            log.warning("metrics: database unreachable: %s", exc)
            up.add_metric(["database"], 0)
            counts, durations = {}, []
        jobs = GaugeMetricFamily("spine_jobs", "Jobs in the database by status.", labels=["status"])
        for status, n in counts.items():
            jobs.add_metric([status], n)
        yield jobs
        depth = GaugeMetricFamily("spine_queue_depth", "Job messages waiting on the broker.")
        try:
            depth.add_metric([], queue_depth(self.celery, self.settings.queue_name))
            up.add_metric(["broker"], 1)
            yield depth
        except Exception as exc:
            log.warning("metrics: broker unreachable: %s", exc)
            up.add_metric(["broker"], 0)
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
