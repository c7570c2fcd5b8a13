"""Standard Webhooks signatures (https://www.standardwebhooks.com/), and whose secret signs.

Every delivery carries ``webhook-id`` (the message id, the same on every retry of a message, so a
receiver can drop duplicates), ``webhook-timestamp`` (Unix seconds of this attempt) and
``webhook-signature: v1,<base64 HMAC-SHA256 of "{id}.{timestamp}.{body}">``. Secrets are written as
Standard Webhooks writes them: ``whsec_`` followed by the base64 of the key bytes.

Whose secret: ``secret_for(session, owner, settings)`` reads the secret of the job owner's most
recent active API key that has one (``services.db.keys.key_webhook_secret``), then falls back to
the service-wide ``SPINE_WEBHOOK_SECRET`` (jobs without an owner, and owners whose active keys predate
per-key secrets), except for an owner whose client keys are all revoked: none then, and its webhooks
are not sent. Its receiver verifies with the client's own secret, so a message signed with the
service-wide one would read as forged there (and verify at a receiver of admin jobs' webhooks, which
holds that one); nor is it signed with a revoked key's secret: a webhook carries the job, result
included, which a client without an active key may no longer read (``GET /v1/jobs/{id}`` answers it
401).
"""

from __future__ import annotations

import base64
import hashlib
import hmac

from sqlalchemy.orm import Session

from services.core.config import Settings
from services.core.webhook_policy import decode_secret
from services.db.keys import client_revoked, key_webhook_secret


def secret_for(session: Session, owner: str | None, settings: Settings) -> bytes | None:
    """The key that signs webhooks of ``owner``'s jobs: the secret of the owner's most recent
    active API key that has one, else the service-wide ``SPINE_WEBHOOK_SECRET``; None when neither,
    and None for an owner whose client keys are all revoked (its webhooks are not sent)."""
    key = key_webhook_secret(session, owner)
    if key is not None:
        return key
    if owner is not None and client_revoked(session, owner):
        return None
    return service_secret(settings)


def service_secret(settings: Settings) -> bytes | None:
    if settings.webhook_secret is None:
        return None
    return decode_secret(settings.webhook_secret.get_secret_value())


def signature(key: bytes, message_id: str, timestamp: int, body: bytes) -> str:
    """The ``webhook-signature`` header value for one attempt."""
    signed = f"{message_id}.{timestamp}.".encode() + body
    return "v1," + base64.b64encode(hmac.new(key, signed, hashlib.sha256).digest()).decode()


def signed_headers(key: bytes, message_id: str, timestamp: int, body: bytes) -> dict[str, str]:
    return {
        "content-type": "application/json",
        "webhook-id": message_id,
        "webhook-timestamp": str(timestamp),
        "webhook-signature": signature(key, message_id, timestamp, body),
    }
