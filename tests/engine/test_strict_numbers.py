"""Every number of the job payload is a JSON number (``spine_engine.models.Number``): the string ``"1.0"``
and the boolean ``true``, which pydantic's lax mode turns into 1.0, are refused with an ``InvalidInput``
naming the field (``float_type``), and a JSON integer where the contract says number is taken as that
number. Each number field of the payload models is tried (the test lists them from the models, so a
field added later is tried too)."""

from __future__ import annotations

import decimal
import json
import typing
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from pydantic import BaseModel

from spine_engine.errors import InvalidInput
from spine_engine.levels import LEVELS
from spine_engine.models import JobPayload
from spine_engine.validation import validate_payload

IDENTITY_LPS = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]  # rows d1, d2, d3

Path = tuple[str | int, ...]


def every_number() -> dict[str, Any]:
    """A valid payload that gives every number field of the payload models at least once: a PA film in px
    with a known acquisition geometry (SID, SOD, ERMF, central ray, image size), landmarks as points, as
    corners and with pedicles, its landmark SD; a lateral film with a known projection; soft boundary poses.
    The numbers are whole (``100.0``) so that the same payload can be sent with JSON integers."""
    spacing = 0.25
    pa_landmarks: list[dict[str, Any]] = []
    lateral_landmarks: list[dict[str, Any]] = []
    for i, level in enumerate(LEVELS):
        col, row = 1000.0 + (i % 3), 200.0 + 100.0 * i  # px: 25 mm between levels at 0.25 mm/px
        landmark: dict[str, Any] = {"level": level, "point": [col, row]}
        if level == "T6":
            landmark = {"level": level, "corners": [[col - 60.0, row], [col + 60.0, row],
                                                    [col - 60.0, row + 80.0], [col + 60.0, row + 80.0]]}  # fmt: skip
        if level == "T9":
            landmark["pedicles"] = [[col - 40.0, row + 20.0], [col + 40.0, row + 20.0]]
        pa_landmarks.append(landmark)
        lateral_landmarks.append({"level": level, "point": [60.0 + (i % 2), 50.0 + 25.0 * i]})
    payload = {
        "pa": {
            "units": "px",
            "pixel_spacing": [spacing, spacing],
            "landmarks": pa_landmarks,
            "landmark_sd_mm": 2.0,
            "acquisition": {
                "distance_source_to_detector_mm": 1800.0,
                "distance_source_to_patient_mm": 1600.0,
                "central_ray": [1000.0, 1000.0],
                "image_size": [2000.0, 2400.0],
            },
        },
        "lateral": {
            "landmarks": lateral_landmarks,
            "projection": {"scale": 1.0, "translation": [0.0, 0.0]},
        },
        "boundary": {
            "T1": {"position": [0.0, 0.0, 0.0], "directors": IDENTITY_LPS, "position_sd_mm": 5.0,
                   "directors_sd_deg": 5.0},
            "L5": {"position": [0.0, 0.0, -400.0], "directors": IDENTITY_LPS, "position_sd_mm": 5.0,
                   "directors_sd_deg": 5.0},
        },
    }  # fmt: skip
    copy: dict[str, Any] = json.loads(json.dumps(payload))  # no shared lists
    return copy


def with_magnification() -> dict[str, Any]:
    """A PA film whose acquisition gives its ERMF alone (a weak perspective: not with SID and SOD)."""
    payload = every_number()
    payload["pa"]["acquisition"] = {"magnification": 1.0}
    return payload


PAYLOADS = {"every_number": every_number, "with_magnification": with_magnification}


def number_leaves(value: Any, path: Path = ()) -> Iterator[Path]:
    """The paths of the JSON numbers in ``value`` (booleans are not numbers)."""
    if isinstance(value, dict):
        for key, item in value.items():
            yield from number_leaves(item, (*path, key))
    elif isinstance(value, list):
        for i, item in enumerate(value):
            yield from number_leaves(item, (*path, i))
    elif isinstance(value, int | float) and not isinstance(value, bool):
        yield path


def field_of(path: Path) -> str:
    """The member a number belongs to: the last name in its path (``pa.landmarks[3].point[0]`` → ``point``)."""
    return next(str(part) for part in reversed(path) if isinstance(part, str))


