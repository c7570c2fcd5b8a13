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


MIN_LEVELS_PROJECTION_GIVEN = 1
"""A view whose projection is given (and, for the PA, with T1 and L5 given exactly) needs one level."""
MIN_LEVELS_PA = 2
"""The PA view otherwise needs two levels: its translation (2 unknowns) and, with the magnification
from the prior or the acquisition, the spine's extent along the film; below that the placement of
the spine in the film is undetermined."""
MIN_LEVELS_LATERAL = 3
"""A lateral view with its projection estimated needs three levels: its scale and vertical
translation are tied to the PA by the vertical axis both films share (two levels), and its in-plane
rotation needs a third. With fewer, leave the lateral out (a lateral with no landmark is ignored)."""


def minimum_levels(name: str, view: PAView | LateralView, exact_boundary: bool) -> int:
    """The fewest landmarked levels the view needs (``MIN_LEVELS_*``); 0 for an empty lateral."""
    if name != "pa" and not view.landmarks:
        return 0
    if view.projection is not None and (name != "pa" or exact_boundary):
        return MIN_LEVELS_PROJECTION_GIVEN
    return MIN_LEVELS_PA if name == "pa" else MIN_LEVELS_LATERAL


def _view_errors(name: str, view: PAView | LateralView, exact_boundary: bool) -> list[FieldError]:
    """px units need a pixel spacing; a view needs at least ``minimum_levels`` landmarked levels
    (any levels: none is required on either view)."""
    errors = []
    if view.units == "px" and view.pixel_spacing is None:
        errors.append(
            FieldError((name, "pixel_spacing"), "pixel_spacing is required when units is 'px'", "missing")
        )
    need = minimum_levels(name, view, exact_boundary)
    have = len({lm.level for lm in view.landmarks})
    if have < need:
        why = (
            "to place the spine in the film" if name == "pa" else
            "to estimate its scale, translation and rotation against the PA (or give lateral.projection, "
            "or leave the lateral out)"
        )  # fmt: skip
        errors.append(
            FieldError(
                (name, "landmarks"),
                f"the {name} view has {have} landmarked level(s); at least {need} are needed {why}",
                "too_few_landmarks",
            )
        )
    return errors


def validate_payload(payload: Any) -> JobPayload:
    """Validate ``payload`` against the contract; raise ``InvalidInput`` listing every bad field.

    Numbers must be finite, levels known and unique per view, directors orthonormal and
    right-handed within 1e-3, ``px`` units need ``pixel_spacing``, and each view needs at least
    ``minimum_levels`` landmarked levels, any levels (``MIN_LEVELS_*``). A landmark has exactly
    one of ``point`` / ``corners`` (the error names the field: ``point`` when neither is given,
    ``corners`` when both are); corners need an upright view (rows H or F), pedicles the PA view
    with columns L or R. On an upright view the landmarks must run head to feet in level order.
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
    exact = model.boundary is not None and not (model.boundary.T1.soft or model.boundary.L5.soft)
    errors = _view_errors("pa", model.pa, exact) + _landmark_form_errors("pa", model.pa, payload.get("pa"))
    errors += _order_errors("pa", model.pa, payload.get("pa"))
    if model.lateral is not None:
        errors += _view_errors("lateral", model.lateral, exact)
        errors += _landmark_form_errors("lateral", model.lateral, payload.get("lateral"))
        errors += _order_errors("lateral", model.lateral, payload.get("lateral"))
    if errors:
        raise InvalidInput(errors)
    return model
