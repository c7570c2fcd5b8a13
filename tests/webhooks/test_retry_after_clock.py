"""A receiver's ``Retry-After`` HTTP-date is a time on the receiver's clock (RFC 9110 §10.2.3), so the
delay it asks for is read against the ``Date`` of the same answer (RFC 9110 §6.6.1), not against the
worker's clock: a receiver whose clock is an hour ahead asking for 30 s got the 120-s cap
(``MAX_RETRY_DELAY_S``), one an hour behind got the 2-s backoff (its date already past for us), and an
asctime date (RFC 9110 §5.6.7, no zone: UTC) was ignored. A date in the past asks for nothing (the
backoff applies), a date or a number beyond the cap is capped, and a value of neither form is ignored.

Real pieces: the database (SQLite), the webhook receiver (an HTTP server on a free loopback port that
writes its own ``Date``, on a clock ``offset`` from the host's) and ``deliver_once``'s request."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from email.utils import format_datetime
from http.server import BaseHTTPRequestHandler
from pathlib import Path

import pytest

from services.core.config import Settings
from services.db import jobs
from services.db.engine import session_scope
from services.db.migrate import upgrade
from services.webhooks.delivery import MAX_RETRY_DELAY_S
from services.worker import webhook_tasks
from tests.conftest import spine_payload
from tests.interop_helpers import TEST_WEBHOOK_SECRET, LoopbackReceiver, reply

BASE_S = 2.0
"""The backoff before attempt 2 (SPINE_WEBHOOK_RETRY_BASE_S's default)."""
ASKED_S = 30
"""The delay the receiver asks for: between the backoff and the cap (MAX_RETRY_DELAY_S, 120 s)."""
HOUR = timedelta(hours=1)


def _imf(moment: datetime) -> str:
    """IMF-fixdate (RFC 9110 §5.6.7): ``Sun, 06 Nov 1994 08:49:37 GMT``."""
    return format_datetime(moment.astimezone(UTC), usegmt=True)


def _asctime(moment: datetime) -> str:
    """The obsolete asctime form (RFC 9110 §5.6.7): ``Sun Nov  6 08:49:37 1994``, UTC."""
    return moment.astimezone(UTC).strftime("%a %b %e %H:%M:%S %Y")


Headers = Callable[[datetime], dict[str, str]]
"""The headers of the receiver's 503, from the receiver's clock's now."""


HOOK = "/hooks/retry-after"


class Receiver(LoopbackReceiver):
    """Answers 503 with the headers ``headers`` gives for its clock (the host's plus ``offset``)."""

    def __init__(self, offset: timedelta, headers: Headers) -> None:
        def answer(handler: BaseHTTPRequestHandler, _body: bytes) -> None:
            now = datetime.now(UTC).replace(microsecond=0) + offset
            reply(handler, 503, headers(now), server_date=False)  # without the host's own Date

        super().__init__(answer)


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    made = Settings(data_dir=tmp_path, webhook_secret=TEST_WEBHOOK_SECRET)
    upgrade(made, quiet=True)
    return made


@pytest.fixture
def delay_for(settings: Settings) -> Iterator[Callable[[timedelta, Headers], float | None]]:
    """The delay ``deliver_once`` gives attempt 2 after a receiver on a clock ``offset`` from the host's
    answered attempt 1 with 503 and the given headers."""
    receivers: list[Receiver] = []

    def run(offset: timedelta, headers: Headers) -> float | None:
        receiver = Receiver(offset, headers)
        receivers.append(receiver)
        hooks = settings.model_copy(update={"webhook_allowed_urls": receiver.url(HOOK)})
        with session_scope(hooks) as session:
            job, _ = jobs.create_job(session, {**spine_payload(), "callback_url": receiver.url(HOOK)})
            jobs.cancel_job(session, job.id)
        return webhook_tasks.deliver_once(hooks, job.id, "cancelled", 1)

    yield run
    for receiver in receivers:
        receiver.close()


def _asks(fmt: Callable[[datetime], str], seconds: float) -> Headers:
    return lambda now: {"date": _imf(now), "retry-after": fmt(now + timedelta(seconds=seconds))}


def _asks_without_date(date: str | None) -> Headers:
    def headers(now: datetime) -> dict[str, str]:
        return {"retry-after": _imf(now + timedelta(seconds=ASKED_S)), **({"date": date} if date else {})}

    return headers


@pytest.mark.parametrize("offset", [HOUR, -HOUR, timedelta(0)], ids=["receiver-ahead", "receiver-behind", "same"])
def test_a_retry_after_date_is_read_against_the_receivers_date(
    delay_for: Callable[[timedelta, Headers], float | None], offset: timedelta
) -> None:
    assert delay_for(offset, _asks(_imf, ASKED_S)) == ASKED_S


def test_an_asctime_retry_after_is_a_utc_date(delay_for: Callable[[timedelta, Headers], float | None]) -> None:
    assert delay_for(timedelta(0), _asks(_asctime, ASKED_S)) == ASKED_S


def test_without_a_date_the_retry_after_date_is_read_against_the_workers_clock(
    delay_for: Callable[[timedelta, Headers], float | None],
) -> None:
    """No usable ``Date`` (none, or not a date): the worker's clock, the host's here; the answer's second
    is truncated (HTTP-dates are whole seconds), so up to 1 s less than asked, plus the request's time."""
    for date in (None, "yesterday"):
        delay = delay_for(timedelta(0), _asks_without_date(date))
        assert delay is not None and ASKED_S - 2 < delay <= ASKED_S


@pytest.mark.parametrize(
    ("headers", "expected"),
    [
        (_asks(_imf, -60), BASE_S),  # a date in the past: no wait asked, the backoff applies
        (_asks(_imf, 86_400), MAX_RETRY_DELAY_S),  # a day ahead: capped
        (lambda now: {"retry-after": "100000"}, MAX_RETRY_DELAY_S),
        (lambda now: {"retry-after": "soon"}, BASE_S),  # neither form: ignored
        (lambda now: {"retry-after": "-5"}, BASE_S),
        (lambda now: {"retry-after": "nan"}, BASE_S),
        (lambda now: {"retry-after": "Fri, 31 Dec 99999 23:59:59 GMT"}, BASE_S),
    ],
    ids=["past", "far-future", "far-seconds", "unparsable", "negative", "nan", "year-99999"],
)
def test_odd_retry_after_values_are_bounded(
    delay_for: Callable[[timedelta, Headers], float | None], headers: Headers, expected: float
) -> None:
    assert delay_for(timedelta(0), headers) == expected
