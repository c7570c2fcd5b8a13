"""What a process of the service costs to stop, in CPU seconds, and what one walk of a heap costs
(tests/worker/test_heap.py, tests/cli/test_service_cli.py).

CPU time, not wall time: the machine the suite runs on is shared and loaded (2 cores, other tests
running), and a wall-clock bound would measure the load. A process's own CPU (utime + stime, proc(5)
``/proc/<pid>/stat`` fields 14 and 15, without its children's) stays readable while it is a zombie,
i.e. after it exited and before its parent reaps it: so it is read before the stop signal and again
once the process is a zombie.

The reference is one full garbage collection (``gc.collect()``) of a heap at least as large as the
process's own: the interpreter's final collections at exit walk every tracked object at least once
(CPython ``Py_FinalizeEx``: ``finalize_modules`` collects after clearing the modules), so a process
whose heap is not frozen (``services.worker.heap``) spends at least that much stopping, and one that
froze it spends less.
"""

from __future__ import annotations

import gc
import os
import signal
import subprocess
import time
from pathlib import Path


def own_cpu_s(pid: int) -> tuple[str, float]:
    """(state, CPU seconds of the process itself) from ``/proc/<pid>/stat`` (proc(5): the fields after
    the command name are state, ppid, …, utime and stime at 11 and 12, in clock ticks)."""
    stat = Path(f"/proc/{pid}/stat").read_text()
    fields = stat[stat.rfind(")") + 2 :].split()
    return fields[0], (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def stop_cpu_s(proc: subprocess.Popen[bytes], sig: signal.Signals, timeout: float = 40.0) -> float:
    """Send ``sig`` to ``proc`` (a child of this process, not yet reaped) and return the CPU seconds it
    spent from then until it exited (its children's excluded); reap it. Raises AssertionError if it
    is still running after ``timeout`` seconds."""
    _, before = own_cpu_s(proc.pid)
    proc.send_signal(sig)
    deadline = time.monotonic() + timeout
    while True:
        state, after = own_cpu_s(proc.pid)
        if state == "Z":
            break
        assert time.monotonic() < deadline, f"process {proc.pid} still running {timeout} s after {sig.name}"
        time.sleep(0.02)
    proc.wait()
    return after - before


def collection_cpu_s() -> float:
    """CPU seconds of one full collection of this process's heap (what it left as garbage collected
    first, so that the timed collection walks the live heap alone)."""
    gc.collect()
    start = time.process_time()
    gc.collect()
    return time.process_time() - start
