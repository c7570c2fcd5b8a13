"""One POST of a job's webhook to its receiver, and what its answer means for the next attempt.

``webhook_body`` is the JSON a receiver gets; ``post`` sends it (signed by the caller with
``signing.signed_headers``) without following redirects and without proxies from the environment, and
reports the receiver's status, ``Retry-After`` and any transport error; ``retry_delay`` is the backoff
before the next attempt (``Retry-After`` honoured). ``SPINE_WEBHOOK_TIMEOUT_S`` bounds the whole
attempt (resolving the receiver's name, connect, send, and the receiver's answer), not each network
operation: a receiver that drips its answer a byte at a time, or a name server that does not answer,
is cut off when the attempt's time is up. Recording, retrying and publishing are the worker's
(``services.worker.webhook_tasks``).
"""

from __future__ import annotations

import json
import os
import socket
import ssl
import threading
import time
from contextvars import ContextVar
from dataclasses import dataclass
from datetime import UTC, datetime
from email.utils import parsedate_to_datetime
from typing import Any

import httpcore
import httpx

from services.core.config import Settings
from services.db.models import iso_utc, utcnow

MAX_RETRY_DELAY_S = 120.0
"""Cap of the delay between attempts (below the Redis visibility timeout, so a scheduled attempt
is never delivered twice)."""
USER_AGENT = "spine-webhooks/1"


@dataclass(frozen=True)
class PostOutcome:
    """What one POST got: the receiver's status (None when no answer came), its ``Retry-After``, the
    transport error, the time it took (ms) and the receiver's ``Date`` (its clock's time of the answer,
    RFC 9110 §6.6.1), against which a ``Retry-After`` HTTP-date is read (``retry_delay``)."""

    status_code: int | None
    retry_after: str | None
    error: str | None
    duration_ms: float
    date: str | None = None

    @property
    def accepted(self) -> bool:
        """The receiver answered 2xx."""
        return self.status_code is not None and 200 <= self.status_code < 300


def webhook_body(job: dict[str, Any], status: str, finished_at: datetime | None) -> bytes:
    """The JSON a receiver gets: ``{"type": "job.<status>", "timestamp", "data": <the job>}``."""
    body = {"type": f"job.{status}", "timestamp": iso_utc(finished_at or utcnow()), "data": job}
    return json.dumps(body, separators=(",", ":"), ensure_ascii=False).encode()


_DEADLINE: ContextVar[float | None] = ContextVar("webhook_attempt_deadline", default=None)
"""``time.monotonic()`` by which the current attempt must be over (None: no overall limit)."""


def _remaining(timeout: float | None, exc: type[Exception]) -> float | None:
    """The time an operation may take: its own timeout, capped by what is left of the attempt."""
    deadline = _DEADLINE.get()
    if deadline is None:
        return timeout
    left = deadline - time.monotonic()
    if left <= 0:
        raise exc("the attempt's time limit passed")
    return left if timeout is None else min(timeout, left)


class _DeadlineStream(httpcore.NetworkStream):
    """A connection whose every read and write ends by the attempt's deadline."""

    def __init__(self, stream: httpcore.NetworkStream) -> None:
        self._stream = stream

    def read(self, max_bytes: int, timeout: float | None = None) -> bytes:
        return self._stream.read(max_bytes, _remaining(timeout, httpcore.ReadTimeout))

    def write(self, buffer: bytes, timeout: float | None = None) -> None:
        self._stream.write(buffer, _remaining(timeout, httpcore.WriteTimeout))

    def close(self) -> None:
        self._stream.close()

    def start_tls(
        self, ssl_context: ssl.SSLContext, server_hostname: str | None = None, timeout: float | None = None
    ) -> httpcore.NetworkStream:
        return _DeadlineStream(
            self._stream.start_tls(ssl_context, server_hostname, _remaining(timeout, httpcore.ConnectTimeout))
        )

    def get_extra_info(self, info: str) -> Any:
        return self._stream.get_extra_info(info)


