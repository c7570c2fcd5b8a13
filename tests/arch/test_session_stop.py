"""The service processes the fixtures start are told to stop together at the session's end
(tests/stopping.py): each gets one SIGTERM, and their graceful stops overlap instead of following
one another."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from tests import stopping

STOP_S = 1.0
"""How long the probe takes to stop after SIGTERM, as a worker finishing its loop does."""
PROBE = f"""
import signal, sys, time
log = open(sys.argv[1], "a", buffering=1)
asked = []
signal.signal(signal.SIGTERM, lambda *_: (asked.append(1), log.write("TERM\\n")))
log.write("ready\\n")
while not asked:
    time.sleep(0.02)
time.sleep({STOP_S})
"""


def test_the_session_end_stops_every_process_once_and_together(tmp_path: Path) -> None:
    logs = [tmp_path / f"probe-{i}.log" for i in range(2)]
    stopper = stopping.Stopper()  # its own: the session's would stop the live services of later tests
    procs = [subprocess.Popen([sys.executable, "-c", PROBE, str(log)], start_new_session=True) for log in logs]
    try:
        deadline = time.monotonic() + 30
        while not all(log.exists() and "ready" in log.read_text() for log in logs):
            assert time.monotonic() < deadline, "the probes did not start"
            time.sleep(0.02)
        for proc in procs:
            stopper.started(proc)
        started = time.monotonic()
        stopper.signal_all()
        stopper.signal_all()  # the session's end comes once, but a second call sends nothing
        time.sleep(0.2)  # the fixtures' teardowns come after (a signal sent at once would merge with the first)
        for proc in procs:
            stopper.stop(proc, grace_s=20)  # what each fixture's teardown does: no second SIGTERM
        elapsed = time.monotonic() - started
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert [log.read_text().count("TERM") for log in logs] == [1, 1]
    assert [proc.returncode for proc in procs] == [0, 0]
    assert elapsed < 2 * STOP_S, elapsed  # one after the other, two stops take 2 × STOP_S at least
