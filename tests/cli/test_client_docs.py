"""docs/client.md documents every command of the client CLI with every one of its options: the
command table is what a newcomer reads instead of ``--help`` (README: "every command and its options")."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from spine_client import tables
from spine_client.cli import build_parser

CLIENT_DOC = Path(__file__).resolve().parents[2] / "docs" / "client.md"
COMMON = {"--url", "--api-key", "--retries", "--request-timeout", "-h", "--help"}
"""Options every subcommand shares, documented once above the table."""


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def _table_rows(command: str) -> str:
    """The command table's rows of ``spine COMMAND`` (their first cells), joined."""
    rows = re.findall(rf"^\| `spine {re.escape(command)} ([^`]*)`", CLIENT_DOC.read_text(), flags=re.M)
    return " ".join(rows)


@pytest.mark.parametrize("command", sorted(_subcommands()))
def test_the_command_table_names_every_option(command: str) -> None:
    documented = _table_rows(command)
    assert documented or command in {"cancel", "fhir"}, f"no row for spine {command} in docs/client.md"
    options = {s for a in _subcommands()[command]._actions for s in a.option_strings if s.startswith("--")}
    missing = sorted(o for o in options - COMMON if not re.search(rf"{re.escape(o)}\b", documented))
    assert not missing, f"docs/client.md's row of spine {command} does not name {missing}"


def test_the_common_options_are_documented_once() -> None:
    text = CLIENT_DOC.read_text()
    assert all(f"`{o}" in text for o in ("--url", "--api-key", "--retries", "--request-timeout"))


def _bullet(starts: str) -> str:
    """The CSV formats' bullet of docs/client.md that starts with ``starts``, up to the next one."""
    text = CLIENT_DOC.read_text()
    start = text.index(f"- {starts}")
    end = text.find("\n- ", start + 1)
    return " ".join(text[start : end if end > 0 else None].split())


def test_the_measure_rows_a_model_estimate_marks_are_those_documented() -> None:
    """docs/client.md's list of the `--measures` rows that get `model_estimate` left out `cobb_angle`,
    which `fit.unreliable` `cobb` marks. A result (fed to ``tables.measure_rows``, no service) whose
    ``fit.unreliable`` lists every quantity docs/measures.md's table has: each row it marks is named in
    the sentence, and a row it leaves unmarked is not among them."""
    curve = {"upper": "T5", "lower": "T12", "apex": "T9", "convexity": "right", "major": True, "angle_deg": 30.0,
             "angle_sd_deg": 3.0, "apex_axial_rotation_deg": -8.0, "plane_of_max_curvature_deg": 20.0,
             "max_curvature_deg": 31.0}  # fmt: skip
    largest = {"upper": "T5", "lower": "T12", "angle_deg": 8.0, "reported_as_curve": False}
    measures = {"cobb": [curve], "largest_cobb": largest, "thoracic_kyphosis_t4_t12_deg": 30.0,
                "thoracic_kyphosis_t5_t12_deg": 28.0, "lumbar_lordosis_l1_l5_deg": 40.0}  # fmt: skip
    every = ["scale", "depth", "kyphosis", "lordosis", "plane_of_max_curvature", "axial_rotation", "twist", "cobb"]
    fit = {"mean_registration_error_mm": 0.5, "landmark_misfit_ratio": 1.3, "unreliable": every}
    result = {"vertebrae": [], "measures": measures, "fit": fit}
    rows = tables.measure_rows(result)
    marked = {r["measure"] for r in rows if r.get("model_estimate")}
    unmarked = {r["measure"] for r in rows} - marked
    assert "cobb_angle" in marked and unmarked == {"mean_registration_error", "landmark_misfit_ratio"}
    bullet = _bullet("`spine get ID --measures` (a separate table")
    start = bullet.index("`model_estimate` is `model estimate`")
    sentence = bullet[start : bullet.index("else empty", start)]
    named = set(re.findall(r"`([a-z0-9_]+)`", sentence))
    assert marked <= named, f"docs/client.md does not name {sorted(marked - named)} among the marked rows"
    assert not unmarked & named, sentence


def test_the_csv_columns_and_marks_are_those_documented() -> None:
    """The column lists of `spine list --format csv` and summary.csv, and the vertebra columns each
    `fit.unreliable` quantity marks, read as docs/client.md gives them."""
    text = " ".join(CLIENT_DOC.read_text().split())
    assert f"`{','.join(tables.LIST_COLUMNS)}`" in text
    assert f"`{','.join(tables.SUMMARY_COLUMNS)}`" in text
    vertebrae = _bullet("`spine get ID --format csv`")
    for quantity, columns in tables.MODEL_COLUMNS.items():
        assert f"`{';'.join(columns)}`" in vertebrae, (quantity, columns)
