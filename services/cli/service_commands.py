"""The service's commands of ``spine``: serve, worker, migrate, keys, openapi, loadtest, bench.

``spine serve`` runs the API with uvicorn and, on the embedded default, a Celery worker as its
child process (Ctrl-C stops both). ``spine bench ...`` hands its arguments to the engine's benches
(``benches.cli``), a package of the source checkout that the wheel does not ship. The client's
commands (``spine submit|get|list…``) never come here: ``services.cli.main`` hands them to the client
first, so that they do not load what these commands need (SQLAlchemy, alembic, psycopg).
"""

from __future__ import annotations

import argparse
import ctypes
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import yaml

from services.cli.client_commands import CLIENT_COMMANDS
from services.cli.errors import explain
from services.cli.keys import add_keys_parser, announce_first_key, ensure_first_key
from services.core.config import Settings, get_settings
from services.core.logs import configure_logging, install_celery_job_context, uvicorn_log_config
from services.db.migrate import upgrade
from services.worker.heap import freeze_for_exit

log = logging.getLogger("services.cli")
DESCRIPTION = "The ``spine`` command: serve, worker, migrate, openapi, loadtest, bench; submit, get, list… (client)."
"""``spine --help``'s first line."""
EXIT_INTERRUPTED = 130
"""128 + SIGINT (2): what a shell reports for a command Ctrl-C ended (the client's code too, spine_client.cli)."""
EXIT_BROKEN_PIPE = 141
"""128 + SIGPIPE (13): what a shell reports for a command whose reader closed the pipe (``spine openapi | head``)."""
CHECKOUT = Path(__file__).resolve().parents[2]
"""The source checkout beside ``services/`` (an editable install); a wheel's site-packages has no tools or benches."""
TOOLS_DIR = CHECKOUT / "tools"
"""The repository's tools/ (load benchmark), beside services/: not part of the installed package."""
BENCHES_DIR = CHECKOUT / "benches"
"""The repository's benches/ (``spine bench``), beside services/: not part of the installed package."""


def _settings() -> Settings:
    return get_settings()


def cmd_migrate(_: argparse.Namespace) -> int:
    upgrade(_settings())
    return 0


def cmd_openapi(_: argparse.Namespace) -> int:
    sys.stdout.write(openapi_yaml())
    return 0


def openapi_yaml() -> str:
    """The app's OpenAPI schema as YAML, exactly as ``openapi.yaml`` holds it."""
    from services.api.app import create_app  # lazy: the API (FastAPI, fhir.resources) only for this command

    schema = create_app(Settings()).openapi()
    return yaml.safe_dump(schema, sort_keys=False, allow_unicode=True, width=100)


NODE_PREFIX = "spine-"
"""A ``spine worker``'s Celery node is ``spine-<pid>@<host>`` (``worker_node_name``)."""


def worker_node_name(pid: int) -> str:
    """The Celery node name (``-n``) of the worker process ``pid``; Celery expands ``%h`` to the host."""
    return f"{NODE_PREFIX}{pid}@%h"


def worker_node_pid(node: str) -> int | None:
    """The process id in a node name ``worker_node_name`` made (``spine-<pid>@<host>``), else None."""
    digits = node.split("@", 1)[0].removeprefix(NODE_PREFIX)
    return int(digits) if node.startswith(NODE_PREFIX) and digits.isdigit() else None


def worker_argv(concurrency: int, beat: bool, loglevel: str, queue: str) -> list[str]:
    argv = ["worker", "--loglevel", loglevel, "-Q", queue, "-n", worker_node_name(os.getpid()), "--without-gossip",
            "--without-mingle"]  # fmt: skip
    if concurrency > 0:
        argv += ["--concurrency", str(concurrency)]
    if beat:
        argv += ["-B"]
    return argv


