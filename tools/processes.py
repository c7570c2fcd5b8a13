"""Stopping the service processes the tools and the tests start (``spine serve``, ``spine worker``)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Sequence
from types import FrameType

INTERRUPTED = 130
"""Exit status of a tool stopped by SIGINT or SIGTERM (128 + SIGINT, the shell's convention)."""


_STOP_ASKED = threading.Event()
"""A stop signal arrived."""
_STOPPING = threading.Event()
"""The tool began stopping what it started (``stop_processes``, ``run_tool``): no more interrupts."""


def interrupt_on_signals() -> None:
    """Make SIGTERM (a QA script's timeout, ``kill``) and SIGINT (Ctrl-C) raise ``KeyboardInterrupt``
    in the main thread, so that a tool's ``finally`` blocks run and stop the processes it started.

    Without it SIGTERM ends the tool at once and leaves its service running, and under
    ``asyncio.run`` SIGINT only cancels the main task, which a pending ``gather`` can absorb (seen:
    the load bench kept running after Ctrl-C). A handler other than Python's default also keeps
    ``asyncio.run`` from installing its own (Python 3.11 ``asyncio.Runner``).

    Python drops an exception raised while it runs a finaliser (a weakref callback, ``__del__``:
    "Exception ignored in …"), and a signal handled there is lost (seen: the load bench ran on after
    one SIGTERM). So the first signal also starts a thread that interrupts the main thread again
    every second until the tool has begun stopping (``_STOPPING``); a signal that comes while it
    stops is ignored, so that the stopping itself is not interrupted."""

    def interrupt(signum: int, _frame: FrameType | None) -> None:
        if _STOPPING.is_set():
            return
        if not _STOP_ASKED.is_set():
            _STOP_ASKED.set()
            threading.Thread(target=_interrupt_until_stopping, args=(signum,), daemon=True).start()
        raise KeyboardInterrupt(signal.Signals(signum).name)

    signal.signal(signal.SIGTERM, interrupt)
    signal.signal(signal.SIGINT, interrupt)


def _interrupt_until_stopping(signum: int, period_s: float = 1.0, tries: int = 30) -> None:
    for _ in range(tries):
        if _STOPPING.wait(period_s):
            return
        os.kill(os.getpid(), signum)  # a real signal: it also wakes a main thread blocked in a sleep or a wait


def run_tool(main: Callable[[], int], name: str) -> None:
    """Exit with ``main()``'s status; stopped by SIGTERM or SIGINT, exit with 130 after ``main``'s
    ``finally`` blocks have stopped what it started (``interrupt_on_signals``)."""
    interrupt_on_signals()
    try:
        status = main()
    except KeyboardInterrupt as stopped:
        _STOPPING.set()
        print(f"{name}: stopped by {stopped}; the processes it started were stopped", file=sys.stderr)
        status = INTERRUPTED
    sys.exit(status)


def stop_processes(
    procs: Sequence[subprocess.Popen[bytes]], grace_s: float = 30.0, first: signal.Signals = signal.SIGTERM
) -> None:
    """Send ``first`` to every process still running, wait up to ``grace_s`` seconds for each, and
    SIGKILL the process group of any that is still there (each was started in its own session, so
    its group holds its children: a worker's pool, the worker child of ``spine serve``)."""
    if _STOP_ASKED.is_set():
        _STOPPING.set()
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(first)
    for proc in procs:
        wait_or_kill(proc, grace_s)


def wait_or_kill(proc: subprocess.Popen[bytes], grace_s: float) -> None:
    """Wait up to ``grace_s`` seconds for ``proc``, already asked to stop, then SIGKILL its process group."""
    try:
        proc.wait(grace_s)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
