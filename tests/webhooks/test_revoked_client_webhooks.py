"""The webhooks of a client whose API keys are all revoked, on the real PostgreSQL (and SQLite) database and a
real receiver on 127.0.0.1, with a service-wide SPINE_WEBHOOK_SECRET set (the one admin jobs are signed with).

While the client has an active key its jobs' webhooks are signed with that key's secret, the one its
receiver verifies with. Once its last key is revoked they are not sent at all: signed with the
service-wide secret, the receiver would see a signature of a key it does not hold (a forgery, to it),
and a receiver of admin jobs' webhooks would take it as the service's; signed with the revoked key's
secret, the client would keep receiving its jobs (results included) that it may no longer read. The
attempt is recorded on the job, "not sent", and no request is made."""

from __future__ import annotations

import uuid
from typing import Any

import pytest
from sqlalchemy import select
from standardwebhooks import Webhook

from services.core.config import Settings
from services.db import jobs as repo
from services.db.engine import session_scope
from services.db.keys import create_key, revoke
from services.db.models import WebhookDelivery
from services.worker.webhook_tasks import deliver_once
from tests.conftest import spine_payload
from tests.interop_helpers import TEST_WEBHOOK_SECRET, Receiver

BACKENDS = pytest.mark.parametrize("db_settings", ["postgresql", "sqlite"], indirect=True)


def _cancelled_job(settings: Settings, owner: str | None, url: str) -> uuid.UUID:
    """A job of ``owner`` that calls back ``url``, cancelled: its ``job.cancelled`` webhook is due."""
    payload: dict[str, Any] = {**spine_payload(), "callback_url": url}
    with session_scope(settings) as session:
        job, _ = repo.create_job(session, payload, owner=owner)
        repo.cancel_job(session, job.id)
    return job.id


def _attempts(settings: Settings, job_id: uuid.UUID) -> list[tuple[int, int | None, str | None]]:
    with session_scope(settings) as session:
        rows = session.scalars(select(WebhookDelivery).where(WebhookDelivery.job_id == job_id,
                                                             WebhookDelivery.attempt > 0))  # fmt: skip
        return [(r.attempt, r.status_code, r.error) for r in rows]


@BACKENDS
def test_a_revoked_clients_webhooks_are_not_sent_nor_signed_with_the_service_secret(
    db_settings: Settings, receiver: Receiver
) -> None:
    settings = db_settings.model_copy(update={"webhook_allowed_urls": receiver.url("/hooks"),
                                              "webhook_secret": TEST_WEBHOOK_SECRET})  # fmt: skip
    client = f"clinic-{uuid.uuid4().hex[:8]}"
    with session_scope(settings) as session:
        row, _ = create_key(session, client)
        client_secret = row.webhook_secret
    assert client_secret is not None

    # -- an active key: the client's receiver verifies the webhook with the client's secret
    before = _cancelled_job(settings, client, receiver.url(f"/hooks/{uuid.uuid4().hex}"))
    assert deliver_once(settings, before, "cancelled", 1) is None
    [got] = receiver.received
    assert Webhook(client_secret).verify(got.body, got.headers)["type"] == "job.cancelled"

    # -- the client's last key revoked: its job's webhook reaches no receiver, and says why on the job
    after = _cancelled_job(settings, client, receiver.url(f"/hooks/{uuid.uuid4().hex}"))
    with session_scope(settings) as session:
        assert [k.id for k in revoke(session, client)] == [row.id]
    assert deliver_once(settings, after, "cancelled", 1) is None
    assert len(receiver.received) == 1, [(r.path, r.headers.get("webhook-signature")) for r in receiver.received]
    [(attempt, status_code, error)] = _attempts(settings, after)
    assert (attempt, status_code) == (1, None)
    assert error is not None and error.startswith("not sent: ")

    # -- admin jobs (no owner) are still signed with the service-wide secret
    admin_job = _cancelled_job(settings, None, receiver.url(f"/hooks/{uuid.uuid4().hex}"))
    assert deliver_once(settings, admin_job, "cancelled", 1) is None
    assert len(receiver.received) == 2
    service = TEST_WEBHOOK_SECRET.get_secret_value()
    assert Webhook(service).verify(receiver.received[1].body, receiver.received[1].headers)["type"] == "job.cancelled"
