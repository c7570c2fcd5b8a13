"""Beat's scheduler (``services.worker.beat.PromptScheduler``) sleeps until the reconciler is due:
Celery's own woke 10 ms early and then ticked without sleeping until it was due, about 60 ticks a pass.

Celery's real beat loop (``celery.beat.Service``) runs for ``RUN_S`` on an app of the service
(``make_celery``, its embedded broker in the test's folder) with the reconciler every ``INTERVAL_S``;
the passes are counted, nothing is sent."""

from __future__ import annotations

import itertools
import statistics
import threading
import time
from pathlib import Path
from typing import Any

from celery import beat

from services.core.config import Settings
from services.core.jobqueue import RECONCILE, make_celery
from services.worker.beat import PromptScheduler

INTERVAL_S = 0.2
RUN_S = 2.0
TICKS_PER_PASS = 4
"""At most this many ticks a pass: one that sends, one that sleeps until the next is due, and those
that the heap's whole-second clock (``Scheduler._when``) adds; Celery's scheduler took about 60."""


def _ticks_and_passes(tmp_path: Path, scheduler_cls: type[beat.Scheduler]) -> tuple[int, list[float]]:
    """The ticks of the run, and the time (s, monotonic) of each pass."""
    app = make_celery(Settings(data_dir=tmp_path))
    app.conf.beat_schedule = {"reconcile": {"task": RECONCILE, "schedule": INTERVAL_S}}
    service = beat.Service(app, scheduler_cls=scheduler_cls, schedule_filename=str(tmp_path / "beat-schedule"))
    scheduler = service.scheduler
    ticks, passes = [0], []
    tick = scheduler.tick

    def counted_tick(*args: Any, **kwargs: Any) -> Any:
        ticks[0] += 1
        return tick(*args, **kwargs)

    def counted_apply(*_: Any, **__: Any) -> None:
        passes.append(time.monotonic())

    scheduler.tick = counted_tick  # type: ignore[method-assign]
    scheduler.apply_entry = counted_apply  # type: ignore[method-assign]
    threading.Timer(RUN_S, service.stop).start()
    service.start()
    return ticks[0], passes


def test_beat_sleeps_until_the_reconciler_is_due(tmp_path: Path) -> None:
    ticks, passes = _ticks_and_passes(tmp_path, PromptScheduler)
    gaps = [b - a for a, b in itertools.pairwise(passes)]
    assert len(gaps) >= 4 and statistics.median(gaps) <= 1.25 * INTERVAL_S, gaps  # on time
    assert ticks <= TICKS_PER_PASS * len(passes) + 2, (ticks, len(passes))


def test_celerys_own_scheduler_spins_before_each_pass(tmp_path: Path) -> None:
    """What the test above holds the worker's scheduler against (so that it can fail)."""
    ticks, passes = _ticks_and_passes(tmp_path, beat.Scheduler)
    assert ticks > TICKS_PER_PASS * len(passes) + 2, (ticks, len(passes))
