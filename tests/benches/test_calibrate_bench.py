"""``spine bench calibrate``: what it draws, where it refuses to write, and its ``--check``."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from benches import calibrate
from spine_engine.anatomy import PROFILES_DIR, load_profile

VERSE_DEV = Path(__file__).resolve().parents[1] / "data" / "verse_dev.csv"


@pytest.fixture()
def dev_folder(tmp_path: Path) -> Path:
    """A VerSe folder holding the dev split the command reads (``dev.csv``)."""
    shutil.copy(VERSE_DEV, tmp_path / "dev.csv")
    return tmp_path


def test_a_profile_with_a_population_prior_draws_only_its_stretch_factor() -> None:
    default, literature = load_profile("default"), load_profile("literature")
    assert calibrate.searched(default) == ("stretch_factor",)
    assert calibrate.searched(literature) == calibrate.MECHANICAL
    draw = calibrate.sample(default, np.random.default_rng(3), 1.5)
    assert (draw.youngs_modulus_mpa, draw.shear_modulus_mpa) == (default.youngs_modulus_mpa, default.shear_modulus_mpa)
    assert draw.stretch_factor != default.stretch_factor
    free = calibrate.sample(literature, np.random.default_rng(3), 1.5)
    same_factor = draw.stretch_factor / default.stretch_factor
    assert free.stretch_factor / literature.stretch_factor == pytest.approx(same_factor)
    assert free.shear_modulus_mpa != literature.shear_modulus_mpa


def test_refusal_names_the_prior_that_would_be_lost_or_moved() -> None:
    default, literature = load_profile("default"), load_profile("literature")
    assert "would drop" in (calibrate.refusal(literature, default) or "")
    assert "population prior" in (calibrate.refusal(default, None) or "")
    assert calibrate.refusal(literature, None) is None
    assert calibrate.refusal(literature, dataclasses.replace(default, population_prior=None)) is None


@pytest.mark.parametrize(("start", "write"), [("literature", "default"), ("default", "default"), ("default", "x")])
def test_write_refused_leaves_the_profiles_alone(dev_folder: Path, start: str, write: str,
                                                  capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    before = (PROFILES_DIR / "default.json").read_bytes()
    code = calibrate.main(["--data", str(dev_folder), "--start", start, "--write", write, "--samples", "0"])
    assert code == 2
    assert f"--write {write}" in capsys.readouterr().out
    assert (PROFILES_DIR / "default.json").read_bytes() == before
    assert not (PROFILES_DIR / "x.json").exists()


def test_unknown_start_is_an_error(dev_folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert calibrate.main(["--data", str(dev_folder), "--start", "nope"]) == 2
    assert "unknown profile 'nope'" in capsys.readouterr().out


def test_check_scores_the_shipped_stretch_factor_on_both_scores(tmp_path: Path) -> None:
    """``--check`` writes one row per multiplier, the shipped factor's at ×1, each with the paper's
    two errors and the clinic's four cases. On three of dev's spines: what is checked here is the
    table the command writes, whose shape does not depend on how many spines it scores, and all 24
    cost 5 × 144 fits (the shipped profile's clinic score on all 24 is test_shipped_calibrations.py's
    landmark-weight check; its paper errors on eight of them, tests/engine/test_reconstruction.py's)."""
    folder = tmp_path / "verse"
    folder.mkdir()
    header, *rows = VERSE_DEV.read_text().splitlines(keepends=True)
    (folder / "dev.csv").write_text(header + "".join(rows[:3]))
    out = tmp_path / "out"
    assert calibrate.main(["--data", str(folder), "--start", "default", "--check", "--out", str(out)]) == 0
    data = json.loads((out / "calibrate-check.json").read_text())
    assert [r["multiplier"] for r in data["rows"]] == list(calibrate.CHECK_GRID)
    shipped = next(r for r in data["rows"] if r["multiplier"] == 1.0)
    assert shipped["stretch_factor"] == load_profile("default").stretch_factor
    cases = load_profile("default").provenance["noise_calibration"]["cases"]
    for row in data["rows"]:
        assert set(row["clinic_mm"]) == set(cases)
        assert row["clinic_score_mm"] == pytest.approx(np.mean(list(row["clinic_mm"].values())))
        assert row["paper_score_mm"] == pytest.approx(sum(row["paper_mm"].values()))
    assert data["searched"] == ["stretch_factor"]


def test_out_without_check_is_a_usage_error(dev_folder: Path, tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as exc:
        calibrate.main(["--data", str(dev_folder), "--out", str(tmp_path)])
    assert exc.value.code == 2
