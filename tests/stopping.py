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

import signal
import subprocess

from tools.processes import stop_processes, wait_or_kill


class Stopper:
    """The processes started and not yet stopped, and those already sent their SIGTERM."""

    def __init__(self) -> None:
        self.running: dict[int, subprocess.Popen[bytes]] = {}
        self.signalled: set[int] = set()

    def started(self, proc: subprocess.Popen[bytes]) -> None:
        """Register ``proc`` (started in a session of its own) to be signalled at the session's end."""
        self.running[proc.pid] = proc

    def signal_all(self) -> None:
        """SIGTERM to every registered process still running, none twice."""
        for pid, proc in list(self.running.items()):
            if pid not in self.signalled and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                self.signalled.add(pid)

    def stop(self, proc: subprocess.Popen[bytes], grace_s: float) -> None:
        """Stop ``proc`` as ``tools.processes.stop_processes`` does (SIGTERM, then SIGKILL to its process
        group after ``grace_s`` seconds), without a second SIGTERM if ``signal_all`` sent one; unregister
        it."""
        try:
            if proc.pid not in self.signalled:
                stop_processes([proc], grace_s=grace_s)
            else:
                wait_or_kill(proc, grace_s)
        finally:
            self.running.pop(proc.pid, None)
            self.signalled.discard(proc.pid)


SESSION = Stopper()
"""The fixtures' processes of this test process's session (a test of the mechanism makes its own
``Stopper``: signalling this one would stop the session's live services under later tests)."""
_OWNER: list[object] = []
"""The session whose end signals them: the first one started in this process."""


def claim(session: object) -> None:
    """Make ``session`` the owner unless one started before it (a session run inside another)."""
    if not _OWNER:
        _OWNER.append(session)


def owns(session: object) -> bool:
    return bool(_OWNER) and _OWNER[0] is session


started = SESSION.started
signal_all = SESSION.signal_all
stop = SESSION.stop
