"""A worker's broker connection lost with a restarted Redis (``services.core.jobqueue.RedisTransport`` on a
real redis-server of the test's own, killed): Celery's consumer collects the connection and then closes it
(``celery.worker.consumer.consumer.Consumer.on_connection_error_after_connected``), and a task that ends
afterwards acknowledges its message on the collected connection's channel. Neither may raise anything
but a connection error: an ``AttributeError`` there stopped the whole worker ("Unrecoverable error")
instead of the consumer reconnecting."""

from __future__ import annotations

import contextlib
import logging
import time
import uuid
from pathlib import Path

import pytest
from celery.worker.consumer.consumer import COLLECT_SOCKET_TIMEOUT, bound_open_broker_sockets
from kombu import Connection, Consumer, Exchange, Message, Queue
from kombu.common import ignore_errors

from services.core.config import Settings
from services.core.jobqueue import make_celery
from tools.loadbench import OwnRedis


def _consuming(tmp_path: Path, own_redis: OwnRedis) -> tuple[Connection, Consumer, Message]:
    """A connection as a worker's consumer holds it: the task queue consumed on the default channel, one
    message delivered and not acknowledged (acks_late), the next BRPOP sent; and a fanout queue that
    deletes itself (as Celery's remote control queue) consumed on a second channel."""
    queue = f"test-close-{uuid.uuid4().hex[:8]}"
    app = make_celery(Settings(data_dir=tmp_path, CELERY_BROKER_URL=own_redis.url, queue_name=queue))
    with app.connection_for_write() as conn:
        conn.SimpleQueue(queue).put({"job": 1})
    conn = app.connection_for_read()
    delivered: list[Message] = []
    tasks = conn.Consumer([Queue(queue)], callbacks=[lambda _body, message: delivered.append(message)],
                          accept=["json"])  # fmt: skip
    tasks.consume()
    remote_control = Queue(f"{queue}.control", Exchange(f"{queue}.x", type="fanout"), auto_delete=True)
    control = Consumer(conn.channel(), [remote_control], callbacks=[lambda *_: None], accept=["json"])
    control.consume()
    deadline = time.monotonic() + 10
    while (not delivered or tasks.channel._in_poll is None) and time.monotonic() < deadline:
        with contextlib.suppress(TimeoutError):
            conn.drain_events(timeout=0.2)
    assert len(delivered) == 1 and tasks.channel._in_poll is not None  # held unacknowledged; BRPOP in flight
    return conn, tasks, delivered[0]


def _lose_connection(conn: Connection) -> None:
    """What Celery's consumer does with its connection once it found it lost, before reconnecting."""
    bound_open_broker_sockets(conn, COLLECT_SOCKET_TIMEOUT)
    with contextlib.suppress(Exception):  # as Celery: a collect that fails is passed over
        conn.collect(socket_timeout=COLLECT_SOCKET_TIMEOUT)
    ignore_errors(conn, conn.close)  # raises what is not a connection error: the worker stops


def test_a_connection_lost_with_the_broker_closes_and_its_late_ack_is_only_logged(
    tmp_path: Path, own_redis: OwnRedis, caplog: pytest.LogCaptureFixture
) -> None:
    conn, tasks, message = _consuming(tmp_path, own_redis)
    own_redis.stop()  # SIGKILL: the broker and the unacknowledged message with it
    _lose_connection(conn)  # the consumer would now reconnect
    assert tasks.channel is not None and tasks.channel.closed
    with caplog.at_level(logging.CRITICAL, logger="celery.worker.request"):
        # the task ends after the reconnection: its message's channel is the collected connection's
        message.ack_log_error(logging.getLogger("celery.worker.request"), conn.connection_errors)
    assert "Couldn't ack" in caplog.text and message.acknowledged is False  # a connection error, logged
    assert "broker connection was closed" in caplog.text  # services.core.jobqueue.BrokerConnectionGone
