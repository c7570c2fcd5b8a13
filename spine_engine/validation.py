"""Turn a raw payload (a JSON object) into a validated ``JobPayload`` or a typed ``InvalidInput``."""

from typing import Any

from pydantic import ValidationError

from .errors import FieldError, InvalidInput
from .models import JobPayload, LateralView, PAView


def _clean_loc(loc: tuple[Any, ...]) -> tuple[str | int, ...]:
    # pydantic adds the type of a union member or a validator tag to the location: drop them.
    return tuple(p for p in loc if isinstance(p, int) or not str(p).startswith(("function-", "tagged-union")))


def _view_errors(name: str, view: PAView | LateralView) -> list[FieldError]:
    errors = []
    if view.units == "px" and view.pixel_spacing is None:
        errors.append(
            FieldError((name, "pixel_spacing"), "pixel_spacing is required when units is 'px'", "missing")
        )
    if view.projection is None:
        levels = {lm.level for lm in view.landmarks}
        missing = [lv for lv in ("T1", "L5") if lv not in levels]
        if missing:
            errors.append(
                FieldError(
                    (name, "landmarks"),
                    f"the boundary vertebrae {missing} have no landmark: without {name}.projection "
                    "the T1 and L5 landmarks are needed to estimate the scale and translation",
                    "boundary_landmarks_missing",
                )
            )
    return errors


def validate_payload(payload: Any) -> JobPayload:
    """Validate ``payload`` against the contract; raise ``InvalidInput`` listing every bad field.

    Numbers must be finite, levels known and unique per view, directors orthonormal and
    right-handed within 1e-3, ``px`` units need ``pixel_spacing``, and without a given
    projection a view must have the T1 and L5 landmarks to estimate it.
    """
    if not isinstance(payload, dict):
        raise InvalidInput([FieldError((), "the payload must be a JSON object", "type_error")])
    try:
        model = JobPayload.model_validate(payload)
    except ValidationError as exc:
        raise InvalidInput(
            [
                FieldError(_clean_loc(tuple(e["loc"])), str(e["msg"]).removeprefix("Value error, "), e["type"])
                for e in exc.errors(include_url=False)
            ]
        ) from None
    errors = _view_errors("pa", model.pa)
    if model.lateral is not None:
        errors += _view_errors("lateral", model.lateral)
    if errors:
        raise InvalidInput(errors)
    return model
