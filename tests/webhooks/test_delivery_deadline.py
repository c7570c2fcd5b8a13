"""SPINE_WEBHOOK_TIMEOUT_S bounds a whole delivery attempt: a real local receiver that drips its
answer one byte at a time (each gap shorter than the timeout) is cut off when the attempt's time is
up, and the attempt is recorded as timed out and retried; the receiver's name is resolved within the
same time (a resolver that hangs is the one function substituted, ``socket.getaddrinfo``)."""

from __future__ import annotations

import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

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
HANG_S = 5.0
"""How long the substituted resolver hangs (then fails, as a resolver gives up): past TIMEOUT_S + SLACK_S."""


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


def _hang_on(name: str, release: threading.Event) -> Callable[..., Any]:
    """``socket.getaddrinfo``, but for ``name`` it hangs until ``release`` (at most HANG_S) and then fails
    as a resolver that gave up does."""
    resolve = socket.getaddrinfo

    def getaddrinfo(host: Any, *args: Any, **kwargs: Any) -> Any:
        if host == name:
            release.wait(HANG_S)
            raise socket.gaierror(socket.EAI_AGAIN, "Temporary failure in name resolution")
        return resolve(host, *args, **kwargs)

    return getaddrinfo


HANGS = "hooks.hangs.example"
"""A name under .example, reserved and never a real host (RFC 2606 §3)."""


def test_a_name_not_resolved_in_time_ends_the_attempt_at_its_time_limit(monkeypatch: pytest.MonkeyPatch) -> None:
    """The receiver's name was resolved outside the attempt's deadline (``socket.getaddrinfo`` in the
    connect, which no timeout bounds): a resolver that hung held the attempt as long as it hung."""
    release = threading.Event()
    monkeypatch.setattr(socket, "getaddrinfo", _hang_on(HANGS, release))
    started = time.monotonic()
    try:
        sent = post(f"http://{HANGS}:8080/hook", b"{}", {"content-type": "application/json"}, TIMEOUT_S)
    finally:
        took = time.monotonic() - started
        release.set()
    assert took < TIMEOUT_S + SLACK_S, f"the attempt took {took:.1f} s under a {TIMEOUT_S} s limit"
    assert sent.status_code is None and sent.error is not None
    assert sent.error.startswith("ConnectTimeout") and "SPINE_WEBHOOK_TIMEOUT_S" in sent.error, sent.error


def test_what_the_caller_spent_leaves_the_resolution_less_time(monkeypatch: pytest.MonkeyPatch) -> None:
    """The lookup gets what is left of the attempt, not a timeout of its own: an attempt of which the
    caller already spent all but 0.2 s ends about 0.2 s later, while its name is still resolving."""
    release = threading.Event()
    monkeypatch.setattr(socket, "getaddrinfo", _hang_on(HANGS, release))
    started = time.monotonic()
    try:
        sent = post(f"http://{HANGS}/hook", b"{}", {}, TIMEOUT_S, spent_s=TIMEOUT_S - 0.2)
    finally:
        took = time.monotonic() - started
        release.set()
    assert took < 0.2 + SLACK_S, f"the attempt took {took:.1f} s with 0.2 s left"
    assert sent.error is not None and sent.error.startswith("ConnectTimeout"), sent.error
