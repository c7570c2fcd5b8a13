"""Real HTTP peers for the client, CLI and webhook tests, all on 127.0.0.1: a webhook receiver, a
proxy that loses or refuses chosen requests (to exercise the client's retries against the real
service), a `spine serve` subprocess (API and worker) and an in-thread API without a worker."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import httpx
from pydantic import SecretStr

from services.core.config import Settings
from services.db import jobs as repo
from services.db.engine import session_scope
from tests.conftest import spine_payload
from tools.processes import stop_processes

TEST_WEBHOOK_SECRET = SecretStr("whsec_" + "A" * 43 + "=")
"""The signing secret of the webhook tests' settings."""


def cancelled_job_calling(settings: Settings, url: str, **update: Any) -> tuple[Settings, Any]:
    """``settings`` allowing ``url`` and signing with ``TEST_WEBHOOK_SECRET`` (then ``update``), and the
    id of a job that calls back ``url``, cancelled: its webhook is due."""
    settings = settings.model_copy(update={"webhook_allowed_urls": url, "webhook_secret": TEST_WEBHOOK_SECRET,
                                           **update})  # fmt: skip
    payload: dict[str, Any] = spine_payload()
    payload["callback_url"] = url
    with session_scope(settings) as session:
        job, _ = repo.create_job(session, payload)
        repo.cancel_job(session, job.id)
    return settings, job.id


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def api_key_for(settings: Settings, name: str, role: str = "admin") -> str | None:
    """A new API key in the service's database, or None while the service has no API keys."""
    try:
        from services.db.keys import create_key  # type: ignore[import-not-found, unused-ignore]
    except ImportError:
        return None
    from services.db.engine import session_factory

    with session_factory(settings)() as session:
        return str(create_key(session, name, role)[1])


def wait_until(check: Callable[[], Any], timeout: float, what: str, interval: float = 0.1) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)


# ------------------------------------------------------------------ webhook receiver


@dataclass
class Received:
    path: str
    headers: dict[str, str]
    body: bytes
    answered: int

    def json(self) -> Any:
        return json.loads(self.body)


def reply(handler: BaseHTTPRequestHandler, status: int, headers: dict[str, str] | None = None, *,
          server_date: bool = True) -> None:
    """Answer a request with an empty body: ``status``, ``headers``, and the server's own ``Date``
    unless ``server_date`` is false (a receiver that writes its own)."""
    if server_date:
        handler.send_response(status)
    else:
        handler.send_response_only(status)
    for name, value in (headers or {}).items():
        handler.send_header(name, value)
    handler.send_header("content-length", "0")
    handler.end_headers()


class LoopbackReceiver:
    """A webhook receiver on a free loopback port, served by a daemon thread: each POST's body is read
    and ``answer(handler, body)`` answers it (``reply``); ``close`` stops it."""

    def __init__(self, answer: Callable[[BaseHTTPRequestHandler, bytes], None]) -> None:
        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                answer(self, self.rfile.read(int(self.headers.get("content-length") or 0)))

            def log_message(self, *_: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = int(self.server.server_address[1])
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.port}{path}"

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@dataclass
class Receiver:
    """Records every POST; answers the statuses queued in ``plan[path]`` first, then 204."""

    plan: dict[str, list[int]] = field(default_factory=dict)
    received: list[Received] = field(default_factory=list)

    def __post_init__(self) -> None:
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("content-length") or 0))
                queued = receiver.plan.get(self.path) or []
                status = queued.pop(0) if queued else 204
                receiver.received.append(Received(self.path, {k.lower(): v for k, v in self.headers.items()}, body,
                                                  status))  # fmt: skip
                self.send_response(status)
                self.send_header("content-length", "0")
                self.end_headers()

            def log_message(self, *_: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.server.server_address[1]
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.port}{path}"

    def at(self, path: str) -> list[Received]:
        return [r for r in self.received if r.path == path]

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


# ------------------------------------------------------------------ flaky proxy


@dataclass
class Rule:
    method: str
    path: str
    mode: str  # "lose": forward, then answer `status` instead of the service's answer; "refuse": do not forward
    status: int
    times: int = 1
    headers: dict[str, str] = field(default_factory=dict)


