"""Stopping the service processes the fixtures start (workers of ``tests.conftest.Service``, the page
tests' `spine serve`), together at the end of a test session.

A graceful stop takes seconds (a Celery worker finishes its loop, its pool and its beat), and the
session's fixtures are torn down one after another: each waited for the previous one's stop. So
each such process is registered while it runs, every one still registered gets its SIGTERM when
the session's last test is torn down (``tests/conftest.py``, ``pytest_runtest_teardown`` with no
next item; with pytest-xdist, each worker's last test), and each fixture's teardown then waits for
its own process, already stopping. A process is signalled once: a second SIGTERM would interrupt
`spine serve` while it stops its worker child. Only the first session of the process does this: a
session run inside it (pytester, tests/arch/test_ci_rules.py) ends long before its fixtures do.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess

from tools.processes import stop_processes

_RUNNING: dict[int, subprocess.Popen[bytes]] = {}
"""Started and not yet stopped, by PID."""
_SIGNALLED: set[int] = set()
"""PIDs already sent their SIGTERM by ``signal_all``."""
_OWNER: list[object] = []
"""The session whose end signals them: the first one started in this process."""


def claim(session: object) -> None:
    """Make ``session`` the owner unless one started before it (a session run inside another)."""
    if not _OWNER:
        _OWNER.append(session)


def owns(session: object) -> bool:
    return bool(_OWNER) and _OWNER[0] is session


def started(proc: subprocess.Popen[bytes]) -> None:
    """Register ``proc`` (started in a session of its own) to be signalled at the session's end."""
    _RUNNING[proc.pid] = proc


def signal_all() -> None:
    """SIGTERM to every registered process still running, none twice."""
    for pid, proc in list(_RUNNING.items()):
        if pid not in _SIGNALLED and proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            _SIGNALLED.add(pid)


def stop(proc: subprocess.Popen[bytes], grace_s: float) -> None:
    """Stop ``proc`` as ``tools.processes.stop_processes`` does (SIGTERM, then SIGKILL to its process
    group after ``grace_s`` seconds), without a second SIGTERM if ``signal_all`` sent one; unregister it."""
    try:
        if proc.pid not in _SIGNALLED:
            stop_processes([proc], grace_s=grace_s)
            return
        try:
            proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    finally:
        _RUNNING.pop(proc.pid, None)
        _SIGNALLED.discard(proc.pid)
