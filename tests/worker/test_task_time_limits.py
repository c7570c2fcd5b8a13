"""The reconciler's and the webhook delivery's Celery tasks carry soft and hard time limits from the
settings, as the worker registers them on its Celery app: a pass or a delivery stuck on a dependency
ends (tests/integration/test_webhook_recovery.py sees a real worker end a stuck delivery)."""

from __future__ import annotations

from pathlib import Path

from services.core.config import Settings
from services.core.jobqueue import DELIVER_WEBHOOK, HARD_LIMIT_GRACE_S, RECONCILE, make_celery
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
