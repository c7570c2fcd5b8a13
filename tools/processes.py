"""Stopping the service processes the tools and the tests start (``spine serve``, ``spine worker``)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Sequence
from types import FrameType

INTERRUPTED = 130
"""Exit status of a tool stopped by SIGINT or SIGTERM (128 + SIGINT, the shell's convention)."""


def interrupt_on_signals() -> None:
    """Make SIGTERM (a QA script's timeout, ``kill``) and SIGINT (Ctrl-C) raise ``KeyboardInterrupt``
    in the main thread, so that a tool's ``finally`` blocks run and stop the processes it started.

    Without it SIGTERM ends the tool at once and leaves its service running, and under
    ``asyncio.run`` SIGINT only cancels the main task, which a pending ``gather`` can absorb (seen:
    the load bench kept running after Ctrl-C). A handler other than Python's default also keeps
    ``asyncio.run`` from installing its own (Python 3.11 ``asyncio.Runner``)."""

    def interrupt(signum: int, _frame: FrameType | None) -> None:
        raise KeyboardInterrupt(signal.Signals(signum).name)

    signal.signal(signal.SIGTERM, interrupt)
    signal.signal(signal.SIGINT, interrupt)


def run_tool(main: Callable[[], int], name: str) -> None:
    """Exit with ``main()``'s status; stopped by SIGTERM or SIGINT, exit with 130 after ``main``'s
    ``finally`` blocks have stopped what it started (``interrupt_on_signals``)."""
    interrupt_on_signals()
    try:
        status = main()
    except KeyboardInterrupt as stopped:
        print(f"{name}: stopped by {stopped}; the processes it started were stopped", file=sys.stderr)
        status = INTERRUPTED
    sys.exit(status)


def stop_processes(
    procs: Sequence[subprocess.Popen[bytes]], grace_s: float = 30.0, first: signal.Signals = signal.SIGTERM
) -> None:
    """Send ``first`` to every process still running, wait up to ``grace_s`` seconds for each, and
    SIGKILL the process group of any that is still there (each was started in its own session, so
    its group holds its children: a worker's pool, the worker child of ``spine serve``)."""
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(first)
    for proc in procs:
        try:
            proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
