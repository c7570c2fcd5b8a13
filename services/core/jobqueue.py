"""The job queue: the Celery app's configuration, the names of the tasks, and the publishing side
used by the API, the worker and the reconciler (one publisher per process: ``publisher``).

Messages carry only a job id (and an attempt number); the database holds the job. Celery's result
backend is not used. Queues: ``SPINE_QUEUE_NAME`` (runs, the reconciler), ``<SPINE_QUEUE_NAME>.webhooks``
(``DELIVER_WEBHOOK``) and ``<SPINE_QUEUE_NAME>.dicom`` (``STORE_DICOM``).
"""

from __future__ import annotations

import logging
import os
import sqlite3
import threading
import uuid
from collections.abc import Iterable, Iterator, Sequence
from contextlib import closing, contextmanager
from typing import Any, cast

from celery import Celery
from kombu import Connection
from kombu.exceptions import ChannelError
from kombu.transport import redis as kombu_redis
from redis import exceptions as redis_exceptions

from services.core.config import Settings

log = logging.getLogger(__name__)

RUN_JOB = "spine.run_job"
RECONCILE = "spine.reconcile"
DELIVER_WEBHOOK = "spine.deliver_webhook"
"""args: job id, final status, attempt (1, 2, …); for the event of a run of STOW-RS attempts, its name
after ``job.`` (``dicom_stored``, ``dicom_store_failed``), the attempt, and the number of the run's first
STOW-RS attempt."""
STORE_DICOM = "spine.dicom_store"
"""args: job id, attempt (1, 2, …)."""
REDIS_TRANSPORT = "services.core.jobqueue:RedisTransport"
HARD_LIMIT_GRACE_S = 5.0
"""Seconds between a task's soft time limit (its code gets ``SoftTimeLimitExceeded`` and unwinds, rolling
back) and its hard limit (its pool process is killed): a task stuck on a dependency may stick again while
it unwinds, e.g. rolling back on a connection whose server went away."""


class BrokerConnectionGone(redis_exceptions.ConnectionError):
    """A command asked of a Redis channel whose kombu connection was closed: one of the transport's
    connection errors, which kombu and Celery ignore while closing and log when acknowledging."""


class _SharedClientChannel(kombu_redis.Channel):
    """kombu's Redis channel, with one ``redis.Redis`` client on the channel's connection pool where
    kombu builds a new one for every call that is given none: the QoS bookkeeping of each delivered
    message (its entry in the unacked hash, then its ack) and each published message. Building a
    ``redis.Redis`` rebuilds its table of ~170 response callbacks (redis-py issue #3624): about a
    quarter of the Celery main process's CPU per task here (docs/performance.md). Every
    command still takes a connection from the same pool, so nothing changes on the wire; a new pool
    (after a reconnection) gets a new client.

    A channel whose kombu connection was already collected (``Connection.collect``: its transport
    dropped, ``transport.client`` None) has no broker address left to build a pool from: kombu's own
    channel raises ``AttributeError`` there, which is no connection error. Celery's consumer, after a
    lost connection, collects the connection and then closes it; a channel the collect left open (a
    BRPOP in flight and another channel's close failing first) is closed then, and its close restores
    its unacknowledged messages through a new pool: the ``AttributeError`` escaped Celery's
    ``ignore_errors`` and stopped the worker ("Unrecoverable error", seen on a Redis restart: the
    supervisor started it again, and the new pool processes had never seen the broker's run id
    before the restart). So is an ack of a message delivered on such a channel. This channel raises
    ``BrokerConnectionGone`` (a ``redis.ConnectionError``, one of the transport's connection errors)
    instead: the close ends, the ack is logged as not made, and the consumer reconnects. The
    messages it could not restore stay in the broker's unacked hash (restored after the visibility
    timeout, or gone with a restarted broker; the reconciler publishes their jobs again)."""

    _shared_client: Any = None

    @contextmanager
    def conn_or_acquire(self, client: Any = None) -> Iterator[Any]:
        if client:
            yield client
            return
        if self._pool is None and getattr(self.connection, "client", None) is None:
            raise BrokerConnectionGone("the channel's broker connection was closed (collected); no command is sent")
        pool = self.pool
        shared = self._shared_client
        if shared is None or shared.connection_pool is not pool:
            shared = self._shared_client = self._create_client()
        yield shared


