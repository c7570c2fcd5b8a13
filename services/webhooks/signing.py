"""Standard Webhooks signatures (https://www.standardwebhooks.com/), and whose secret signs.

Every delivery carries ``webhook-id`` (the message id, the same on every retry of a message, so a
receiver can drop duplicates), ``webhook-timestamp`` (Unix seconds of this attempt) and
``webhook-signature: v1,<base64 HMAC-SHA256 of "{id}.{timestamp}.{body}">``. Secrets are written as
Standard Webhooks writes them: ``whsec_`` followed by the base64 of the key bytes.

Whose secret: ``secret_for(session, owner, settings)`` asks the resolvers registered with
``register_secret_resolver`` first (the API and the worker register
``services.db.access.key_webhook_secret``: the secret of the job owner's most recent active API key
that has one), then falls back to the service-wide ``SPINE_WEBHOOK_SECRET``.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import hmac
from collections.abc import Callable

from sqlalchemy.orm import Session

from services.settings import Settings

SECRET_PREFIX = "whsec_"
MIN_SECRET_BYTES = 16

SecretResolver = Callable[[Session, str | None], bytes | None]
"""(session, job owner) -> that owner's signing key bytes, or None to fall through."""

_RESOLVERS: list[SecretResolver] = []


def decode_secret(secret: str) -> bytes:
    """The key bytes of a ``whsec_<base64>`` (or bare base64) secret; raise ``ValueError``."""
    text = secret.strip().removeprefix(SECRET_PREFIX)
    try:
        key = base64.b64decode(text + "=" * (-len(text) % 4), validate=True)
    except (binascii.Error, ValueError):
        raise ValueError("a webhook secret is whsec_ followed by base64") from None
    if len(key) < MIN_SECRET_BYTES:
        raise ValueError(f"a webhook secret needs at least {MIN_SECRET_BYTES} bytes of key, this one {len(key)}")
    return key


def register_secret_resolver(resolver: SecretResolver) -> None:
    """Make ``resolver`` the first place a job owner's signing key is looked up."""
    _RESOLVERS.insert(0, resolver)


def secret_for(session: Session, owner: str | None, settings: Settings) -> bytes | None:
    """The key that signs webhooks of ``owner``'s jobs, or None when there is none."""
    for resolver in _RESOLVERS:
        key = resolver(session, owner)
        if key is not None:
            return key
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