def cmd_worker(args: argparse.Namespace) -> int:
    if not args.child:
        return supervise_worker(args)
    settings = _settings()
    configure_logging(settings.log_level)  # JSON lines, with the job id of the task running
    install_celery_job_context()
    from services.worker.celery_app import app  # lazy: builds the worker's Celery app from the settings

    concurrency = args.concurrency if args.concurrency is not None else settings.worker_concurrency
    queues = f"{settings.queue_name},{settings.webhook_queue},{settings.dicom_queue}"  # jobs, webhooks, STOW-RS
    app.worker_main(worker_argv(concurrency, not args.no_beat, args.loglevel or settings.log_level,
                                queues))  # fmt: skip
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn  # lazy: the HTTP server only for `spine serve`

    settings = _settings()
    configure_logging(settings.log_level)  # JSON lines, with the request id
    if settings.embedded:
        upgrade(settings, quiet=True)
        first_key = ensure_first_key(settings)  # first start: an admin key, printed now and once ready
        if first_key is not None:
            host = "127.0.0.1" if args.host in ("0.0.0.0", "::") else args.host
            threading.Thread(target=announce_first_key, args=(first_key, f"http://{host}:{args.port}"),
                             name="spine-first-key", daemon=True).start()  # fmt: skip
    # uvicorn re-raises the signal that stopped it: make SIGTERM an exception, so that the
    # worker child is stopped below instead of being orphaned.
    signal.signal(signal.SIGTERM, _raise_exit)
    child: subprocess.Popen[bytes] | None = None
    if settings.starts_worker and not args.no_worker:
        # Its own session: a Ctrl-C or a group signal reaches `serve` only, which then stops the
        # worker with one SIGTERM (a pool child killed by a stray group signal hangs Celery's
        # shutdown). On Linux the worker is also told to stop if `serve` dies without cleaning up.
        child = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "worker"], start_new_session=True, preexec_fn=_die_with_parent
        )
        log.info("started worker process %d", child.pid)
    try:
        uvicorn.run(
            "services.api.app:create_app",
            factory=True,
            host=args.host,
            port=args.port,
            workers=args.workers,
            log_level=settings.log_level.lower(),
            log_config=uvicorn_log_config(settings.log_level),
            access_log=args.access_log,
        )
    finally:
        freeze_for_exit()  # the API has stopped: the interpreter's last collections need not walk its heap
        if child is not None:
            _stop(child)
    return 0


def _worker_child_argv(args: argparse.Namespace) -> list[str]:
    argv = [sys.executable, "-m", "services.cli", "worker", "--child"]
    if args.concurrency is not None:
        argv += ["--concurrency", str(args.concurrency)]
    if args.no_beat:
        argv.append("--no-beat")
    if args.loglevel:
        argv += ["--loglevel", args.loglevel]
    return argv


def supervise_worker(args: argparse.Namespace, max_backoff_s: float = 30.0) -> int:
    """Run the Celery worker as a child process and start it again whenever it stops unasked.

    Celery's worker can leave its main loop for good on a broker fault (seen here: kombu failing
    to reconnect to a restarted Redis while acknowledging a message); the jobs themselves are safe
    in the database, but nothing would consume them. SIGTERM or SIGINT to this process stops the
    child (one SIGTERM, then SIGKILL after a grace period) and ends the supervision. Restarts back
    off from 1 s to ``max_backoff_s``; a child that ran for a minute resets the backoff.
    """
    configure_logging(_settings().log_level)
    stopping: list[int] = []

    def _on_signal(signum: int, _frame: object) -> None:
        stopping.append(signum)

    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, _on_signal)
    backoff = 1.0
    while True:
        started = time.monotonic()
        child = subprocess.Popen(_worker_child_argv(args), preexec_fn=_die_with_parent)
        while child.poll() is None and not stopping:
            time.sleep(0.2)
        if stopping:
            _stop(child)
            return 0
        code = child.returncode
        if time.monotonic() - started > 60:
            backoff = 1.0
        log.warning("celery worker %d stopped unasked (exit code %s); starting it again in %.0f s",
                    child.pid, code, backoff)  # fmt: skip
        deadline = time.monotonic() + backoff
        while time.monotonic() < deadline and not stopping:
            time.sleep(0.2)
        if stopping:
            return 0
        backoff = min(2 * backoff, max_backoff_s)


def _die_with_parent() -> None:
    if sys.platform.startswith("linux"):
        pr_set_pdeathsig = 1
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGTERM)


def _raise_exit(signum: int, _frame: object) -> None:
    raise SystemExit(128 + signum)


def _stop(child: subprocess.Popen[bytes], grace: float = 30.0) -> None:
    if child.poll() is None:
        child.send_signal(signal.SIGTERM)
        try:
            child.wait(grace)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
    log.info("worker process %d stopped (exit %s)", child.pid, child.returncode)


def cmd_loadtest(args: argparse.Namespace) -> int:
    """Run the load benchmark (tools/loadbench.py, a tool of the repository, not of the package)."""
    if not (TOOLS_DIR / "loadbench.py").is_file():
        print(f"spine loadtest: the load benchmark is a tool of the source repository ({TOOLS_DIR} not found)",
              file=sys.stderr)  # fmt: skip
        return 2
    return subprocess.call([sys.executable, "-m", "tools.loadbench", *args.rest], cwd=TOOLS_DIR.parent)


def cmd_bench(args: argparse.Namespace) -> int:
    """Run a bench (``benches/cli.py``). The benches are a top-level package of the source checkout, not
    of the wheel: found in the checkout beside ``services/`` (an editable install, ``make install``)."""
    if not (BENCHES_DIR / "cli.py").is_file():
        print(f"spine bench: the benches are part of the source repository ({BENCHES_DIR} not found); "
              "run it from a checkout installed with `pip install -e .` (`make install`)", file=sys.stderr)  # fmt: skip
        return 2
    if str(CHECKOUT) not in sys.path:
        sys.path.append(str(CHECKOUT))  # the editable install maps the wheel's packages only
    from benches.cli import main as bench_main  # lazy: a package of the checkout, with the benches' data and plots

    return int(bench_main(args.rest))


