"""A callback_url's query string and user info (a receiver's access token) never reach the logs:
the service's logging set-up keeps the HTTP client's loggers (httpx writes every request's URL at
INFO) at WARNING, and the service's own lines about a delivery name the job, not the URL."""

from __future__ import annotations

import io
import logging
import uuid
from collections.abc import Iterator

import pytest

from services.core.config import Settings
from services.core.logs import QUIET_LOGGERS, configure_logging
from services.worker import webhook_tasks
from tests.interop_helpers import Receiver, cancelled_job_calling

TOKEN = "SECRET-TOKEN-123"


@pytest.fixture()
def service_logs() -> Iterator[io.StringIO]:
    """The service's own logging set-up (``configure_logging``, as ``spine worker`` runs it), at DEBUG,
    writing to a buffer; the root logger and the libraries' levels restored afterwards."""
    root = logging.getLogger()
    saved = (list(root.handlers), root.level, {name: logging.getLogger(name).level for name in QUIET_LOGGERS})
    configure_logging("DEBUG")
    stream = io.StringIO()
    root.handlers[0].setStream(stream)  # type: ignore[attr-defined]
    yield stream
    for handler in list(root.handlers):
        root.removeHandler(handler)
    for handler in saved[0]:
        root.addHandler(handler)
    root.setLevel(saved[1])
    for name, level in saved[2].items():
        logging.getLogger(name).setLevel(level)


def test_a_callback_urls_token_is_never_logged(db_settings: Settings, service_logs: io.StringIO) -> None:
    receiver = Receiver()
    try:
        path = f"/hooks/{uuid.uuid4().hex}?access_token={TOKEN}"
        receiver.plan[path] = [500]
        settings, job_id = cancelled_job_calling(db_settings, receiver.url(path),
                                                 webhook_allowed_urls=receiver.url("/hooks"))  # fmt: skip
        assert webhook_tasks.deliver_once(settings, job_id, "cancelled", 1) is not None  # 500: retried
        assert webhook_tasks.deliver_once(settings, job_id, "cancelled", 2) is None  # 204
        assert [r.answered for r in receiver.received] == [500, 204]
        assert all(TOKEN in r.path for r in receiver.received)  # it was sent, to the receiver only
    finally:
        receiver.close()
    logged = service_logs.getvalue()
    assert TOKEN not in logged
    assert "HTTP Request" not in logged  # httpx's INFO line, which carries the full URL
