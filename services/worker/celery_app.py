"""The worker's Celery app (``celery -A services.worker.celery_app``), built from the settings.

It registers the job task, the webhook delivery and the STOW-RS push of results, and the
reconciler, which Celery beat (embedded in the worker with ``-B``) runs every
``SPINE_RECONCILE_INTERVAL_S``. Celery's own lines about the reconciler's runs (beat sending it, the
worker receiving it, its success) are DEBUG: at INFO they would be three lines every 2 s that bury the
rest; the reconciler logs at INFO itself when it acted (``tasks.reconcile_once``).
"""

from __future__ import annotations

import logging
from typing import Any

from celery.signals import worker_init, worker_process_init

from services.core.config import Settings, get_settings
from services.core.jobqueue import RECONCILE, make_celery
from services.db.engine import dispose_engines
from services.worker import tasks
from services.worker.beat import PromptScheduler
from services.worker.dicom_tasks import register_dicom_tasks
from services.worker.heap import freeze_startup_heap
from services.worker.webhook_tasks import register_webhook_tasks
from spine_engine.warmup import warm_up

log = logging.getLogger(__name__)

CELERY_TASK_LOGGERS = ("celery.beat", "celery.worker.strategy", "celery.app.trace")
"""Celery's loggers of a task being sent by beat, received and finished."""


class ReconcilerAtDebug(logging.Filter):
    """Celery's INFO records about the reconciler task, lowered to DEBUG (dropped unless the logger
    shows DEBUG); warnings and errors about it stay as they are."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno != logging.INFO or RECONCILE not in record.getMessage():
            return True
        if not logging.getLogger(record.name).isEnabledFor(logging.DEBUG):
            return False
        record.levelno, record.levelname = logging.DEBUG, "DEBUG"
        return True


for _name in CELERY_TASK_LOGGERS:
    logging.getLogger(_name).addFilter(ReconcilerAtDebug())


def beat_schedule(settings: Settings) -> dict[str, dict[str, Any]]:
    """The reconciler every ``SPINE_RECONCILE_INTERVAL_S``. Runs that queued while they could not start
    (the database down, the pool busy) are ended by the task itself (``tasks.RunSpacing``), not by
    Celery's ``expires``, an instant on beat's clock that a worker whose clock runs ahead would read as
    past for every run."""
    return {"reconcile": {"task": RECONCILE, "schedule": settings.reconcile_interval_s}}


settings = get_settings()
app = make_celery(settings)
tasks.register_tasks(app, settings)
register_webhook_tasks(app, settings)
register_dicom_tasks(app, settings)
app.conf.beat_schedule = beat_schedule(settings)
app.conf.beat_scheduler = PromptScheduler


@worker_process_init.connect
def _fresh_connections(**_: Any) -> None:
    # A forked pool process must not share its parent's database connections.
    dispose_engines()


@worker_init.connect
def _load_engine_kernels(**_: Any) -> None:
    # In the main process, before the pool forks: each pool process inherits the engine's compiled
    # kernels (about 0.4 s here) instead of loading them from the disk cache on its first job.
    log.info("engine kernels loaded in %.2f s", warm_up())
    # Last before the fork (services.worker.heap): the pool processes share these pages untouched.
    freeze_startup_heap()