class FlakyProxy:
    """A reverse proxy in front of a real service that loses or refuses the requests its rules name."""

    def __init__(self, target: str):
        self.rules: list[Rule] = []
        self.log: list[tuple[str, str, int, bool]] = []  # method, path, status sent, forwarded
        self.upstream = httpx.Client(base_url=target, timeout=30)
        proxy = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def do_GET(self) -> None:
                self._handle()

            def do_POST(self) -> None:
                self._handle()

            def _handle(self) -> None:
                body = self.rfile.read(int(self.headers.get("content-length") or 0))
                path = self.path.split("?", 1)[0]
                rule = next((r for r in proxy.rules if r.times > 0 and r.method == self.command and r.path == path),
                            None)  # fmt: skip
                if rule is not None:
                    rule.times -= 1
                forwarded = rule is None or rule.mode == "lose"
                if forwarded:
                    headers = {k: v for k, v in self.headers.items() if k.lower() not in ("host", "content-length",
                                                                                         "connection")}  # fmt: skip
                    answer = proxy.upstream.request(self.command, self.path, content=body, headers=headers)
                    status, content = answer.status_code, answer.content
                    out = {k: v for k, v in answer.headers.items() if k.lower() in ("content-type", "location",
                                                                                    "retry-after")}  # fmt: skip
                if rule is not None:
                    status, content = rule.status, b'{"type": "about:blank", "title": "flaky proxy"}'
                    out = {"content-type": "application/problem+json", **rule.headers}
                proxy.log.append((self.command, path, status, forwarded))
                self.send_response(status)
                for k, v in out.items():
                    self.send_header(k, v)
                self.send_header("content-length", str(len(content)))
                self.end_headers()
                self.wfile.write(content)

            def log_message(self, *_: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        self.upstream.close()


# ------------------------------------------------------------------ services


class Served:
    """`spine serve` (API and worker) as a subprocess on a free port: the embedded default, or
    PostgreSQL and Redis when ``DATABASE_URL`` and ``CELERY_BROKER_URL`` are given (with
    ``SPINE_SERVE_WORKER=true``, so that `serve` still starts its worker)."""

    def __init__(self, data_dir: Path, **env: str):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.data_dir = data_dir
        self.log = data_dir / "serve.log"
        self.env = {k: v for k, v in os.environ.items() if k not in ("DATABASE_URL", "CELERY_BROKER_URL")}
        self.env.update(SPINE_DATA_DIR=str(data_dir), SPINE_WORKER_CONCURRENCY="2", **env)
        self.settings = Settings(data_dir=data_dir, DATABASE_URL=env.get("DATABASE_URL"),
                                 CELERY_BROKER_URL=env.get("CELERY_BROKER_URL"))  # fmt: skip
        from services.db.migrate import upgrade

        upgrade(self.settings, quiet=True)
        self.api_key = api_key_for(self.settings, "interop-admin")
        if self.api_key:
            self.env["SPINE_API_KEY"] = self.api_key
        self.env["SPINE_URL"] = self.url
        with self.log.open("wb") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "services.cli", "serve", "--port", str(self.port)],
                env=self.env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
            )  # fmt: skip
        try:
            wait_until(self._ready, 60, f"spine serve on {self.url}", 0.2)
        except AssertionError:
            self.stop()
            raise AssertionError(f"spine serve did not become ready:\n{self.text()[-4000:]}") from None

    def _ready(self) -> bool:
        assert self.proc.poll() is None, self.text()[-4000:]
        try:
            return httpx.get(f"{self.url}/readyz", timeout=2).status_code == 200 and " ready." in self.text()
        except httpx.TransportError:
            return False

    def text(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def stop(self) -> None:
        stop_processes([self.proc], grace_s=40, first=signal.SIGINT)


class ApiOnly:
    """The API alone (uvicorn in a thread, no worker) on a fresh embedded database: jobs stay queued."""

    def __init__(self, data_dir: Path):
        import uvicorn

        from services.api.app import create_app
        from services.db.migrate import upgrade

        self.settings = Settings(data_dir=data_dir)
        upgrade(self.settings, quiet=True)
        self.api_key = api_key_for(self.settings, "interop-api-only")
        port = free_port()
        self.url = f"http://127.0.0.1:{port}"
        config = uvicorn.Config(create_app(self.settings), host="127.0.0.1", port=port, log_level="warning")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        wait_until(lambda: self.server.started, 30, "the in-thread API")

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(10)