def _resolve(host: str, port: int, timeout: float | None) -> list[tuple[Any, ...]]:
    """The TCP addresses of ``host`` (``socket.getaddrinfo``), or ``httpcore.ConnectTimeout`` once
    ``timeout`` seconds have passed without them (None: no limit), or ``httpcore.ConnectError`` when
    the name does not resolve.

    ``getaddrinfo`` has no timeout of its own and cannot be interrupted (the C library's resolver waits
    as its resolv.conf says: 5 s per try and server by default, resolv.conf(5)), so it runs in a daemon
    thread that this call stops waiting for; a lookup left behind ends when the resolver gives up, and
    its answer is dropped."""
    done = threading.Event()
    found: list[list[tuple[Any, ...]] | OSError] = []

    def lookup() -> None:
        try:
            found.append(socket.getaddrinfo(host, port, type=socket.SOCK_STREAM))
        except OSError as exc:
            found.append(exc)
        finally:
            done.set()

    threading.Thread(target=lookup, name="webhook-getaddrinfo", daemon=True).start()
    if not done.wait(timeout):
        raise httpcore.ConnectTimeout(f"no address for {host} within the attempt's time limit")
    if isinstance(found[0], OSError):
        raise httpcore.ConnectError(str(found[0]))
    return found[0]


class _DeadlineBackend(httpcore.NetworkBackend):
    """The default network backend, with the receiver's name resolved and its connections' operations
    ended by the attempt's deadline."""

    def __init__(self) -> None:
        self._backend = httpcore.SyncBackend()

    def connect_tcp(
        self, host: str, port: int, timeout: float | None = None, local_address: str | None = None,
        socket_options: Any = None,
    ) -> httpcore.NetworkStream:  # fmt: skip
        """Each address of ``host`` in turn, as ``socket.create_connection`` tries them, until one
        connects; the name's lookup and every try take what is left of the attempt. (TLS still names
        ``host``: httpcore passes it to ``start_tls`` as the server name.)"""
        failed: httpcore.ConnectError | httpcore.ConnectTimeout | None = None
        for *_, address in _resolve(host, port, _remaining(timeout, httpcore.ConnectTimeout)):
            left = _remaining(timeout, httpcore.ConnectTimeout)  # raises once the attempt's time is up
            try:
                stream = self._backend.connect_tcp(str(address[0]), port, left, local_address, socket_options)
            except (httpcore.ConnectError, httpcore.ConnectTimeout) as exc:
                failed = exc
                continue
            return _DeadlineStream(stream)
        raise failed or httpcore.ConnectError(f"no address for {host}")

    def connect_unix_socket(
        self, path: str, timeout: float | None = None, socket_options: Any = None
    ) -> httpcore.NetworkStream:
        return _DeadlineStream(
            self._backend.connect_unix_socket(path, _remaining(timeout, httpcore.ConnectTimeout), socket_options)
        )

    def sleep(self, seconds: float) -> None:
        self._backend.sleep(seconds)


class _DeadlineTransport(httpx.HTTPTransport):
    """httpx's transport on ``_DeadlineBackend`` (no proxies: ``trust_env`` is off)."""

    def __init__(self) -> None:
        super().__init__(trust_env=False)
        limits = httpx.Limits()
        self._pool = httpcore.ConnectionPool(
            ssl_context=httpx.create_ssl_context(trust_env=False),
            max_connections=limits.max_connections,
            max_keepalive_connections=limits.max_keepalive_connections,
            keepalive_expiry=limits.keepalive_expiry,
            network_backend=_DeadlineBackend(),
        )


_CLIENTS: dict[tuple[float, int], httpx.Client] = {}
_LOCK = threading.Lock()


def _client(timeout: float) -> httpx.Client:
    key = (timeout, os.getpid())
    with _LOCK:
        if key not in _CLIENTS:
            # No redirects (a 3xx could point anywhere), no proxies or .netrc from the environment.
            _CLIENTS[key] = httpx.Client(
                timeout=timeout, follow_redirects=False, trust_env=False, headers={"user-agent": USER_AGENT},
                transport=_DeadlineTransport(),
            )  # fmt: skip
        return _CLIENTS[key]


