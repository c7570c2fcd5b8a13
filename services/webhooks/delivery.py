"""One POST of a job's webhook to its receiver, and what its answer means for the next attempt.

``webhook_body`` is the JSON a receiver gets; ``post`` sends it (signed by the caller with
``signing.signed_headers``) without following redirects and without proxies from the environment, and
reports the receiver's status, ``Retry-After`` and any transport error; ``retry_delay`` is the backoff
before the next attempt (``Retry-After`` honoured). Recording, retrying and publishing are the worker's
(``services.worker.webhook_tasks``).
"""

from __future__ import annotations

import json
import os
import threading
import time
from dataclasses import dataclass
from datetime import datetime
from email.utils import parsedate_to_datetime
from typing import Any

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
    transport error, and the time it took (ms)."""

    status_code: int | None
    retry_after: str | None
    error: str | None
    duration_ms: float

    @property
    def accepted(self) -> bool:
        """The receiver answered 2xx."""
        return self.status_code is not None and 200 <= self.status_code < 300


def webhook_body(job: dict[str, Any], status: str, finished_at: datetime | None) -> bytes:
    """The JSON a receiver gets: ``{"type": "job.<status>", "timestamp", "data": <the job>}``."""
    body = {"type": f"job.{status}", "timestamp": iso_utc(finished_at or utcnow()), "data": job}
    return json.dumps(body, separators=(",", ":"), ensure_ascii=False).encode()


_CLIENTS: dict[tuple[float, int], httpx.Client] = {}
_LOCK = threading.Lock()


def _client(timeout: float) -> httpx.Client:
    key = (timeout, os.getpid())
    with _LOCK:
        if key not in _CLIENTS:
            # No redirects (a 3xx could point anywhere), no proxies or .netrc from the environment.
            _CLIENTS[key] = httpx.Client(
                timeout=timeout, follow_redirects=False, trust_env=False, headers={"user-agent": USER_AGENT}
            )
        return _CLIENTS[key]


def post(url: str, body: bytes, headers: dict[str, str], timeout_s: float) -> PostOutcome:
    """POST ``body`` to ``url``; never raises for the receiver's faults (they are in the outcome)."""
    started = time.perf_counter()
    status_code: int | None = None
    retry_after: str | None = None
    error: str | None = None
    try:
        with _client(timeout_s).stream("POST", url, content=body, headers=headers) as response:
            status_code = response.status_code
            retry_after = response.headers.get("retry-after")
    except httpx.HTTPError as exc:
        error = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    if status_code is not None and not 200 <= status_code < 300:
        error = f"HTTP {status_code}" + (" (redirects are not followed)" if 300 <= status_code < 400 else "")
    return PostOutcome(status_code, retry_after, error, (time.perf_counter() - started) * 1000)


def retry_delay(settings: Settings, attempt: int, retry_after: str | None = None) -> float:
    """Delay before attempt ``attempt + 1``: base·2^(attempt−1), or the receiver's Retry-After if longer."""
    delay = settings.webhook_retry_base_s * 2 ** (attempt - 1)
    wanted = _retry_after_s(retry_after)
    if wanted is not None:
        delay = max(delay, wanted)
    return min(delay, MAX_RETRY_DELAY_S)


def _retry_after_s(value: str | None) -> float | None:
    if not value:
        return None
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        return max(0.0, (parsedate_to_datetime(value) - utcnow()).total_seconds())
    except (TypeError, ValueError):
        return None
