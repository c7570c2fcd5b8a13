"""The worker's Celery app (``celery -A services.worker.celery_app``), built from the settings.

It registers the job task, the webhook delivery and the STOW-RS push of results, and the
reconciler, which Celery beat (embedded in the worker with ``-B``) runs every
``SPINE_RECONCILE_INTERVAL_S``.
"""

from __future__ import annotations

import logging
from typing import Any

from celery.signals import worker_init, worker_process_init

from services.core.config import get_settings
from services.core.jobqueue import RECONCILE, make_celery
from services.db.engine import dispose_engines
from services.worker import tasks
from services.worker.dicom_tasks import register_dicom_tasks
from services.worker.webhook_tasks import register_webhook_tasks
from spine_engine.warmup import warm_up

log = logging.getLogger(__name__)
settings = get_settings()
app = make_celery(settings)
tasks.register_tasks(app, settings)
register_webhook_tasks(app, settings)
register_dicom_tasks(app, settings)
app.conf.beat_schedule = {
    "reconcile": {"task": RECONCILE, "schedule": settings.reconcile_interval_s},
}


@worker_process_init.connect
def _fresh_connections(**_: Any) -> None:
    # A forked pool process must not share its parent's database connections.
    dispose_engines()


@worker_init.connect
def _load_engine_kernels(**_: Any) -> None:
    # In the main process, before the pool forks: each pool process inherits the engine's compiled
    # kernels (about 0.4 s here) instead of loading them from the disk cache on its first job.
    log.info("engine kernels loaded in %.2f s", warm_up())
