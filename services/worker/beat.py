"""The scheduler of the beat embedded in each worker (``spine worker``: ``-B``), which sends the reconciler."""

from __future__ import annotations

from celery import beat


class PromptScheduler(beat.Scheduler):
    """Celery beat's in-memory scheduler, waking when an entry is due rather than 10 ms before.

    ``beat.Scheduler.adjust`` takes 10 ms off every wait (``drift=-0.010``). Within the last 10 ms before
    the entry is due a wait so shortened is 0 or less, which beat's loop (``beat.Service.start``) does not
    sleep: it ticks again at once, about 60 ticks (10 ms of CPU here) each time the reconciler is due, half
    of an idle worker's CPU (docs/performance.md). Without the drift, beat sleeps until the entry is due."""

    def adjust(self, n: float | None, drift: float = 0.0) -> float | None:
        """The wait ``n`` (s) plus ``drift``, by default none."""
        result: float | None = super().adjust(n, drift=drift)
        return result
