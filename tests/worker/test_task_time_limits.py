"""The reconciler's and the webhook delivery's Celery tasks carry soft and hard time limits from the
settings, as the worker registers them on its Celery app: a pass or a delivery stuck on a dependency
ends (tests/integration/test_webhook_recovery.py sees a real worker end a stuck delivery); and the
reconciler's periodic runs queued while they could not start end at once."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.core.config import Settings
from services.core.jobqueue import DELIVER_WEBHOOK, HARD_LIMIT_GRACE_S, RECONCILE, make_celery
from services.worker import tasks
from services.worker.celery_app import app, beat_schedule
from services.worker.celery_app import settings as worker_settings
from services.worker.tasks import register_tasks
from services.worker.webhook_tasks import register_webhook_tasks


def test_the_reconcile_and_webhook_tasks_have_time_limits_from_the_settings(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path, reconcile_time_limit_s=12, webhook_timeout_s=3, webhook_task_margin_s=4)
    app = make_celery(settings)
    register_tasks(app, settings)
    register_webhook_tasks(app, settings)
    reconcile, deliver = app.tasks[RECONCILE], app.tasks[DELIVER_WEBHOOK]
    assert (reconcile.soft_time_limit, reconcile.time_limit) == (12, 12 + HARD_LIMIT_GRACE_S)
    # the delivery's bound is its attempt's deadline (3 s) plus the margin for its bookkeeping (4 s)
    assert (deliver.soft_time_limit, deliver.time_limit) == (3 + 4, 3 + 4 + HARD_LIMIT_GRACE_S)


def test_reconcile_runs_queued_while_they_could_not_start_end_at_once_on_the_process_clock(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Beat sends the reconciler every interval with no ``expires`` (an instant on beat's clock, which a
    worker whose clock runs ahead would read as past for every run); a run that reaches a process less
    than half an interval after its last one ends at once, so the runs queued while the database was
    down do not all run when it is back."""
    settings = Settings(data_dir=tmp_path, reconcile_interval_s=7)
    entry = beat_schedule(settings)["reconcile"]
    assert entry == {"task": RECONCILE, "schedule": 7}
    assert app.conf.beat_schedule == beat_schedule(worker_settings)  # what the worker's beat runs

    runs: list[Settings] = []
    monkeypatch.setattr(tasks, "reconcile_once", lambda s, _app: runs.append(s))
    own = make_celery(settings)
    register_tasks(own, settings)
    for _ in range(5):  # a backlog delivered back to back
        own.tasks[RECONCILE]()
    assert runs == [settings]

    spacing = tasks.RunSpacing(3.5)
    assert [spacing.due(t) for t in (100.0, 101.0, 103.4, 103.5, 106.9, 107.0)] == [
        True, False, False, True, False, True
    ]
