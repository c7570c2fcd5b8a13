"""docs/client.md documents every command of the client CLI with every one of its options: the
command table is what a newcomer reads instead of ``--help`` (README: "every command and its options")."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

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
