"""SPINE_WEBHOOK_TIMEOUT_S bounds a whole delivery attempt: a real local receiver that drips its
answer one byte at a time (each gap shorter than the timeout) is cut off when the attempt's time is
up, and the attempt is recorded as timed out and retried."""

from __future__ import annotations

import socket
import threading
import time
import uuid
from collections.abc import Iterator

import pytest
from sqlalchemy import select

from services.core.config import Settings
from services.db.engine import session_scope
from services.db.models import WebhookDelivery
from services.webhooks.delivery import post
from services.worker import webhook_tasks
from tests.interop_helpers import cancelled_job_calling

ANSWER = b"HTTP/1.1 200 OK\r\nX-Pad: " + b"a" * 30 + b"\r\ncontent-length: 0\r\n\r\n"
TIMEOUT_S = 1.0
SLACK_S = 0.8


class DrippingReceiver:
    """Reads a request, then sends a 200 one byte every ``gap_s`` seconds (about 60 bytes)."""

    def __init__(self, gap_s: float = 0.2) -> None:
        self.gap_s = gap_s
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.stopped = threading.Event()
        self.requests = 0
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while not self.stopped.is_set():
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            threading.Thread(target=self._drip, args=(conn,), daemon=True).start()

    def _drip(self, conn: socket.socket) -> None:
        with conn:
            conn.settimeout(5)
            data = b""
            try:
                while b"\r\n\r\n" not in data:
                    data += conn.recv(65536)
                head, _, rest = data.partition(b"\r\n\r\n")
                length = next((int(line.split(b":")[1]) for line in head.split(b"\r\n")
                               if line.lower().startswith(b"content-length:")), 0)  # fmt: skip
                while len(rest) < length:
                    rest += conn.recv(65536)
                self.requests += 1
                for byte in ANSWER:
                    if self.stopped.is_set():
                        return
                    conn.sendall(bytes([byte]))
                    time.sleep(self.gap_s)
            except OSError:
                return  # the client hung up: what the deadline is for

    def url(self, path: str = "/hooks/drip") -> str:
        return f"http://127.0.0.1:{self.port}{path}"

    def close(self) -> None:
        self.stopped.set()
        self.sock.close()


@pytest.fixture()
def dripping() -> Iterator[DrippingReceiver]:
    receiver = DrippingReceiver()
    yield receiver
    receiver.close()


def test_a_dripped_answer_ends_the_attempt_at_its_time_limit(dripping: DrippingReceiver) -> None:
    started = time.monotonic()
    sent = post(dripping.url(), b"{}", {"content-type": "application/json"}, TIMEOUT_S)
    took = time.monotonic() - started
    assert took < TIMEOUT_S + SLACK_S, f"the attempt took {took:.1f} s under a {TIMEOUT_S} s limit"
    assert sent.status_code is None and not sent.accepted
    assert sent.error is not None and "Timeout" in sent.error and "SPINE_WEBHOOK_TIMEOUT_S" in sent.error
    assert sent.duration_ms < (TIMEOUT_S + SLACK_S) * 1000


def test_a_timed_out_attempt_is_recorded_and_retried(db_settings: Settings, dripping: DrippingReceiver) -> None:
    settings, job_id = cancelled_job_calling(db_settings, dripping.url(f"/hooks/{uuid.uuid4().hex}"),
                                             webhook_timeout_s=TIMEOUT_S, webhook_retry_base_s=1.0,
                                             webhook_max_attempts=3)  # fmt: skip
    started = time.monotonic()
    delay = webhook_tasks.deliver_once(settings, job_id, "cancelled", 1)
    assert time.monotonic() - started < TIMEOUT_S + SLACK_S + 0.5  # the database's share included
    assert delay == 1.0  # retried per policy
    with session_scope(settings) as session:
        [row] = session.scalars(select(WebhookDelivery).where(WebhookDelivery.job_id == job_id))
        assert row.status_code is None and row.error is not None and "Timeout" in row.error
        assert row.next_attempt_at is not None
    assert dripping.requests == 1
