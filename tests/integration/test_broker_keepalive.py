"""The Redis broker's connections carry TCP keepalive and TCP_USER_TIMEOUT from SPINE_BROKER_TCP_TIMEOUT_S
(``Settings.broker_socket_options``), read back from the kernel on real connections to the machine's Redis:
without them kombu gives redis-py ``socket_keepalive=None``, and an idle connection whose server vanished
(a failover, a dropped NAT entry) is never probed."""

from __future__ import annotations

import socket
from pathlib import Path

from services.core.config import Settings
from services.core.jobqueue import make_celery


def test_broker_connections_carry_keepalive_and_a_tcp_user_timeout(tmp_path: Path, redis_url: str) -> None:
    settings = Settings(data_dir=tmp_path, CELERY_BROKER_URL=redis_url, broker_tcp_timeout_s=3)
    app = make_celery(settings)
    for connection in (app.connection_for_write(), app.connection_for_read()):  # the publisher's, the consumer's
        with connection:
            client = connection.default_channel.client
            client.ping()
            pooled = client.connection_pool.get_connection()
            try:
                sock = pooled._sock
                assert sock.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE) == 1
                assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT) == 3000
                # T = 3 s: first probe after T/3, then every T/6 (1 s at least), 2 unanswered → dropped at 3 s
                assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE) == 1
                assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL) == 1
                assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT) == 2
            finally:
                client.connection_pool.release(pooled)
