"""Turn a raw payload (a JSON object) into a validated ``JobPayload`` or a typed ``InvalidInput``."""

import itertools
from typing import Any

from pydantic import ValidationError

from .errors import FieldError, InvalidInput
from .levels import LEVEL_INDEX, LEVELS
from .models import JobPayload, LateralView, PAView

_FIELD_OF_ERROR = {"landmark_point_missing": "point", "landmark_point_and_corners": "corners"}
"""Errors raised by a model validator on a whole landmark, and the field their location names."""

_UPRIGHT_ROWS = ("H", "F")
_FRONTAL_COLUMNS = ("L", "R")


def _clean_loc(loc: tuple[Any, ...], kind: str = "") -> tuple[str | int, ...]:
    # pydantic adds the type of a union member or a validator tag to the location: drop them.
    clean = tuple(p for p in loc if isinstance(p, int) or not str(p).startswith(("function-", "tagged-union")))
    return (*clean, _FIELD_OF_ERROR[kind]) if kind in _FIELD_OF_ERROR else clean


def _landmark_form_errors(name: str, view: PAView | LateralView, raw: Any) -> list[FieldError]:
    """Corners need an upright view and pedicles a frontal one; locations use the payload's indices."""
    errors: list[FieldError] = []
    raw_landmarks = raw.get("landmarks") if isinstance(raw, dict) else None
    if not isinstance(raw_landmarks, list):
        return errors
    column, row = view.patient_orientation
    for i, lm in enumerate(raw_landmarks):
        if not isinstance(lm, dict):
            continue
        if lm.get("corners") is not None and row not in _UPRIGHT_ROWS:
            errors.append(
                FieldError(
                    (name, "landmarks", i, "corners"),
                    f"corners need an upright image (row direction H or F), got patient orientation {[column, row]}",
                    "corners_need_upright_view",
                )
            )
        if lm.get("pedicles") is not None and (name != "pa" or column not in _FRONTAL_COLUMNS):
            errors.append(
                FieldError(
                    (name, "landmarks", i, "pedicles"),
                    "pedicles are supported on the PA view only, with columns toward the patient's L or R",
                    "pedicles_not_supported",
                )
            )
    return errors


def _reference_row(landmark: dict[str, Any]) -> float | None:
    """Image row of a raw landmark's top endplate midpoint: its point, or the mean of its top corners."""
    if landmark.get("point") is not None:
        return float(landmark["point"][1])
    if landmark.get("corners") is not None:
        return 0.5 * (float(landmark["corners"][0][1]) + float(landmark["corners"][1][1]))
    return None


def _order_errors(name: str, view: PAView | LateralView, raw: Any) -> list[FieldError]:
    """On an upright view (rows toward F or H) the levels must follow each other head to feet.

    A vertebra drawn above the one cranial to it is an annotation error (swapped or misplaced
    landmarks) that no spine can have; it is refused rather than reconstructed into nonsense.
    Locations use the payload's own indices.
    """
    row_direction = view.patient_orientation[1]
    if row_direction not in _UPRIGHT_ROWS or not isinstance(raw, dict) or not isinstance(raw.get("landmarks"), list):
        return []
    toward_feet = 1.0 if row_direction == "F" else -1.0
    placed = sorted(
        (LEVEL_INDEX[lm["level"]], i, row)
        for i, lm in enumerate(raw["landmarks"])
        if (row := _reference_row(lm)) is not None
    )
    errors = []
    for (_, _, upper_row), (lower, i, lower_row) in itertools.pairwise(placed):
        if (lower_row - upper_row) * toward_feet <= 0:
            errors.append(
                FieldError(
                    (name, "landmarks", i),
                    f"level {LEVELS[lower]} (row {lower_row:g}) is not below the level above it (row {upper_row:g}): "
                    f"on an image whose rows run toward {row_direction}, landmarks must run head to feet",
                    "landmarks_out_of_order",
                )
            )
    return errors


def _view_errors(name: str, view: PAView | LateralView, has_boundary: bool) -> list[FieldError]:
    """px units need a pixel spacing; the T1 and L5 landmarks are needed to estimate a view's
    projection when none is given, and on the PA view to place the spine without a boundary."""
    errors = []
    if view.units == "px" and view.pixel_spacing is None:
        errors.append(
            FieldError((name, "pixel_spacing"), "pixel_spacing is required when units is 'px'", "missing")
        )
    if view.projection is None:
        needed_for = (
            f"without {name}.projection the T1 and L5 landmarks are needed to estimate the scale and translation"
        )
    elif name == "pa" and not has_boundary:
        needed_for = "without boundary conditions the PA view needs the T1 and L5 landmarks to place the spine"
    else:
        return errors
    levels = {lm.level for lm in view.landmarks}
    missing = [lv for lv in ("T1", "L5") if lv not in levels]
    if missing:
        errors.append(
            FieldError(
                (name, "landmarks"),
                f"the boundary vertebrae {missing} have no landmark: {needed_for}",
                "boundary_landmarks_missing",
            )
        )
    return errors


def validate_payload(payload: Any) -> JobPayload:
    """Validate ``payload`` against the contract; raise ``InvalidInput`` listing every bad field.

    Numbers must be finite, levels known and unique per view, directors orthonormal and
    right-handed within 1e-3, ``px`` units need ``pixel_spacing``, and without a given
    projection a view must have the T1 and L5 landmarks to estimate it. A landmark has exactly
    one of ``point`` / ``corners`` (the error names the field: ``point`` when neither is given,
    ``corners`` when both are); corners need an upright view (rows H or F), pedicles the PA view
    with columns L or R. Without ``boundary`` the PA view needs T1 and L5 landmarks. On an
    upright view the landmarks must run head to feet in level order.
    """
    if not isinstance(payload, dict):
        raise InvalidInput([FieldError((), "the payload must be a JSON object", "type_error")])
    try:
        model = JobPayload.model_validate(payload)
    except ValidationError as exc:
        raise InvalidInput(
            [
                FieldError(
                    _clean_loc(tuple(e["loc"]), e["type"]), str(e["msg"]).removeprefix("Value error, "), e["type"]
                )
                for e in exc.errors(include_url=False)
            ]
        ) from None
    has_boundary = model.boundary is not None
    errors = _view_errors("pa", model.pa, has_boundary) + _landmark_form_errors("pa", model.pa, payload.get("pa"))
    errors += _order_errors("pa", model.pa, payload.get("pa"))
    if model.lateral is not None:
        errors += _view_errors("lateral", model.lateral, has_boundary)
        errors += _landmark_form_errors("lateral", model.lateral, payload.get("lateral"))
        errors += _order_errors("lateral", model.lateral, payload.get("lateral"))
    if errors:
        raise InvalidInput(errors)
    return model
