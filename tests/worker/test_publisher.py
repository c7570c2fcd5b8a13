"""One publisher per process (``services.core.jobqueue.publisher``): the STOW-RS pushes and webhook
deliveries of many jobs go through one Celery app built once, whose messages land on their queues of
a real broker (Redis), named as the worker's tasks are registered."""

from __future__ import annotations

import json
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import redis
from celery import Celery

from services.core import jobqueue
from services.core.config import Settings
from services.core.jobqueue import DELIVER_WEBHOOK, STORE_DICOM, publish_dicom_store, publish_webhook, publisher
from services.worker.dicom_tasks import register_dicom_tasks
from services.worker.webhook_tasks import register_webhook_tasks
from tests.conftest import _purge_queue


@pytest.fixture
def settings(tmp_path: Path, redis_url: str) -> Iterator[Settings]:
    queue = f"test-publisher-{uuid.uuid4().hex[:8]}"
    yield Settings(data_dir=tmp_path, CELERY_BROKER_URL=redis_url, queue_name=queue)
    for name in (f"{queue}.dicom", f"{queue}.webhooks"):
        _purge_queue(redis_url, name)


def test_one_publisher_per_process_carries_every_push(settings: Settings, redis_url: str,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    built: list[Celery] = []

    def counting(s: Settings) -> Celery:
        built.append(make(s))
        return built[-1]

    make = jobqueue.make_celery
    monkeypatch.setattr(jobqueue, "make_celery", counting)
    monkeypatch.setattr(jobqueue, "_PUBLISHERS", {})
    jobs = [uuid.uuid4() for _ in range(3)]
    for job_id in jobs:
        publish_dicom_store(settings, job_id, 1)
        publish_webhook(settings, job_id, "succeeded", 1)
    assert len(built) == 1 and publisher(settings) is built[0]

    broker = redis.Redis.from_url(redis_url)
    messages: dict[str, list[dict[str, Any]]] = {
        queue: [json.loads(m) for m in broker.lrange(queue, 0, -1)]
        for queue in (settings.dicom_queue, settings.webhook_queue)
    }
    assert {m["headers"]["task"] for m in messages[settings.dicom_queue]} == {STORE_DICOM}
    assert {m["headers"]["task"] for m in messages[settings.webhook_queue]} == {DELIVER_WEBHOOK}
    assert sorted(m["headers"]["argsrepr"] for m in messages[settings.dicom_queue]) == sorted(
        f"['{j}', 1]" for j in jobs
    )

    worker = make(settings)  # the names published are the names the worker registers
    register_dicom_tasks(worker, settings)
    register_webhook_tasks(worker, settings)
    assert {STORE_DICOM, DELIVER_WEBHOOK} <= set(worker.tasks)
