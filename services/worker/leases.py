"""The worker's leases on running jobs: renewed while the fit runs, so that a job whose worker
died (kill -9, a lost machine) is found by the reconciler within ``SPINE_LEASE_S`` plus one
reconcile interval, not after the fit time limit.

One thread per worker process renews, every third of the lease, the leases of the runs that have
been going for more than a third of it: a 5 ms fit ends long before and costs nothing beyond the
lease set by its claim (``services.db.runs.claim_job``). A run whose job was cancelled or taken
back meanwhile is not renewed (the update is fenced by attempt) and will store nothing.
"""

from __future__ import annotations

import logging
import os
import threading
import time
import uuid
from datetime import timedelta

from services.core.config import Settings
from services.db import runs
from services.db.engine import worker_session

log = logging.getLogger(__name__)


class LeaseKeeper:
    """Renews the leases of this process's running claims (a daemon thread, started on first use)."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self.lease = timedelta(seconds=settings.lease_s)
        self.period_s = settings.lease_s / 3
        self._lock = threading.Lock()
        self._claims: dict[uuid.UUID, tuple[runs.Claim, float]] = {}
        self._thread: threading.Thread | None = None
        self._pid = 0

    def hold(self, claim: runs.Claim) -> None:
        """Keep ``claim``'s lease alive until ``release``."""
        with self._lock:
            self._claims[claim.job_id] = (claim, time.monotonic())
            if self._thread is None or self._pid != os.getpid():  # first use, or a forked child
                self._pid = os.getpid()
                self._thread = threading.Thread(target=self._run, name="spine-lease-keeper", daemon=True)
                self._thread.start()

    def release(self, claim: runs.Claim) -> None:
        with self._lock:
            self._claims.pop(claim.job_id, None)

    def due(self, now: float) -> list[runs.Claim]:
        """Claims held for more than a third of the lease (their lease needs renewing)."""
        with self._lock:
            return [c for c, since in self._claims.values() if now - since >= self.period_s]

    def renew_once(self) -> int:
        due = self.due(time.monotonic())
        if not due:
            return 0
        with worker_session(self.settings) as session:
            kept = runs.renew_leases(session, due, self.lease)
        lost = {c.job_id for c in due} - {c.job_id for c in kept}
        for job_id in lost:
            log.warning("job %s: lease not renewed (cancelled or taken back); its outcome will not be stored", job_id)
        return len(kept)

    def _run(self) -> None:
        while True:
            time.sleep(self.period_s)
            try:
                self.renew_once()
            except Exception as exc:  # the database is away: the next period tries again
                log.warning("could not renew job leases: %s", exc)
