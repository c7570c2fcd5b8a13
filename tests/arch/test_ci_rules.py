"""CI cannot pass without its back ends: with CI=true (as .ci/run sets it) a skipped test
is a failure, naming why it skipped; on a developer's machine it stays a skip."""

from __future__ import annotations

import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PROBE = '''
import pytest


def test_needs_a_back_end():
    pytest.skip("PostgreSQL unreachable at postgresql://127.0.0.1:1/test: connection refused")
'''


def _run(tmp_path: Path, **env: str) -> subprocess.CompletedProcess[str]:
    probe = tmp_path / "test_probe.py"
    probe.write_text(PROBE)
    base = {k: v for k, v in os.environ.items() if k not in ("CI", "SPINE_REQUIRE_BACKENDS")}
    # -p tests.conftest: the project's hooks, loaded as a plugin for a test outside tests/.
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "tests.conftest", "-p", "no:cacheprovider",
                           str(probe)], cwd=ROOT, env={**base, **env}, capture_output=True, text=True,
                          timeout=120)  # fmt: skip


def test_a_skip_fails_in_ci(tmp_path: Path) -> None:
    run = _run(tmp_path, CI="true")
    assert run.returncode == 1, run.stdout[-2000:]
    assert "1 failed" in run.stdout and "skipped where every back end must be present" in run.stdout
    assert "PostgreSQL unreachable" in run.stdout


def test_a_skip_stays_a_skip_on_a_developers_machine(tmp_path: Path) -> None:
    run = _run(tmp_path)
    assert run.returncode == 0 and "1 skipped" in run.stdout, run.stdout[-2000:]


def test_ci_script_fails_on_skips_and_on_no_tests() -> None:
    script = (ROOT / ".ci" / "run").read_text()
    assert "SPINE_REQUIRE_BACKENDS=1" in script and "skipped" in script and "no tests ran" in script


def _makefile_serial_files() -> set[str]:
    """The test files ``make test`` runs in a serial pytest of their own (``FUZZ :=`` in the Makefile)."""
    for line in (ROOT / "Makefile").read_text().splitlines():
        if line.startswith("FUZZ :="):
            return set(line.split(":=", 1)[1].split())
    return set()


def test_no_two_tests_share_a_node_id_where_xdist_runs_them(request: pytest.FixtureRequest) -> None:
    """pytest-xdist runs and reports a group of tests sharing a node id once: the others vanish without
    a word (schemathesis's 17 operations did, 762 of 778 tests reported). Such tests live only in the
    files ``make test`` runs serially, and the parallel run has none."""
    counts = Counter(item.nodeid for item in request.session.items)
    shared = sorted(nodeid for nodeid, n in counts.items() if n > 1)
    assert {nodeid.split("::")[0] for nodeid in shared} <= _makefile_serial_files(), shared
    if os.environ.get("PYTEST_XDIST_WORKER"):
        assert not shared, shared
