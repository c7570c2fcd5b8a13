"""The JSON fields the benches write for docs/engine.md and docs/performance.md, each on a tiny input.

docs/ reads every figure from a bench's JSON in docs/figures/; these tests run each command (its
``main``) on a few spines or radiographs and check that the field is there and holds what its
docstring says, as an identity with the other fields or the shipped profile (no bound is copied from
a run's output). VerSe spines: the dev split shipped in ``tests/data/verse_dev.csv`` (CC BY-SA 4.0,
credited in ``tests/data/README.md``).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from benches import aasce, clinic, noise_weight, perf, prior, verse
from benches.truth import read_verse
from spine_engine.anatomy import length_over_pa_projection, load_profile, rest_shape_unit
from spine_engine.frames import frames_from_centreline
from spine_engine.levels import N_LEVELS
from spine_engine.measures import kyphosis_lordosis_deg
from spine_engine.reconstruction import LANDMARK_SD_CONTRADICTED

VERSE_DEV = Path(__file__).resolve().parents[1] / "data" / "verse_dev.csv"
AASCE_TRAINING = clinic.shared_data_dir("aasce2019") / "training"


def _verse_folder(tmp_path: Path, spines: int) -> Path:
    """A VerSe folder whose dev.csv holds the first ``spines`` rows of the shipped dev split."""
    lines = VERSE_DEV.read_text().splitlines()
    folder = tmp_path / "verse"
    folder.mkdir()
    (folder / "dev.csv").write_text("\n".join(lines[: spines + 1]) + "\n")
    return folder


# ---------------------------------------------------------------- spine bench prior


def test_shipped_figures_are_the_profiles() -> None:
    """``prior.json`` ``shipped``: L/P of the population (the profile's) and of the rest shape
    (recomputed here from its positions), c their ratio, the rest rod shorter by 1 − 1/c without it;
    the T1/L5 inclination SDs are the set-up prior's d1 entries; the rest shape's measures are those of
    its centreline frames; T9, near the kyphosis' apex (posterior, +y), lies behind the centroid along
    the PA beam (−y): a negative offset; on the lateral, whose beam (+x) is normal to the rest shape's
    sagittal plane (x = 0), the offset is 0."""
    profile = load_profile()
    found = prior.shipped_figures(profile)
    data = profile.population_prior
    assert data is not None
    lp = found["length_over_pa_projection"]
    rest = rest_shape_unit(profile)[1]
    assert lp["population_mean"] == data["length_over_pa_projection"]
    assert lp["rest_shape"] == pytest.approx(length_over_pa_projection(rest), rel=1e-12)
    assert lp["length_correction"] == pytest.approx(lp["population_mean"] / lp["rest_shape"], rel=1e-12)
    assert lp["rest_rod_shorter_without_it_pct"] == pytest.approx(100 * (1 - lp["rest_shape"] / lp["population_mean"]))
    assert found["sagittal_inclination_sd_deg"] == {k: v[0] for k, v in data["orientation_sd_deg"].items()}
    assert found["measure_sd_deg"] == data["measure_sd_deg"]
    kyphosis, kyphosis_t5, lordosis = kyphosis_lordosis_deg(frames_from_centreline(rest))
    assert found["rest_shape_measures_deg"] == {"kyphosis_t4_t12": kyphosis, "kyphosis_t5_t12": kyphosis_t5,
                                                "lordosis_l1_l5": lordosis}  # fmt: skip
    assert found["mid_plane_offset_mm"]["pa"] < 0.0
    assert found["mid_plane_offset_mm"]["lateral"] == 0.0


@pytest.mark.skipif(not AASCE_TRAINING.is_dir(), reason=f"AASCE 2019 training not found at {AASCE_TRAINING}")
def test_prior_command_writes_the_shipped_figures(tmp_path: Path) -> None:
    """``spine bench prior`` (50 draws) writes ``shipped`` into prior.json."""
    prior.main(["--verse", str(VERSE_DEV), "--aasce", str(AASCE_TRAINING), "--samples", "50", "--out", str(tmp_path)])
    written = json.loads((tmp_path / "prior.json").read_text())
    assert written["shipped"] == json.loads(json.dumps(prior.shipped_figures(load_profile())))


# ---------------------------------------------------------------- spine bench clinic --seeds


def test_sweep_file_is_named_by_noise_seeds_and_dropped_levels(tmp_path: Path) -> None:
    """Each sweep keeps its own file; ``median_residual_to_sd`` lies between 0 and the maximum."""
    data = _verse_folder(tmp_path, 1)
    args = ["--split", "dev", "--data", str(data), "--synthetic", "0", "--cases", "e", "--out", str(tmp_path)]
    assert clinic.main([*args, "--seeds", "1", "--noise-mm", "2", "--drop-levels"]) == 0
    assert clinic.main([*args, "--seeds", "2", "--seed", "1"]) == 0
    assert clinic.sweep_stem("dev", 1.0, False) == "clinic-sweep-dev"
    first = json.loads((tmp_path / "clinic-sweep-dev-noise2-seeds0-0-drop-levels.json").read_text())
    second = json.loads((tmp_path / "clinic-sweep-dev-seeds1-2.json").read_text())
    assert first["noise_mm"] == 2.0 and first["drop_levels"] and not second["drop_levels"]
    for sweep in (first, second):
        assert set(sweep["per_case"]) == {"e", "e0"}
        for row in sweep["per_case"].values():
            assert 0.0 < row["median_residual_to_sd"] <= row["max_residual_to_sd"]


def test_sweep_with_a_stated_sd_too_small_counts_the_refusals_and_their_ratio(tmp_path: Path) -> None:
    """``--stated-sd-mm 0.01`` on 1 mm of noise, case (a): the payload is refused for a contradicted
    SD, which the sweep counts apart from failures, with the ratio the refusal states, above the
    bound that refused it (``reconstruction.LANDMARK_SD_CONTRADICTED``)."""
    data = _verse_folder(tmp_path, 1)
    args = ["--split", "dev", "--data", str(data), "--synthetic", "0", "--cases", "a", "--out", str(tmp_path)]
    assert clinic.main([*args, "--seeds", "1", "--stated-sd-mm", "0.01"]) == 0
    sweep = json.loads((tmp_path / "clinic-sweep-dev-stated0.01-seeds0-0.json").read_text())
    row = sweep["per_case"]["a"]
    assert sweep["stated_sd_mm"] == 0.01 and sweep["failed"] == 0
    assert row["runs"] == row["refused_sd_contradicted"] == 1
    assert row["median_residual_to_sd"] == row["max_residual_to_sd"] > LANDMARK_SD_CONTRADICTED


# ---------------------------------------------------------------- spine bench aasce


def _radiographs(folder: Path) -> None:
    """Two made-up radiographs from a VerSe dev spine's PA projection (0.5 mm per px): upright
    40 × 20 mm boxes whose top edges' midpoints are the vertebrae; the second with one box's top
    corners swapped (a crossed quadrilateral)."""
    positions = read_verse(VERSE_DEV)[0][1]
    height_px = aasce.CASSETTE_HEIGHT_MM / 0.5
    col = 600.0 + (positions[:, 0] - positions[0, 0]) / 0.5
    row = 200.0 + (positions[0, 2] - positions[:, 2]) / 0.5
    corners = np.stack([np.stack([col - 40, row], 1), np.stack([col + 40, row], 1),
                        np.stack([col - 40, row + 40], 1), np.stack([col + 40, row + 40], 1)], axis=1)  # fmt: skip
    crossed = corners.copy()
    crossed[8, [0, 1]] = crossed[8, [1, 0]]
    folder.mkdir(parents=True)
    header = ["filename", "img_w_est", "img_h_est"] + [f"{a}{k}" for k in range(4 * N_LEVELS) for a in "xy"]
    with (folder / "landmarks_px_from_mat.csv").open("w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(header)
        for name, quads in (("good.jpg", corners), ("crossed.jpg", crossed)):
            out.writerow([name, 1200.0, height_px, *quads.reshape(-1).tolist()])
    (folder / "angles.csv").write_text("5,0,0\n5,0,0\n")
    (folder / "filenames.csv").write_text("good.jpg\ncrossed.jpg\n")


def test_aasce_counts_the_refusals_by_reason(tmp_path: Path) -> None:
    """``refused_by_reason``: the crossed quadrilateral refuses the second radiograph's corners
    (``corners_not_convex``), its midpoints are fitted; each radiograph lists its own refusals."""
    _radiographs(tmp_path / "aasce" / "test")
    assert aasce.main(["--split", "test", "--data", str(tmp_path / "aasce"), "--out", str(tmp_path)]) == 0
    written = json.loads((tmp_path / "aasce-test.json").read_text())
    rows = {r["method"]: r for r in written["all"]}
    assert rows["corners"]["refused_by_reason"] == {"corners_not_convex": 1}
    assert rows["corners"]["not_reconstructed"] == 1
    assert rows["midpoints"]["refused_by_reason"] == {}
    assert [r["refusals"] for r in written["per_radiograph"]] == [{}, {"corners": ["corners_not_convex"]}]


# ---------------------------------------------------------------- spine bench noise-weight


def test_noise_weight_writes_its_grid(tmp_path: Path) -> None:
    """``noise-weight.json``: one row per multiplier with the weight it scored and the score, the mean
    of the cases' errors; the best is the lowest score."""
    data = _verse_folder(tmp_path, 2)
    assert noise_weight.main(["--data", str(data), "--grid", "3,1", "--cases", "e", "--out", str(tmp_path)]) == 0
    written = json.loads((tmp_path / "noise-weight.json").read_text())
    profile = load_profile()
    assert written["fit_weight_pa"] == profile.fit_weight_pa and written["spines"] == 2
    assert [r["multiplier"] for r in written["grid"]] == [3.0, 1.0]
    for r in written["grid"]:
        assert r["fit_weight_pa"] == pytest.approx(r["multiplier"] * profile.fit_weight_pa)
        assert r["score_mm"] == pytest.approx(np.mean(list(r["mean_3d_error_mm"].values())))
    assert written["best_multiplier"] == min(written["grid"], key=lambda r: r["score_mm"])["multiplier"]


# ---------------------------------------------------------------- spine bench verse --pa-kyphosis


def test_pa_kyphosis_reports_what_its_spines_read(tmp_path: Path) -> None:
    """``verse-dev-pa-kyphosis-noise1.json``: the summary is the per-spine rows' (RMSE, coverage, SD
    range); T1 and L5 given exactly flag the kyphosis on every spine; the trivial answer is the
    profile's population mean."""
    data = _verse_folder(tmp_path, 3)
    args = ["--split", "dev", "--data", str(data), "--pa-kyphosis", "--noise-mm", "1", "--out", str(tmp_path)]
    assert verse.main(args) == 0
    written = json.loads((tmp_path / "verse-dev-pa-kyphosis-noise1.json").read_text())
    rows = written["per_spine"]
    truth = np.array([r["truth_deg"] for r in rows])
    reported = np.array([r["reported_deg"] for r in rows])
    sd = np.array([r["sd_deg"] for r in rows])
    assert written["spines"] == 3 and written["flagged"] == 3
    assert written["kyphosis_rmse_deg"] == pytest.approx(float(np.sqrt(np.mean((reported - truth) ** 2))))
    assert written["coverage_95"] == pytest.approx(float(np.mean(np.abs(reported - truth) <= 1.96 * sd)))
    assert written["sd_deg"]["min"] == sd.min() and written["sd_deg"]["max"] == sd.max()
    population = load_profile().population_prior["provenance"]["population"]  # type: ignore[index]
    assert written["population_mean_deg"] == population["kyphosis_t4_t12_deg"]["mean"]
    assert -1.0 <= written["truth_correlation_with_t1_inclination"] <= 1.0


# ---------------------------------------------------------------- spine bench perf


def test_perf_register_rows_say_their_spines_and_calls(tmp_path: Path) -> None:
    """``perf.json``: the ``register()`` rows give the spines cycled over and the timed calls."""
    out = tmp_path / "perf.json"
    assert perf.main(["--repeats", "2", "--register", "--clinic", "e", "--out", str(out)]) == 0
    rows = [r for r in json.loads(out.read_text())["results"] if r["problem"].startswith("register()")]
    assert [(r["spines"], r["repeats"]) for r in rows] == [(24, 2), (24, 2)]
