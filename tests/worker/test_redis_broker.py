"""The Redis broker's transport (``services.core.jobqueue.RedisTransport``) on a real Redis: one
``redis.Redis`` client per channel and connection pool instead of one per call, and the message
life cycle the worker relies on unchanged (published, delivered, held as unacknowledged, acked)."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.core.config import Settings
from services.core.jobqueue import RUN_JOB, RedisTransport, enqueue, make_celery, queue_depth
from tests.conftest import _purge_queue


@pytest.fixture
def queue(redis_url: str) -> Iterator[str]:
    name = f"test-broker-{uuid.uuid4().hex[:8]}"
    yield name
    _purge_queue(redis_url, name)


def _settings(tmp_path: Path, broker_url: str, queue: str) -> Settings:
    return Settings(data_dir=tmp_path, CELERY_BROKER_URL=broker_url, queue_name=queue)


def test_a_redis_broker_uses_one_client_per_pool(tmp_path: Path, redis_url: str, queue: str) -> None:
    app = make_celery(_settings(tmp_path, redis_url, queue))
    with app.connection_for_write() as conn:
        assert isinstance(conn.transport, RedisTransport)
        channel = conn.default_channel
        with channel.conn_or_acquire() as first, channel.conn_or_acquire() as second:
            assert first is second and first.connection_pool is channel.pool
            assert first.ping()
        given = object()
        with channel.conn_or_acquire(given) as client:  # a client handed in is used as it is
            assert client is given
        channel._pool = None  # a new pool (as after a reconnection): a new client on it
        with channel.conn_or_acquire() as third:
            assert third is not first and third.connection_pool is channel.pool


def test_messages_are_delivered_held_unacked_and_acked(tmp_path: Path, redis_url: str, queue: str) -> None:
    """Three job messages through the transport as the worker consumes them (acks late): each is held
    in the broker's unacknowledged set while it runs and leaves it when acked; the queue ends empty.
    The set is the broker's, shared with every other consumer of the same Redis database (tests on
    the other pytest process), so each message is looked up by its delivery tag, not counted."""
    app = make_celery(_settings(tmp_path, redis_url, queue))
    job_ids = [uuid.uuid4() for _ in range(3)]
    assert enqueue(app, job_ids) == 3
    assert queue_depth(app, queue) == 3
    received = []
    with app.connection_for_read() as conn:
        channel = conn.default_channel

        def held(tag: str) -> bool:  # in the QoS bookkeeping of delivered, unacknowledged messages
            return bool(channel.client.hexists(channel.unacked_key, tag))

        simple = conn.SimpleQueue(queue, no_ack=False)
        try:
            for _ in job_ids:
                message = simple.get(timeout=5)
                assert message.headers["task"] == RUN_JOB
                assert held(message.delivery_tag)
                received.append(uuid.UUID(message.payload[0][0]))
                message.ack()
                assert not held(message.delivery_tag)
        finally:
            simple.close()
    assert received == job_ids
    assert queue_depth(app, queue) == 0


def test_a_tls_broker_keeps_kombus_own_transport(tmp_path: Path, queue: str) -> None:
    """rediss:// keeps kombu's transport: kombu turns TLS on by the transport's name."""
    app = make_celery(_settings(tmp_path, "rediss://127.0.0.1:6380/0?ssl_cert_reqs=required", queue))
    assert app.conf.broker_transport is None
    app_plain = make_celery(_settings(tmp_path, "redis://127.0.0.1:6379/0", queue))
    assert app_plain.conf.broker_transport == "services.core.jobqueue:RedisTransport"
