"""The reconciler's and the webhook delivery's Celery tasks carry soft and hard time limits from the
settings, as the worker registers them on its Celery app: a pass or a delivery stuck on a dependency
ends (tests/integration/test_webhook_recovery.py sees a real worker end a stuck delivery); and the
reconciler's periodic runs expire when the next is due."""

from __future__ import annotations

from pathlib import Path

from services.core.config import Settings
from services.core.jobqueue import DELIVER_WEBHOOK, HARD_LIMIT_GRACE_S, RECONCILE, make_celery
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


def test_a_reconcile_run_that_could_not_start_in_time_expires_instead_of_piling_up(tmp_path: Path) -> None:
    """Beat sends the reconciler every interval with ``expires`` equal to it, so the runs queued while the
    database was down (none could start) are dropped, not run all at once when it is back."""
    settings = Settings(data_dir=tmp_path, reconcile_interval_s=7)
    entry = beat_schedule(settings)["reconcile"]
    assert entry["task"] == RECONCILE and entry["schedule"] == 7
    assert entry["options"] == {"expires": 7}
    assert app.conf.beat_schedule == beat_schedule(worker_settings)  # what the worker's beat runs