def _port(value: str) -> int:
    """``--port``: a TCP port, 1 to 65535 (RFC 9293 §3.1: 16 bits; 0 would be any free port, unannounced)."""
    try:
        port = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a port number from 1 to 65535, not {value!r}") from None
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"must be a port number from 1 to 65535, not {port}")
    return port


def _at_least_one(value: str) -> int:
    """A whole number, 1 or more (``--workers``)."""
    try:
        number = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, 1 or more, not {value!r}") from None
    if number < 1:
        raise argparse.ArgumentTypeError(f"must be 1 or more, not {number}")
    return number


def package_version() -> str:
    """The installed service's version (``spine --version``), as pyproject.toml gives it."""
    try:
        return version("spine-reconstruction")
    except PackageNotFoundError:  # run from a checkout that was never installed
        return "(not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="spine", description=DESCRIPTION)
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}",
                        help="print the version and exit")  # fmt: skip
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    serve = sub.add_parser("serve", help="run the API (and, on the embedded default, a worker)")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=_port, default=8000, help="TCP port, 1 to 65535 (default 8000)")
    serve.add_argument("--workers", type=_at_least_one, default=1, help="uvicorn worker processes of the API")
    serve.add_argument("--no-worker", action="store_true", help="do not start a Celery worker child")
    serve.add_argument("--access-log", action="store_true", help="log every request")
    serve.set_defaults(func=cmd_serve)

    worker = sub.add_parser("worker", help="run a Celery worker with the reconciler (beat) embedded")
    worker.add_argument("--concurrency", type=int, default=None, help="processes (default SPINE_WORKER_CONCURRENCY)")
    worker.add_argument("--no-beat", action="store_true", help="do not run the reconciler in this worker")
    worker.add_argument("--loglevel", default=None)
    worker.add_argument("--child", action="store_true",
                        help="run the Celery worker in this process, unsupervised (what the supervisor starts)")
    worker.set_defaults(func=cmd_worker)

    migrate = sub.add_parser("migrate", help="apply the database migrations")
    migrate.set_defaults(func=cmd_migrate)

    add_keys_parser(sub)  # spine keys create|list|revoke

    openapi = sub.add_parser("openapi", help="print the API's OpenAPI schema as YAML")
    openapi.set_defaults(func=cmd_openapi)

    loadtest = sub.add_parser("loadtest", help="load benchmark of a running service (tools/loadbench.py)",
                              add_help=False)  # fmt: skip
    loadtest.add_argument("rest", nargs=argparse.REMAINDER)
    loadtest.set_defaults(func=cmd_loadtest)

    bench = sub.add_parser("bench", help="the engine's benches (benches/, in a source checkout)", add_help=False)
    bench.add_argument("rest", nargs=argparse.REMAINDER)
    bench.set_defaults(func=cmd_bench)

    for name, text in CLIENT_COMMANDS.items():  # listed here; services.cli.main hands them to the client
        sub.add_parser(name, help=text, add_help=False)
    return parser




PASSTHROUGH = {"bench": cmd_bench, "loadtest": cmd_loadtest}
"""Subcommands whose arguments belong to another parser: handed over untouched."""


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in PASSTHROUGH:
        return PASSTHROUGH[argv[0]](argparse.Namespace(rest=argv[1:]))
    try:
        try:
            args = build_parser().parse_args(argv)
            return int(args.func(args))
        finally:  # here, where a closed pipe is still caught (also after --help)
            sys.stdout.flush()
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # `spine openapi | head -1`: the reader is gone, as after SIGPIPE
        return stdout_closed()
    except Exception as exc:
        explained = _explain(exc)
        if explained is None:
            raise
        code, line = explained
        command = " ".join(argv[:2] if argv[:1] == ["keys"] else argv[:1])
        print(f"spine {command}: {line}", file=sys.stderr)
        return code


def stdout_closed() -> int:
    """After a ``BrokenPipeError``: stdout's reader is gone. Points stdout at the null device, so that the
    interpreter's last flush does not fail again, and returns ``EXIT_BROKEN_PIPE``. The client's
    ``spine_client.cli.stdout_closed`` does the same; it is not imported here, so that an operator command
    does not load the client (httpx, its models: 0.3 s)."""
    with open(os.devnull, "wb") as devnull:
        os.dup2(devnull.fileno(), sys.stdout.fileno())
    return EXIT_BROKEN_PIPE


def _explain(exc: BaseException) -> tuple[int, str] | None:
    """``services.cli.errors.explain`` of the exception or of one it came from."""
    try:
        url: str | None = _settings().sqlalchemy_url
    except Exception:
        url = None
    seen: BaseException | None = exc
    while seen is not None:
        explained = explain(seen, url)
        if explained is not None:
            return explained
        seen = seen.__cause__ or seen.__context__
    return None

