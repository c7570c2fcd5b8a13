"""Bad client arguments are usage errors (exit 2) naming the option, before any request: a --url
(or $SPINE_URL) that is not an http(s) URL, or that carries user:password@ (httpx would send it as
Basic authentication instead of the Bearer key), a --request-timeout not above 0, --retries below
0. A URL's password is never printed."""

from __future__ import annotations

import http.server
import threading
from collections.abc import Iterator
from typing import Any, ClassVar

import pytest

from spine_client import SpineClient, cli

JOB_ID = "00000000-0000-4000-8000-000000000000"


class _Counting(http.server.BaseHTTPRequestHandler):
    seen: ClassVar[list[dict[str, str]]] = []

    def do_GET(self) -> None:
        _Counting.seen.append({k.lower(): v for k, v in self.headers.items()})
        self.send_response(401)
        self.send_header("content-length", "0")
        self.end_headers()

    def log_message(self, *_: Any) -> None:
        pass


@pytest.fixture()
def server() -> Iterator[str]:
    _Counting.seen = []
    httpd = http.server.HTTPServer(("127.0.0.1", 0), _Counting)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    yield f"127.0.0.1:{httpd.server_address[1]}"
    httpd.shutdown()
    httpd.server_close()


@pytest.mark.parametrize("url", ["ftp://127.0.0.1:{port}", "not a url", "127.0.0.1:{port}", "http://127.0.0.1:99999",
                                 "http://"])  # fmt: skip
def test_a_url_that_is_not_the_services_is_a_usage_error(
    url: str, server: str, capsys: pytest.CaptureFixture[str]
) -> None:
    port = server.split(":")[1]
    assert cli.main(["list", "--url", url.format(port=port), "--api-key", "k", "--retries", "0"]) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert err.startswith("spine: error: --url is not the service's URL: ") and "Traceback" not in err
    assert _Counting.seen == []


def test_a_url_with_a_password_is_refused_and_the_password_never_printed(
    server: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    url = f"http://user:hunter2@{server}"
    assert cli.main(["list", "--url", url, "--api-key", "k", "--retries", "0"]) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert "--url" in err and "password" in err and "hunter2" not in err
    monkeypatch.setenv("SPINE_URL", url)
    assert cli.main(["list", "--api-key", "k", "--retries", "0"]) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert "$SPINE_URL" in err and "hunter2" not in err
    assert _Counting.seen == []  # no request: the key was never replaced by Basic credentials
    with pytest.raises(ValueError, match="user name or password") as refused:
        SpineClient(url, "k")
    assert "hunter2" not in str(refused.value)


@pytest.mark.parametrize(("option", "value", "says"), [
    ("--request-timeout", "0", "above 0"), ("--request-timeout", "-1", "above 0"),
    ("--request-timeout", "nan", "above 0"), ("--request-timeout", "soon", "above 0"),
    ("--retries", "-1", "0 or more"), ("--retries", "x", "0 or more"),
])  # fmt: skip
def test_timeouts_and_retries_out_of_range_are_usage_errors(
    option: str, value: str, says: str, server: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as stopped:
        cli.main(["list", "--url", f"http://{server}", "--api-key", "k", option, value])
    assert stopped.value.code == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert f"argument {option}: must be" in err and says in err
    assert _Counting.seen == []


def test_a_good_url_still_reaches_the_service(server: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["get", JOB_ID, "--url", f"http://{server}/", "--api-key", "k", "--retries", "0"]) == cli.EXIT_AUTH
    assert _Counting.seen and _Counting.seen[0]["authorization"] == "Bearer k"


def test_a_bug_of_the_client_exits_70_with_its_traceback(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """An exception no handler expects (a bug) exits with 70, apart from 1 (a job that failed), which a
    QA script would otherwise read as the job's outcome; its traceback is on stderr, stdout stays empty."""

    def broken(argv: list[str]) -> int:
        raise RuntimeError("a bug in the client")

    monkeypatch.setattr(cli, "_main", broken)
    assert cli.main(["list"]) == cli.EXIT_INTERNAL == 70
    out, err = capsys.readouterr()
    assert out == ""
    assert "Traceback" in err and "RuntimeError: a bug in the client" in err
    assert err.rstrip().endswith("please report it with the traceback above)")
