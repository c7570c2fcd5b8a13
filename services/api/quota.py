"""The per-client cap on queued jobs (``SPINE_MAX_QUEUED_PER_CLIENT``): 429 with Retry-After past it.

The count of a client's queued jobs is read from the database (a partial index holds only queued
jobs) at most once a second per client and API process; in between, the jobs this process
accepted are added to it. The cap is thus approximate by what other replicas accepted in the
last second, which is what a protective limit needs, and costs nothing on most requests.
"""

from __future__ import annotations

import threading
import time

from sqlalchemy.orm import Session

from services.api.errors import ProblemError
from services.core.problems import problem
from services.db import stats
from services.db.keys import Caller

REFRESH_S = 1.0
RETRY_AFTER_S = 30


class QueuedCap:
    def __init__(self, cap: int):
        self.cap = cap
        self._lock = threading.Lock()
        self._known: dict[str, tuple[int, float]] = {}  # owner -> (queued count, when read)

    def admit(self, session: Session, caller: Caller, n: int) -> None:
        """Raise a 429 problem when ``n`` more queued jobs would put ``caller`` over the cap."""
        if self.cap <= 0 or caller.is_admin or n <= 0:
            return
        now = time.monotonic()
        with self._lock:
            known = self._known.get(caller.owner)
        if known is None or now - known[1] > REFRESH_S:
            known = (stats.count_queued(session, caller.owner, self.cap + 1), now)
            with self._lock:
                self._known[caller.owner] = known
        queued = known[0]
        if queued + n > self.cap:
            raise ProblemError(
                problem(
                    "too-many-queued-jobs",
                    f"{queued} of this client's jobs are queued and {n} more would pass the cap of {self.cap}; "
                    f"retry once some have run",
                    queued=queued,
                    limit=self.cap,
                ),
                headers={"Retry-After": str(RETRY_AFTER_S)},
            )

    def accepted(self, caller: Caller, n: int) -> None:
        """Count ``n`` jobs just stored for ``caller`` until the next read of the database."""
        if self.cap <= 0 or caller.is_admin or n <= 0:
            return
        with self._lock:
            known = self._known.get(caller.owner)
            if known is not None:
                self._known[caller.owner] = (known[0] + n, known[1])