class RedisTransport(kombu_redis.Transport):
    """kombu's Redis transport with ``_SharedClientChannel`` (``redis://`` brokers; ``REDIS_TRANSPORT``)."""

    Channel = _SharedClientChannel


def make_celery(settings: Settings) -> Celery:
    """A Celery app for ``settings``: broker from the settings, no result backend."""
    settings.ensure_data_dir()
    app = Celery("spine", broker=settings.celery_broker_url, set_as_current=False)
    transport_options: dict[str, object] = {}
    if settings.celery_broker_url.startswith("sqla+sqlite:///"):
        _use_wal(settings.celery_broker_url.removeprefix("sqla+sqlite:///"))
        transport_options = {"connect_args": {"timeout": 30, "factory": _BrokerConnection}}
    elif settings.celery_broker_url.startswith(("redis", "rediss")):
        # A message not acknowledged within this time is delivered again (acks_late); keep it
        # above the fit time limit so that a slow fit is not run twice.
        # The socket timeouts bound every synchronous command (a publish, an ack, a ping) on a broker
        # that stopped answering without closing the connection (redis-py waits forever without
        # them); the worker's BRPOP runs in its event loop, which kombu checks by itself.
        transport_options = {
            "visibility_timeout": int(settings.fit_time_limit_s * 2 + 60),
            "socket_timeout": settings.broker_timeout_s,
            "socket_connect_timeout": settings.broker_timeout_s,
            # TCP keepalive and TCP_USER_TIMEOUT (SPINE_BROKER_TCP_TIMEOUT_S): kombu passes None to redis-py
            # for both unless given, which turns redis-py's own keepalive off
            **settings.broker_socket_options,
        }
        if settings.celery_broker_url.startswith("redis://"):
            # (not rediss://: kombu turns TLS on by the transport's name being "rediss")
            app.conf.broker_transport = REDIS_TRANSPORT
    app.conf.update(
        broker_transport_options=transport_options,
        broker_connection_retry_on_startup=True,
        broker_connection_timeout=5,
        result_backend=None,
        task_ignore_result=True,
        task_store_errors_even_if_ignored=False,
        task_default_queue=settings.queue_name,
        task_routes={RUN_JOB: {"queue": settings.queue_name}, RECONCILE: {"queue": settings.queue_name}},
        task_serializer="json",
        accept_content=["json"],
        task_acks_late=True,
        task_reject_on_worker_lost=False,
        task_publish_retry_policy={"max_retries": 2, "interval_start": 0, "interval_step": 0.5},
        worker_prefetch_multiplier=4,
        worker_hijack_root_logger=False,
        worker_send_task_events=False,
        task_send_sent_event=False,
        enable_utc=True,
    )
    return app


_PUBLISHERS: dict[tuple[str, int], Celery] = {}
_LOCK = threading.Lock()


def publisher(settings: Settings) -> Celery:
    """The process's Celery app for publishing to the broker of ``settings``: built once per process
    (a forked child builds its own, so that no broker connection is shared across a fork)."""
    key = (settings.celery_broker_url, os.getpid())
    with _LOCK:
        if key not in _PUBLISHERS:
            _PUBLISHERS[key] = make_celery(settings)
        return _PUBLISHERS[key]


def publish_webhook(
    settings: Settings, job_id: uuid.UUID | str, status: str, attempt: int, *, run: int | None = None,
    countdown: float = 0.0, celery: Celery | None = None,
) -> None:  # fmt: skip
    """Publish attempt ``attempt`` of the webhook of a job that ended in ``status`` (or of event
    ``job.<status>`` of its run of STOW-RS attempts ``run``), after ``countdown`` s, with ``celery``
    (default: the process's ``publisher``). Raises when the broker cannot take it. A job's end's message
    has the three arguments it always had."""
    app = celery or publisher(settings)
    args: list[object] = [str(job_id), status, attempt, *([] if run is None else [run])]
    app.send_task(DELIVER_WEBHOOK, args=args, countdown=countdown or None, queue=settings.webhook_queue)


def publish_dicom_store(
    settings: Settings, job_id: uuid.UUID | str, attempt: int, *, countdown: float = 0.0,
    celery: Celery | None = None,
) -> None:  # fmt: skip
    """Publish attempt ``attempt`` of the STOW-RS of a succeeded job's results, after ``countdown`` s,
    with ``celery`` (default: the process's ``publisher``). Raises when the broker cannot take it."""
    app = celery or publisher(settings)
    app.send_task(STORE_DICOM, args=[str(job_id), attempt], countdown=countdown or None, queue=settings.dicom_queue)


