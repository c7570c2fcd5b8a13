"""Payloads that describe the same films give the same answer: the landmarks in pixels of a
non-square spacing instead of millimetres, the film's columns mirrored with the patient orientation
saying so (DICOM PS3.3 C.7.6.1.1.1), or every coordinate shifted with the film. ``register()`` on
each clinic case (``spine bench clinic``'s films of a VerSe dev spine and a synthetic one) must
return the same shape and measures; the solver stops at 1e-9 of a relative step, so equal answers
agree to far below 1e-6 mm and degrees (measured: 4e-13)."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benches.clinic import synthetic_truths, truths_of_csv
from benches.clinic_films import CASES, Truth, build_payload, simulate_series
from spine_engine import register

VERSE_DEV = Path(__file__).resolve().parents[1] / "data" / "verse_dev.csv"
FLIP = {"L": "R", "R": "L", "A": "P", "P": "A", "H": "F", "F": "H"}
DEFAULT_ORIENTATION = {"pa": ("L", "F"), "lateral": ("A", "F")}
SPACING = (0.15, 0.1)
"""[row, column] mm per pixel, as DICOM (0028,0030) orders them."""


def _free_views(payload: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """(name, view) of the views whose film coordinates the transformations move (not one with a
    known projection)."""
    return [(name, v) for name in ("pa", "lateral") if (v := payload.get(name)) and not v.get("projection")]


def _map_points(view: dict[str, Any], f: Any) -> None:
    for lm in view["landmarks"]:
        lm["point"] = f(lm["point"])
    acquisition = view.get("acquisition") or {}
    if "central_ray" in acquisition:
        acquisition["central_ray"] = f(acquisition["central_ray"])


def in_pixels(payload: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(payload)
    for name in ("pa", "lateral"):
        if view := out.get(name):
            _map_points(view, lambda p: [p[0] / SPACING[1], p[1] / SPACING[0]])
            view.update(units="px", pixel_spacing=list(SPACING))
    return out


def mirrored(payload: dict[str, Any], width: float = 480.0) -> dict[str, Any]:
    out = copy.deepcopy(payload)
    for name, view in _free_views(out):
        column, row = view.get("patient_orientation", DEFAULT_ORIENTATION[name])
        view["patient_orientation"] = [FLIP[column], row]
        _map_points(view, lambda p: [width - p[0], p[1]])
    return out


def shifted(payload: dict[str, Any], by: tuple[float, float] = (37.0, -23.0)) -> dict[str, Any]:
    out = copy.deepcopy(payload)
    for _, view in _free_views(out):
        _map_points(view, lambda p: [p[0] + by[0], p[1] + by[1]])
    return out


def _answer(result: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    positions = np.array([v["position"] for v in result["vertebrae"]])
    m = result["measures"]
    measures = [m["thoracic_kyphosis_t4_t12_deg"], m["lumbar_lordosis_l1_l5_deg"], m["largest_cobb"]["angle_deg"],
                m["thoracic_kyphosis_t4_t12_sd_deg"], m["lumbar_lordosis_l1_l5_sd_deg"]]  # fmt: skip
    return positions - positions.mean(axis=0), np.array(measures, dtype=float)


@pytest.fixture(scope="module")
def truths() -> list[Truth]:
    return truths_of_csv(VERSE_DEV)[:1] + synthetic_truths(1, 0, "dev")


@pytest.mark.parametrize("transform", [in_pixels, mirrored, shifted], ids=["pixels", "mirrored", "shifted"])
def test_the_same_films_described_otherwise_give_the_same_answer(truths: list[Truth], transform: Any) -> None:
    for truth in truths:
        series = simulate_series(truth, 1.0, 0)
        for key, case in CASES.items():
            payload = build_payload(series, case).model_dump(mode="json", exclude_none=True)
            assert all("point" in lm for _, v in _free_views(payload) for lm in v["landmarks"])
            positions, measures = _answer(register(payload))
            other_positions, other_measures = _answer(register(transform(payload)))
            np.testing.assert_allclose(other_positions, positions, atol=1e-6, err_msg=f"{truth.spine_id} ({key})")
            np.testing.assert_allclose(other_measures, measures, atol=1e-6, err_msg=f"{truth.spine_id} ({key})")