def post(url: str, body: bytes, headers: dict[str, str], timeout_s: float, *, spent_s: float = 0.0) -> PostOutcome:
    """POST ``body`` to ``url``; never raises for the receiver's faults (they are in the outcome).

    The attempt, from resolving the receiver's name to its status line and headers, ends ``timeout_s`` after
    it started, ``spent_s`` ago (the caller's share of the attempt, before this call), whatever the
    receiver does (an answer dripped a byte at a time included): it is then recorded as timed out.
    The answer's body is never read.
    """
    started = time.perf_counter()
    status_code: int | None = None
    retry_after: str | None = None
    date: str | None = None
    error: str | None = None
    token = _DEADLINE.set(time.monotonic() + timeout_s - max(0.0, spent_s))
    try:
        with _client(timeout_s).stream("POST", url, content=body, headers=headers) as response:
            status_code = response.status_code
            retry_after = response.headers.get("retry-after")
            date = response.headers.get("date")
    except httpx.TimeoutException as exc:
        error = f"{type(exc).__name__}: no complete answer within {timeout_s:g} s (SPINE_WEBHOOK_TIMEOUT_S)"
    except httpx.HTTPError as exc:
        error = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    finally:
        _DEADLINE.reset(token)
    if status_code is not None and not 200 <= status_code < 300:
        error = f"HTTP {status_code}" + (" (redirects are not followed)" if 300 <= status_code < 400 else "")
    return PostOutcome(status_code, retry_after, error, (time.perf_counter() - started) * 1000, date)


def retry_delay(settings: Settings, attempt: int, retry_after: str | None = None, date: str | None = None) -> float:
    """Delay (s) before attempt ``attempt + 1``: base·2^(attempt−1), or the receiver's ``Retry-After`` if
    longer; at most ``MAX_RETRY_DELAY_S``.

    ``Retry-After`` is delay-seconds or an HTTP-date (RFC 9110 §10.2.3). An HTTP-date is a time on the
    receiver's clock, so it is read against the receiver's ``Date`` of the same answer (RFC 9110 §6.6.1)
    when that parses, never against this worker's clock, which may differ from the receiver's by any
    amount; without a usable ``Date``, against this worker's clock. A date in the past asks for no delay
    (the backoff applies), one beyond ``MAX_RETRY_DELAY_S`` is capped, and a value that is neither form
    is ignored.
    """
    delay = settings.webhook_retry_base_s * 2 ** (attempt - 1)
    wanted = _retry_after_s(retry_after, date)
    if wanted is not None:
        delay = max(delay, wanted)
    return min(delay, MAX_RETRY_DELAY_S)


def _http_date(value: str | None) -> datetime | None:
    """An HTTP-date (RFC 9110 §5.6.7: IMF-fixdate, or the obsolete RFC 850 and asctime forms, all UTC),
    or None when ``value`` is none of them. The asctime form carries no zone: it is UTC."""
    if not value:
        return None
    try:
        parsed = parsedate_to_datetime(value)
    except (TypeError, ValueError, IndexError, OverflowError):
        return None
    return parsed if parsed.tzinfo is not None else parsed.replace(tzinfo=UTC)


def _retry_after_s(value: str | None, date: str | None = None) -> float | None:
    """The seconds a ``Retry-After`` asks for (at least 0), read against ``date`` (the answer's ``Date``)
    or, without one, this worker's clock; None when ``value`` is neither delay-seconds nor an HTTP-date."""
    if not value:
        return None
    try:
        seconds = float(value)
    except ValueError:
        pass
    else:
        return seconds if seconds > 0 else 0.0  # a NaN or a negative asks for nothing
    at = _http_date(value)
    if at is None:
        return None
    return max(0.0, (at - (_http_date(date) or utcnow())).total_seconds())