class _BrokerConnection(sqlite3.Connection):
    """A connection to the embedded broker file that does not fsync every commit.

    Safe in WAL mode (no corruption; at worst the last messages are lost at a power cut, and
    the reconciler publishes their jobs again).
    """

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.execute("PRAGMA synchronous=NORMAL")


def _use_wal(path: str) -> None:
    """Put the embedded broker's SQLite file in WAL mode (persistent): commits get much cheaper."""
    with closing(sqlite3.connect(path, timeout=30)) as db:
        db.execute("PRAGMA journal_mode=WAL")


def enqueue(app: Celery, job_ids: Iterable[uuid.UUID], countdowns_s: Sequence[float] | None = None) -> int:
    """Publish one message per job id, each with its countdown (s) when ``countdowns_s`` is given (a job not
    due yet, ``services.db.runs.Reconciliation.later``); return how many were published.

    A failure to publish is logged, not raised: the job is stored as queued and the reconciler
    publishes it again (``services.db.runs.publish`` marks it for the reconciler's next pass).
    """
    sent = 0
    try:
        with app.producer_or_acquire() as producer:
            for k, job_id in enumerate(job_ids):
                countdown = countdowns_s[k] if countdowns_s is not None else None
                app.send_task(RUN_JOB, args=[str(job_id)], countdown=countdown or None, producer=producer)
                sent += 1
    except Exception as exc:
        log.warning("could not publish job messages (the reconciler will): %s", exc)
    return sent


@contextmanager
def broker_connection(app: Celery) -> Iterator[Connection]:
    """A connection from the app's broker pool (``app.pool``, the one the producers take theirs from),
    given back after use: the reconciler's looks at the broker every ``SPINE_RECONCILE_INTERVAL_S`` and
    the metrics' queue depth reuse its sockets, where a new connection each time is a TCP connection to
    the broker per look (docs/performance.md). A pooled socket the broker closed (a restart) is opened
    again by its next command (redis-py)."""
    with app.pool.acquire(block=True) as conn:
        yield conn


def _redis_channel(conn: Connection) -> kombu_redis.Channel:
    """The default channel of a connection to a Redis broker (``redis``, ``rediss``), with its client."""
    return cast(kombu_redis.Channel, conn.default_channel)


def queue_depth(app: Celery, queue: str) -> int:
    """Messages waiting in ``queue`` on the broker, asked on a connection of the app's pool
    (``broker_connection``)."""
    with broker_connection(app) as conn:
        try:
            return int(conn.default_channel.queue_declare(queue=queue, passive=True).message_count)
        except ChannelError:  # not declared yet: nothing was ever published to it
            return 0


def broker_run_id(app: Celery) -> str | None:
    """An id of the broker's current run (Redis ``INFO server`` run_id): it changes when the
    broker restarts, and with it every message it held may be gone. None for other brokers."""
    if not app.conf.broker_url.startswith(("redis", "rediss")):
        return None
    with broker_connection(app) as conn:
        info = _redis_channel(conn).client.info("server")
        return str(info.get("run_id")) if info.get("run_id") else None


RESTART_CLAIM_TTL_S = 86_400
"""How long the broker keeps the mark that one reconciler took a restart (a day: every reconciler
that looked before the restart looks again within ``SPINE_RECONCILE_INTERVAL_S``)."""


def claim_broker_restart(app: Celery, queue: str, run_id: str) -> bool:
    """Whether the caller is the first to take the broker's run ``run_id`` as a restart for ``queue``:
    Redis ``SET NX`` of ``spine:<queue>:restart:<run_id>`` (expiring after ``RESTART_CLAIM_TTL_S``).
    Every pool process of every worker that looked at the broker before it restarted sees the new run
    id; the one whose claim succeeds publishes every queued job again, the others do not."""
    with broker_connection(app) as conn:
        client = _redis_channel(conn).client
        return bool(client.set(f"spine:{queue}:restart:{run_id}", "1", nx=True, ex=RESTART_CLAIM_TTL_S))


def ping_broker(app: Celery) -> None:
    """Raise when the broker cannot be reached: one new connection, no retry (a readiness probe asks
    again by itself); on Redis it sends PING, bounded by ``SPINE_BROKER_TIMEOUT_S``."""
    with app.connection_for_read() as conn:
        conn.ensure_connection(max_retries=0)
