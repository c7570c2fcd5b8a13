"""The worker's main process freezes its start-up heap before the pool forks (``services.worker.heap``):
its exit then does not walk the 300 000 objects of the engine's kernels, the modules and the Celery
app. Before, an idle `spine worker` spent 3 to 4 s in the interpreter's last collections after its
warm shutdown had ended (measured on this 2-core machine under the suite's load), which every
stop of a worker paid: a deploy, a restart, and each test that stops one."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from tests.stop_cost import own_cpu_s

MAIN_PROCESS = """
import gc, json, time
from celery.signals import worker_init
from spine_engine.warmup import warm_up
import services.worker.celery_app  # the worker's app, as `spine worker --child` builds it
warm_up()
gc.collect()
start = time.process_time()
gc.collect()  # one walk of the heap the worker's exit would walk
walk = time.process_time() - start
worker_init.send(sender=None)  # what Celery's WorkController sends in its main process, before the pool
print(json.dumps({"walk_s": walk, "frozen": gc.get_freeze_count(), "cpu_s": time.process_time()}), flush=True)
"""


def test_the_worker_main_process_exits_without_walking_its_start_up_heap(tmp_path: Path) -> None:
    """A fresh interpreter builds the worker's main process (its Celery app, the engine's kernels,
    Celery's ``worker_init``) and exits: the exit costs less CPU than one full collection of that heap,
    which the interpreter's final collections would spend at least (tests/stop_cost.py)."""
    env = {**os.environ, "SPINE_DATA_DIR": str(tmp_path)}
    proc = subprocess.Popen([sys.executable, "-c", MAIN_PROCESS], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        deadline = time.monotonic() + 60
        while own_cpu_s(proc.pid)[0] != "Z":  # exited, not yet reaped: its own CPU is final
            assert time.monotonic() < deadline, "the probe did not exit"
            time.sleep(0.02)
        _, total = own_cpu_s(proc.pid)
    finally:
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0 and line, err[-3000:]
    report = json.loads(line)
    assert report["frozen"] > 100_000, report  # the modules and kernels, not a handful of objects
    exit_s = total - report["cpu_s"]
    assert exit_s < report["walk_s"], (exit_s, report)
