"""The worker's CPU cost per job, in process (docs/performance.md): claim, fit and finish of N jobs
on a fresh embedded SQLite database, CPU time from ``getrusage``. ``python -m tools.workercost [N]``.
"""

from __future__ import annotations

import resource
import sys
import tempfile
import time
from pathlib import Path

from services.core.config import Settings
from services.db import jobs as jobs_repo
from services.db.engine import session_scope
from services.db.migrate import upgrade
from services.worker.tasks import execute_job
from tools.hops import payload

WARMUP = 20


def main(argv: list[str]) -> int:
    n = int(argv[0]) if argv else 300
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp))
        upgrade(settings, quiet=True)
        with session_scope(settings) as session:
            ids = [jobs_repo.create_job(session, payload())[0].id for _ in range(n + WARMUP)]
        for job_id in ids[:WARMUP]:
            execute_job(settings, job_id)
        before, started = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        outcomes = {execute_job(settings, job_id) for job_id in ids[WARMUP:]}
        after, ended = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    cpu_ms = (after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime) * 1000 / n
    print(f"{n} jobs {sorted(outcomes)}: CPU {cpu_ms:.2f} ms/job, wall {(ended - started) * 1000 / n:.2f} ms/job")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
