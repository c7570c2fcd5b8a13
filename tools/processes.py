"""Stopping the service processes the tools and the tests start (``spine serve``, ``spine worker``)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
from collections.abc import Sequence


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
