"""Celery's lines about each reconciler run (beat sending it, the worker receiving it, its success)
are DEBUG: at INFO, every SPINE_RECONCILE_INTERVAL_S, they buried the console (`make run`). Other
tasks' lines and the reconciler's warnings and errors stay as they were."""

from __future__ import annotations

import logging

import pytest

from services.core.jobqueue import RECONCILE
from services.worker.celery_app import CELERY_TASK_LOGGERS


class Capture(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@pytest.mark.parametrize("name", CELERY_TASK_LOGGERS)
def test_reconciler_runs_are_debug_and_other_lines_unchanged(name: str) -> None:
    logger = logging.getLogger(name)
    capture = Capture()
    logger.addHandler(capture)
    level = logger.level
    try:
        logger.setLevel(logging.INFO)
        logger.info("Task %s[1234] succeeded in 0.01s: None", RECONCILE)
        logger.info("Task spine.run_job[5678] succeeded in 0.9s: None")
        logger.error("Task %s[1234] raised unexpected: OperationalError()", RECONCILE)
        assert [(r.levelname, r.getMessage()[:20]) for r in capture.records] == [
            ("INFO", "Task spine.run_job[5"),
            ("ERROR", f"Task {RECONCILE}[1234]"[:20]),
        ]
        capture.records.clear()
        logger.setLevel(logging.DEBUG)
        logger.info("Scheduler: Sending due task reconcile (%s)", RECONCILE)
        assert [r.levelname for r in capture.records] == ["DEBUG"]
    finally:
        logger.setLevel(level)
        logger.removeHandler(capture)
