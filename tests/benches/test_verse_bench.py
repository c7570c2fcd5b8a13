"""``spine bench verse`` measures the user's path: every figure of a case is read from the result
``register()`` returns for the same payload, and a fit the engine refuses is counted, not crashed on.

VerSe spines: the dev split shipped in ``tests/data/verse_dev.csv`` (CC BY-SA 4.0, credited in
``tests/data/README.md``). No bound here is copied from a run: each figure is compared with the
same quantity recomputed from ``register()``'s JSON result (an identity, to float rounding).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benches import calibrate, verse
from benches.truth import payload_from_truth, read_verse
from spine_engine.anatomy import load_profile
from spine_engine.frames import axial_rotation_deg, frames_from_centreline
from spine_engine.levels import N_LEVELS
from spine_engine.measures import compute_measures
from spine_engine.reconstruction import register

VERSE_DEV = Path(__file__).resolve().parents[1] / "data" / "verse_dev.csv"
ALL = list(range(N_LEVELS))

PAYLOAD_ARGS: dict[str, dict[str, Any]] = {
    "PA-17": {},
    "PA-17+corners": {"corner_levels": ALL},
    "PA-17+L-17": {"lateral_levels": ALL},
}
"""The bench's cases as ``payload_from_truth`` arguments, written out here (not read from the bench)."""

WEAK_LANDMARKS = 1e-6
"""Multiplier of the default profile's PA and lateral landmark weights under which the rod ignores
its landmarks: the fit lies millimetres from landmarks stated exact (``EXACT_LANDMARK_SD_MM``), far
beyond ``LANDMARK_SD_CONTRADICTED`` times their SD, so ``register_model`` refuses it
(``InvalidInput``, landmark_sd_contradicted) as it would a user's job under such a profile."""


@pytest.mark.parametrize("case", list(PAYLOAD_ARGS))
def test_figures_are_those_of_the_register_result(case: str) -> None:
    """One VerSe dev spine without noise: the bench's per-level 3D error, kyphosis and lordosis
    errors, registration error and axial rotation error equal those read from ``register()``'s JSON
    result for the payload a user would send (positions, ``measures``, ``fit``, each vertebra's
    reported ``axial_rotation_deg``: without pedicles the population's, not the directors')."""
    spine_id, positions = read_verse(VERSE_DEV)[0]
    rotations = frames_from_centreline(positions)
    result = register(payload_from_truth(positions, rotations, ALL, **PAYLOAD_ARGS[case]))
    found = verse.reconstruct_spine(spine_id, positions, case, load_profile("default"))

    recon = np.array([v["position"] for v in result["vertebrae"]])
    psi = np.array([v["axial_rotation_deg"] for v in result["vertebrae"]])
    truth = compute_measures(positions, rotations)
    m = result["measures"]
    np.testing.assert_allclose(found.per_level_mm, np.linalg.norm(recon - positions, axis=1), rtol=1e-9, atol=1e-9)
    assert found.kyphosis_error_deg == pytest.approx(
        abs(m["thoracic_kyphosis_t4_t12_deg"] - truth.thoracic_kyphosis_t4_t12_deg), rel=1e-9, abs=1e-9
    )
    assert found.lordosis_error_deg == pytest.approx(
        abs(m["lumbar_lordosis_l1_l5_deg"] - truth.lumbar_lordosis_l1_l5_deg), rel=1e-9, abs=1e-9
    )
    assert found.registration_error_mm == pytest.approx(result["fit"]["mean_registration_error_mm"], rel=1e-9)
    assert found.converged is result["fit"]["converged"] is True
    assert found.axial_rotation_error_deg == pytest.approx(
        float(np.mean(np.abs(psi - axial_rotation_deg(rotations))[1:-1])), rel=1e-9, abs=1e-9
    )


def test_pa_only_axial_rotation_is_the_population_s() -> None:
    """Without pedicles the result names population_axial_rotation: the bench's axial rotation error
    is that of the population's rotations the result reports, which here differ from the fitted
    directors' (else the test above could not tell the two apart)."""
    positions = read_verse(VERSE_DEV)[0][1]
    rotations = frames_from_centreline(positions)
    result = register(payload_from_truth(positions, rotations, ALL))
    assert "population_axial_rotation" in [a["name"] for a in result["fit"]["assumed"]]
    directors = np.array([np.array(v["directors"]).T for v in result["vertebrae"]])
    reported = np.array([v["axial_rotation_deg"] for v in result["vertebrae"]])
    assert np.max(np.abs(reported - axial_rotation_deg(directors))[1:-1]) > 0.1


def test_refused_fits_are_counted_not_raised() -> None:
    """Under a profile whose landmark weights are ``WEAK_LANDMARKS`` times the default's,
    ``register_model`` refuses every spine: the summary counts them in ``refused``, reconstructs none,
    and each spine's row names its failure; ``spine bench calibrate``'s score of such a draw is +inf
    (it may never be chosen)."""
    spines = read_verse(VERSE_DEV)[:2]
    base = load_profile("default")
    weak = dataclasses.replace(
        base,
        fit_weight_pa=base.fit_weight_pa * WEAK_LANDMARKS,
        fit_weight_lateral=base.fit_weight_lateral * WEAK_LANDMARKS,
    )
    found = verse.summary("PA-17", verse.evaluate(spines, "PA-17", weak))
    assert (found["spines"], found["reconstructed"], found["refused"], found["not_converged"]) == (2, 0, 2, 0)
    assert [r.get("failure") for r in found["per_spine"]] == ["refused", "refused"]
    assert calibrate.score(spines, weak) == (math.inf, math.inf)


def test_written_json_says_what_it_measured(tmp_path: Path) -> None:
    """``verse-dev.json`` (two spines): every case summary's field is described in ``fields`` and the
    JSON says its figures are read from register_model's result; means are over the reconstructed."""
    folder = tmp_path / "verse"
    folder.mkdir()
    lines = VERSE_DEV.read_text().splitlines()
    (folder / "dev.csv").write_text("\n".join(lines[:3]) + "\n")
    assert verse.main(["--split", "dev", "--data", str(folder), "--out", str(tmp_path)]) == 0
    written = json.loads((tmp_path / "verse-dev.json").read_text())
    assert "register_model" in written["measured"]
    for case in written["cases"]:
        assert case["spines"] == case["reconstructed"] == 2
        assert set(verse.FIELDS) <= set(case)
        assert case["mean_3d_error_mm"] == pytest.approx(np.mean([r["mean_mm"] for r in case["per_spine"]]))
