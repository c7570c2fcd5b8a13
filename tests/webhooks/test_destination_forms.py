"""The other spellings of an allowed webhook host an attacker tries (decimal, octal and hexadecimal
IPv4, IPv4-mapped IPv6, loopback names, a trailing dot, the cloud metadata address), and a receiver
that answers with a redirect to another address: none reaches any host but the allowed one."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import pytest

from services.core.webhook_policy import allow_list, destination_problem
from services.webhooks.delivery import post

ALLOWED = "http://127.0.0.1:9000/hooks/"


@pytest.mark.parametrize(
    "url",
    [
        "http://2130706433:9000/hooks/x",  # 127.0.0.1 as one decimal number
        "http://0x7f.0.0.1:9000/hooks/x",  # hexadecimal part
        "http://0177.0.0.1:9000/hooks/x",  # octal part
        "http://127.1:9000/hooks/x",  # inet_aton's short form
        "http://127.0.0.1.:9000/hooks/x",  # trailing dot
        "http://[::ffff:127.0.0.1]:9000/hooks/x",  # IPv4-mapped IPv6 (RFC 4291 §2.5.5.2)
        "http://[::ffff:7f00:1]:9000/hooks/x",
        "http://[::1]:9000/hooks/x",
        "http://localhost:9000/hooks/x",
        "http://169.254.169.254/latest/meta-data/",  # cloud instance metadata (link-local)
        "http://[fe80::1%25eth0]:9000/hooks/x",
        "http://0.0.0.0:9000/hooks/x",
    ],
)
def test_other_spellings_of_the_allowed_host_are_refused(url: str) -> None:
    """The host is compared as the operator wrote it, never resolved nor normalised into an address."""
    reason = destination_problem(url, allow_list(ALLOWED))
    assert reason is not None, url


@pytest.mark.parametrize("url", ["http://[127.0.0.1]:9000/hooks/x", "http://127.0.0.1:９０００/hooks/x"])
def test_a_url_that_does_not_parse_is_refused(url: str) -> None:
    reason = destination_problem(url, allow_list(ALLOWED))
    assert reason is not None and "parse" in reason, reason


class _Server:
    """A loopback HTTP server answering every POST with ``status`` (and ``Location`` when given),
    counting the requests it got."""

    def __init__(self, status: int, location: str | None = None):
        self.hits = 0
        server = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                self.rfile.read(int(self.headers.get("content-length") or 0))
                server.hits += 1
                self.send_response(status)
                if location:
                    self.send_header("Location", location)
                self.send_header("content-length", "0")
                self.end_headers()

            def do_GET(self) -> None:  # a 303 followed would come as a GET
                self.do_POST()

            def log_message(self, *_: Any) -> None:
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = int(self.httpd.server_address[1])
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def inner() -> Iterator[_Server]:
    """What the attacker wants reached: a host the allow-list does not name."""
    server = _Server(200)
    yield server
    server.close()


@pytest.mark.parametrize("status", [301, 302, 303, 307, 308])
def test_a_redirect_to_another_address_is_not_followed(inner: _Server, status: int) -> None:
    receiver = _Server(status, location=f"http://127.0.0.1:{inner.port}/latest/meta-data/")
    try:
        outcome = post(f"http://127.0.0.1:{receiver.port}/hooks/x", b"{}", {"content-type": "application/json"}, 5.0)
    finally:
        receiver.close()
    assert receiver.hits == 1 and inner.hits == 0
    assert outcome.status_code == status and not outcome.accepted
    assert outcome.error == f"HTTP {status} (redirects are not followed)"
