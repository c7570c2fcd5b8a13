"""Admission of a job payload: validated once into ``JobPayload``, then the service's limits are
applied to that model (not to the raw JSON again).

``admit`` is the one place a posted payload is checked, for ``POST /v1/jobs`` and for each entry
of ``POST /v1/jobs/batch``: the engine's contract (``spine_engine.validation.validate_payload``:
types, finite numbers, levels, orthonormal directors...), then the magnitudes, then the
``callback_url`` (``services.webhooks.submission``); before all, no text may hold a NUL character
or an unpaired surrogate (``check_text``). Every failure is an ``InvalidInput`` naming
each offending field by its JSON path.

Magnitudes: coordinates, poses, spacings and scales are millimetres or pixels: a number larger
than ``MAX_MAGNITUDE`` in absolute value is a mistake (or an attack on the fit's arithmetic: 1e300
overflows it). The engine's contract already refuses NaN and infinities; this refuses the
absurdly large finite ones with the same 422 validation problem, naming each field.

By reference (``SPINE_DICOMWEB_URL`` set): a view whose image the ``study`` names by SOP Instance UID
may leave out ``pixel_spacing`` even in px, since the worker reads it from the image's header
(``services.dicom.reference``); the rest of the payload is checked now, with a stand-in spacing, and
the header's own refusals (no spacing there either, not a radiograph...) fail the job with a problem
naming the attribute.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from pydantic import BaseModel, ValidationError
from sqlalchemy.orm import Session

from services.api.errors import MAX_ERRORS
from services.core.config import Settings
from services.db.job_forms import apply_reads, engine_payload
from services.dicom.reference import views_to_fetch
from services.webhooks.submission import check_callback
from spine_client.dicom.merge import DicomProvenance, client_identity_errors, client_provenance_errors
from spine_engine.errors import FieldError, InvalidInput
from spine_engine.models import JobPayload
from spine_engine.validation import validate_payload

STAND_IN_SPACING = [1.0, 1.0]
"""Only for checking a by-reference payload before its header is read; never stored nor run."""


def _with_stand_in_spacing(body: Any) -> tuple[Any, tuple[str, ...]]:
    """``body`` with the stand-in spacing in each by-reference view that has none, and those views
    (whose millimetres are unknown until the header is read: no absolute distance check on them)."""
    wanted = views_to_fetch(body) if isinstance(body, dict) else {}
    if not wanted:
        return body, ()
    checked, stood_in = dict(body), []
    for role in wanted:
        view = checked.get(role)
        if isinstance(view, dict) and view.get("pixel_spacing") is None:
            checked[role] = {**view, "pixel_spacing": STAND_IN_SPACING}
            stood_in.append(role)
    return checked, tuple(stood_in)


MAX_MAGNITUDE = 1e6
NUL = "\x00"


def _leaves(value: Any, path: tuple[str | int, ...]) -> Iterator[tuple[tuple[str | int, ...], Any]]:
    """Every leaf of ``value`` (a validated model, or plain JSON) with its JSON path; the member names
    of a plain JSON object are leaves too, each at its own path."""
    if isinstance(value, BaseModel):
        for name, info in type(value).model_fields.items():
            yield from _leaves(getattr(value, name), (*path, info.alias or name))
    elif isinstance(value, dict):
        for key, item in value.items():
            yield (*path, str(key)), key
            yield from _leaves(item, (*path, str(key)))
    elif isinstance(value, list | tuple):
        for index, item in enumerate(value):
            yield from _leaves(item, (*path, index))
    else:
        yield path, value


def check_magnitudes(payload: BaseModel) -> None:
    """Raise ``InvalidInput`` naming (by JSON path) every number of the validated ``payload`` above
    ``MAX_MAGNITUDE`` in absolute value."""
    errors = []
    for path, number in _leaves(payload, ()):
        if isinstance(number, bool) or not isinstance(number, int | float):
            continue
        try:
            too_large = abs(number) > MAX_MAGNITUDE
        except OverflowError:  # an int beyond float range
            too_large = True
        if too_large:
            errors.append(FieldError(path, f"must be at most {MAX_MAGNITUDE:g} in absolute value", "number_too_large"))
            if len(errors) >= MAX_ERRORS:
                break
    if errors:
        raise InvalidInput(errors)


def _text_problem(text: str) -> tuple[str, str] | None:
    """(reason, type) when ``text`` holds what no stored text may, else None."""
    if NUL in text:
        return "holds the NUL character (U+0000), which no text of a job may hold", "nul_character"
    surrogate = next((ch for ch in text if "\ud800" <= ch <= "\udfff"), None)
    if surrogate is not None:
        return (f"holds an unpaired surrogate (U+{ord(surrogate):04X}), which is no character: JSON text holds "
                "characters only (RFC 8259 §8.2, RFC 7493 §2.1)", "unpaired_surrogate")  # fmt: skip
    return None


def check_text(body: Any, path: tuple[str | int, ...] = ()) -> None:
    """Raise ``InvalidInput`` naming (by JSON path) every string of the posted JSON ``body``, member
    names included, that holds the NUL character U+0000 or an unpaired surrogate (a ``\\ud800`` escape
    alone). The job is stored whole in PostgreSQL, whose text and jsonb cannot hold a NUL (PostgreSQL 15
    documentation, §8.3 "Character Types" and §8.14 "JSON Types") and whose json parser refuses an
    unpaired surrogate; refused here, each is a 422 naming the field on every database, not a failed
    insert."""
    errors = []
    for at, leaf in _leaves(body, path):
        found = _text_problem(leaf) if isinstance(leaf, str) else None
        if found is not None:
            errors.append(FieldError(at, *found))
    if errors:
        raise InvalidInput(errors[:MAX_ERRORS])


def split_dicom(body: Any) -> tuple[Any, dict[str, Any] | None]:
    """``POST /v1/jobs``'s body as (payload, ``dicom`` block or None). The block is what a client read
    from its image files (``spine submit --pa-dicom``; ``DicomProvenance``, every view's ``source``
    ``file``): kept on the job as the service keeps its own PACS reads, it completes the payload as
    a header does (``spine_client.dicom.merge.client_provenance_errors``). Raises ``InvalidInput`` naming
    each wrong member by its JSON path under ``dicom``; and, as ``patient_conflict``, the payload's study
    field on which the payload and the films, or the two films, are not of one patient and study, or the
    read of a film's study value the payload replaced (``client_identity_errors``): never reconstructed
    nor stored into the film's study."""
    if not isinstance(body, dict) or body.get("dicom") is None:
        return (({k: v for k, v in body.items() if k != "dicom"}) if isinstance(body, dict) else body), None
    check_text(body["dicom"], ("dicom",))
    payload = {k: v for k, v in body.items() if k != "dicom"}
    try:
        provenance = DicomProvenance.model_validate(body["dicom"])
    except ValidationError as exc:
        raise InvalidInput([FieldError(("dicom", *e["loc"]), e["msg"], e["type"]) for e in exc.errors()]) from None
    errors = client_provenance_errors(provenance)
    if errors:
        raise InvalidInput([FieldError(("dicom", *loc), reason, "dicom_read") for loc, reason in errors[:MAX_ERRORS]])
    conflicts = client_identity_errors(payload, provenance)
    if conflicts:
        raise InvalidInput([FieldError(loc, reason, "patient_conflict") for loc, reason in conflicts[:MAX_ERRORS]])
    return payload, provenance.model_dump(mode="json")


def admit(body: Any, settings: Settings, session: Session, owner: str | None,
          dicom: dict[str, Any] | None = None) -> JobPayload:  # fmt: skip
    """The payload ``body`` (completed by the client's ``dicom`` reads, ``split_dicom``) as a validated
    ``JobPayload`` within the service's limits; raise ``InvalidInput`` otherwise."""
    check_text(body)
    if dicom is not None and isinstance(body, dict):
        body = engine_payload(apply_reads(body, dicom))
    checked, stood_in = _with_stand_in_spacing(body) if settings.dicomweb is not None else (body, ())
    model = validate_payload(checked, unscaled_views=stood_in)
    check_magnitudes(model)
    check_callback(model.callback_url, settings, session, owner)
    return model
