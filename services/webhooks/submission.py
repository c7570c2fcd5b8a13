"""The API side of webhooks: refuse a callback_url this service may not call."""

from __future__ import annotations

from sqlalchemy.orm import Session

from services.core.config import Settings
from services.core.webhook_policy import check_callback_url
from services.webhooks.signing import secret_for


def check_callback(url: str | None, settings: Settings, session: Session, owner: str | None) -> None:
    """Raise ``InvalidInput`` naming ``callback_url`` when it is given and not allowed.

    Allowed means: http(s), no credentials, matching ``SPINE_WEBHOOK_ALLOWED_URLS``, and a signing
    secret exists for ``owner`` (per API key, or the service-wide ``SPINE_WEBHOOK_SECRET``).
    """
    if url is None:
        return
    check_callback_url(url, settings.webhook_allowed_urls, secret_for(session, owner, settings) is not None)
