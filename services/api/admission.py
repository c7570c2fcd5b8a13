"""Admission of a job payload: validated once into ``JobPayload``, then the service's limits are
applied to that model (not to the raw JSON again).

``admit`` is the one place a posted payload is checked, for ``POST /v1/jobs`` and for each entry
of ``POST /v1/jobs/batch``: the engine's contract (``spine_engine.validation.validate_payload``:
types, finite numbers, levels, orthonormal directors...), then the magnitudes
(``services.api.limits``), then the ``callback_url`` (``services.webhooks.submission``). Every
failure is an ``InvalidInput`` naming each offending field by its JSON path.
"""

from __future__ import annotations

from typing import Any

from sqlalchemy.orm import Session

from services.api.limits import check_magnitudes
from services.core.config import Settings
from services.webhooks.submission import check_callback
from spine_engine.models import JobPayload
from spine_engine.validation import validate_payload


def admit(body: Any, settings: Settings, session: Session, owner: str | None) -> JobPayload:
    """The payload ``body`` as a validated ``JobPayload`` within the service's limits; raise
    ``InvalidInput`` otherwise."""
    model = validate_payload(body)
    check_magnitudes(model)
    check_callback(model.callback_url, settings, session, owner)
    return model
