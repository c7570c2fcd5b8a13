"""``spine bench perf --clinic``: register() timed on the payloads of ``spine bench clinic``'s cases."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benches import perf


def test_clinic_payloads_are_the_clinic_cases_without_boundary() -> None:
    """Case (a): a PA and a full lateral film per VerSe dev spine, no T1/L5; case (e): the PA only."""
    both = perf.clinic_payloads("a")
    assert len(both) == 24
    assert all(p.get("boundary") is None and p["lateral"] and len(p["pa"]["landmarks"]) == 17 for p in both)
    assert all(p.get("lateral") is None for p in perf.clinic_payloads("e"))


def test_command_times_the_clinic_cases(tmp_path: Path) -> None:
    """``--clinic ae`` adds one row per case with the whole call's and the fit's medians; an unknown
    case is refused by argparse (exit 2)."""
    out = tmp_path / "perf.json"
    assert perf.main(["--repeats", "3", "--clinic", "ae", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["results"]
    clinic = [r for r in rows if "clinic" in r["problem"]]
    assert [r["problem"].split("(")[2][0] for r in clinic] == ["a", "e"]
    assert all(r["register_total"]["median_ms"] >= r["initial_plus_fit"]["median_ms"] > 0 for r in clinic)
    with pytest.raises(SystemExit) as exc:
        perf.main(["--repeats", "3", "--clinic", "z"])
    assert exc.value.code == 2
