"""CI cannot pass without its back ends: with CI=true (as .ci/run sets it) a skipped test
is a failure, naming why it skipped; on a developer's machine it stays a skip."""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PROBE = '''
import pytest


def test_needs_a_back_end():
    pytest.skip("PostgreSQL unreachable at postgresql://127.0.0.1:1/test: connection refused")
'''


def _run(pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch, **env: str) -> pytest.RunResult:
    """pytest on the probe file, in this process (pytester), with the project's hooks loaded as a plugin
    (-p tests.conftest: the file is outside tests/) and ``env`` as the run's environment."""
    for name in ("CI", "SPINE_REQUIRE_BACKENDS"):
        monkeypatch.delenv(name, raising=False)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    pytester.makepyfile(test_probe=PROBE)
    return pytester.runpytest_inprocess("-q", "-p", "tests.conftest", "-p", "no:cacheprovider")


def test_a_skip_fails_in_ci(pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch) -> None:
    run = _run(pytester, monkeypatch, CI="true")
    out = run.stdout.str()
    assert run.ret == 1, out[-2000:]
    assert "1 failed" in out and "skipped where every back end must be present" in out
    assert "PostgreSQL unreachable" in out


def test_a_skip_stays_a_skip_on_a_developers_machine(pytester: pytest.Pytester,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    run = _run(pytester, monkeypatch)
    out = run.stdout.str()
    assert run.ret == 0 and "1 skipped" in out, out[-2000:]


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