def json_path(path: Path) -> str:
    """``path`` as ``FieldError.path`` writes it."""
    text = ""
    for part in path:
        text += f"[{part}]" if isinstance(part, int) else ("." if text else "") + part
    return text


def replaced(payload: dict[str, Any], path: Path, value: Any) -> dict[str, Any]:
    copy: dict[str, Any] = json.loads(json.dumps(payload))
    node: Any = copy
    for part in path[:-1]:
        node = node[part]
    node[path[-1]] = value
    return copy


def _has_float(annotation: Any) -> bool:
    if annotation is float:
        return True
    return any(_has_float(arg) for arg in typing.get_args(annotation))


def _models_in(annotation: Any) -> Iterator[type[BaseModel]]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        yield annotation
    for arg in typing.get_args(annotation):
        yield from _models_in(arg)


def payload_number_fields() -> set[str]:
    """The names of the number fields of ``JobPayload`` and of every model under it."""
    found: set[str] = set()
    seen: set[type[BaseModel]] = set()
    pending: list[type[BaseModel]] = [JobPayload]
    while pending:
        model = pending.pop()
        if model in seen:
            continue
        seen.add(model)
        for name, info in model.model_fields.items():
            annotation = info.rebuild_annotation()
            if _has_float(annotation):
                found.add(name)
            pending.extend(_models_in(annotation))
    return found


def all_paths() -> list[tuple[str, Path]]:
    return [(name, path) for name, make in PAYLOADS.items() for path in number_leaves(make())]


def test_the_payloads_are_valid_and_give_every_number_field() -> None:
    for make in PAYLOADS.values():
        validate_payload(make())
    given = {field_of(path) for _, path in all_paths()}
    assert given == payload_number_fields() != set()


@pytest.mark.parametrize("sent", ["1.0", True, False, "abc"], ids=["string", "true", "false", "text"])
def test_a_string_or_a_boolean_for_a_number_is_refused_naming_the_field(sent: Any) -> None:
    for name, path in all_paths():
        with pytest.raises(InvalidInput) as refused:
            validate_payload(replaced(PAYLOADS[name](), path, sent))
        errors = [(e.path, e.type) for e in refused.value.errors]
        assert errors == [(json_path(path), "float_type")], (name, path, errors)
        message = refused.value.errors[0].msg
        expected = "not a boolean" if isinstance(sent, bool) else "not a string"
        assert message.startswith("a number is expected") and expected in message, message


def test_json_integers_are_numbers() -> None:
    """The same payloads with every whole number sent as a JSON integer (``100`` for ``100.0``) give the
    same model, as a client whose JSON writer drops ``.0`` sends them. Every number field is sent so but
    the pixel spacing (0.25 mm: whole millimetres per pixel would put the levels metres apart)."""
    sent_as_integers: set[str] = set()
    for make in PAYLOADS.values():
        payload = make()
        integers = payload
        for path in number_leaves(payload):
            node: Any = payload
            for part in path:
                node = node[part]
            if float(node).is_integer():
                integers = replaced(integers, path, int(node))
                sent_as_integers.add(field_of(path))
        assert isinstance(integers["pa"]["landmarks"][0]["point"][0], int)
        assert validate_payload(integers) == validate_payload(payload)
    assert sent_as_integers == payload_number_fields() - {"pixel_spacing"}


def test_the_contract_still_says_number() -> None:
    """The JSON schema of the number fields is unchanged by their strictness: ``type: number``."""
    schema = json.dumps(JobPayload.model_json_schema(mode="validation"))
    assert '"type": "number"' in schema and "strict" not in schema


def test_python_numbers_from_other_libraries_are_numbers() -> None:
    """A payload built in Python (the benches', the DICOM layer's) may hold numpy numbers or a
    ``decimal.Decimal``: numbers, so taken."""
    payload = every_number()
    payload["pa"]["landmarks"][0]["point"] = [np.float64(1000.0), np.int64(200)]
    payload["pa"]["landmark_sd_mm"] = decimal.Decimal("2.0")
    model = validate_payload(payload)
    assert model.pa.landmarks[0].point == (1000.0, 200.0) and model.pa.sd_mm == 2.0
