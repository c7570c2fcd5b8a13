"""A view's stated landmark SD that its own landmarks contradict is refused, naming the field
(``reconstruction.LANDMARK_SD_CONTRADICTED``): stated 100 or 1000 times below the clicks' scatter
it used to give intervals that much too narrow, or, with SID and SOD and no central ray, a fit that
crawled to "did not converge in 500 iterations". Stated as it is, nothing is refused."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from benches.clinic import truths_of_csv
from benches.clinic_films import CASES, Truth, build_payload, simulate_series
from spine_engine import register
from spine_engine.errors import InvalidInput
from spine_engine.models import LANDMARK_SD_MM_MIN
from tests.conftest import spine_payload

VERSE_DEV = Path(__file__).resolve().parents[1] / "data" / "verse_dev.csv"


@pytest.fixture(scope="module")
def truths() -> list[Truth]:
    return truths_of_csv(VERSE_DEV)[:4]


def _films(truth: Truth, case: str, noise_mm: float, stated_mm: float) -> dict[str, Any]:
    payload = build_payload(simulate_series(truth, noise_mm, 3), CASES[case]).model_dump(mode="json", exclude_none=True)
    for view in ("pa", "lateral"):
        if view in payload:
            payload[view]["landmark_sd_mm"] = stated_mm
    return payload


@pytest.mark.parametrize("stated_mm", [0.01, 0.001])
def test_an_sd_far_below_the_clicks_scatter_is_refused_naming_it(truths: list[Truth], stated_mm: float) -> None:
    """1 mm of noise stated as 0.01 or 0.001 mm; case (g), where 0.001 mm made every one of these
    four spines fail to converge, and case (a)."""
    for truth in truths:
        for case in "ag":
            with pytest.raises(InvalidInput) as info:
                register(_films(truth, case, 1.0, stated_mm))
            paths = {e.path for e in info.value.errors}
            assert paths == {"pa.landmark_sd_mm", "lateral.landmark_sd_mm"}, (truth.spine_id, case, paths)
            assert all(e.type == "landmark_sd_contradicted" for e in info.value.errors)
            assert "times the landmark SD stated" in str(info.value)


@pytest.mark.parametrize("noise_mm", [0.5, 1.0, 3.0])
def test_an_sd_stated_as_the_clicks_have_it_is_never_refused(truths: list[Truth], noise_mm: float) -> None:
    for truth in truths:
        for case in "abcdeg":
            assert register(_films(truth, case, noise_mm, noise_mm))["fit"]["converged"]


@pytest.mark.parametrize("stated_mm", [1e-5, 1e-9])
def test_a_landmark_sd_below_the_floor_is_refused_naming_it(stated_mm: float) -> None:
    """Below ``LANDMARK_SD_MM_MIN`` the fit failed to converge (1e-5 mm: ``FitFailed`` naming no field,
    a valid payload failing) or reported every SD as 0 (1e-9 mm): it is refused before the fit, naming
    the field; the floor itself fits."""
    payload = spine_payload()
    payload.pop("boundary")
    payload["pa"]["landmark_sd_mm"] = stated_mm
    with pytest.raises(InvalidInput) as info:
        register(payload)
    assert [e.path for e in info.value.errors] == ["pa.landmark_sd_mm"]
    payload["pa"]["landmark_sd_mm"] = LANDMARK_SD_MM_MIN
    assert register(payload)["fit"]["converged"] is not False
