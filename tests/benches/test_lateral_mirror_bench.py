"""``spine bench lateral-mirror`` on three VerSe dev spines (``tests/data/verse_dev.csv``, CC BY-SA 4.0,
credited in ``tests/data/README.md``): the JSON fields docs/engine.md reads, each checked as an identity
with the other fields or with the engine (no bound copied from a run)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benches import lateral_mirror
from spine_engine.frames import frames_from_centreline
from spine_engine.measures import kyphosis_lordosis_deg

VERSE_DEV = Path(__file__).resolve().parents[1] / "data" / "verse_dev.csv"


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    folder = tmp_path_factory.mktemp("verse")
    lines = VERSE_DEV.read_text().splitlines()
    (folder / "dev.csv").write_text("\n".join(lines[:4]) + "\n")
    out = tmp_path_factory.mktemp("out")
    assert lateral_mirror.main(["--data", str(folder), "--seeds", "1", "--synthetic", "0", "--out", str(out)]) == 0
    return json.loads((out / "lateral-mirror.json").read_text())


def test_sweep_counts_every_payload_and_both_mirrors_agree(report: dict[str, Any]) -> None:
    """Per noise SD: 3 spines × 7 lateral cases × 1 seed × 2 forms payloads, none refused as inverted (the
    command exits 0); the two mirrors (labels swapped, columns flipped) read the same depths negated, so
    they are refused alike; the per-form rates average to the whole."""
    assert list(report["sweep"]) == ["verse-dev"]
    for noise, row in report["sweep"]["verse-dev"].items():
        assert row["stated"]["payloads"] == 3 * len(lateral_mirror.LATERAL_CASES) * 2, noise
        assert row["stated"]["refused_inverted"] == 0 and row["stated"]["refused_payloads"] == []
        assert row["detection_rate_labels"] == row["detection_rate_columns"]
        forms = row["detection_rate_labels_per_form"]
        assert row["detection_rate_labels"] == pytest.approx(0.5 * (forms["all_levels"] + forms["levels_left_out"]))


def test_population_is_the_engines_measure_and_the_checks_reading(report: dict[str, Any]) -> None:
    """``population.verse-dev.spines``: kyphosis and lordosis of ``measures.kyphosis_lordosis_deg`` on the
    centreline's frames, and the summaries their min / max."""
    rows = report["population"]["verse-dev"]["spines"]
    for line, row in zip(VERSE_DEV.read_text().splitlines()[1:4], rows, strict=True):
        cells = line.split(",")
        assert row["spine"] == cells[0]
        positions = np.array(cells[1:], dtype=float).reshape(-1, 3)
        k4, _, lo = kyphosis_lordosis_deg(frames_from_centreline(positions))
        assert row["kyphosis_t4_t12_deg"] == pytest.approx(k4) and row["lordosis_l1_l5_deg"] == pytest.approx(lo)
    summary = report["population"]["verse-dev"]["reading_minus_kyphosis_deg"]
    diffs = [r["reading_kyphosis_deg"] - r["kyphosis_t4_t12_deg"] for r in rows]
    assert (summary["min"], summary["max"]) == pytest.approx((min(diffs), max(diffs)))
