"""``spine bench <name> ...`` reaches the benches of the checkout (``benches.cli``), from any working
directory, and says where to run it when the installed package has no benches beside it (a wheel)."""

from __future__ import annotations

import argparse
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

import services.cli.service_commands
from benches.cli import COMMANDS

SPINE = Path(sys.executable).with_name("spine")


def test_every_bench_command_names_a_module_with_a_main() -> None:
    for name, (module, _) in COMMANDS.items():
        assert module.startswith("benches."), name
        assert callable(importlib.import_module(module).main), name


def test_spine_bench_runs_a_bench_outside_the_checkout(tmp_path: Path) -> None:
    """The console script from an unrelated folder: the bench's own argument parser answers."""
    run = subprocess.run([str(SPINE), "bench", "paper", "--help"], cwd=tmp_path, capture_output=True, text=True,
                         timeout=120)  # fmt: skip
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.startswith("usage: spine bench paper") and "--noise-mm" in run.stdout


def test_spine_bench_without_the_checkout_says_where_to_run_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(services.cli.service_commands, "BENCHES_DIR", tmp_path / "site-packages" / "benches")
    assert services.cli.service_commands.cmd_bench(argparse.Namespace(rest=["paper"])) == 2
    err = capsys.readouterr().err
    assert "part of the source repository" in err and "pip install -e ." in err
