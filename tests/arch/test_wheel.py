"""The wheel ships the science and the service only (DESIGN.md "House rules"): built from a copy of the
sources, it holds ``spine_engine/`` (with its profiles and priors) and ``services/``, and no bench,
test or tool (the DICOM test kit included: ``tools/dicom``). The benches run from a source checkout
(``spine bench``, README "Benches")."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SOURCES = ("pyproject.toml", "README.md", "spine_engine", "services", "spine_client", "migrations", "benches",
           "tests", "tools")  # fmt: skip
"""What the build sees: the packaged folders and, to prove they are left out, the benches, tests and tools."""


def _wheel_names(tmp_path: Path) -> list[str]:
    src = tmp_path / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "build", "node_modules", "*.pyc")
    for name in SOURCES:
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=ignore)
        else:
            shutil.copy2(path, src / name)
    out = tmp_path / "wheels"
    command = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-cache-dir", "-q"]
    run = subprocess.run([*command, "-w", str(out), str(src)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    (wheel,) = out.glob("spine_reconstruction-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        return archive.namelist()


def test_the_wheel_ships_the_engine_and_the_service_without_the_benches(tmp_path: Path) -> None:
    names = _wheel_names(tmp_path)
    tops = {n.split("/", 1)[0] for n in names if "/" in n}
    assert {"spine_engine", "services", "spine_client", "migrations"} <= tops
    assert "spine_engine/reconstruction.py" in names
    assert "spine_engine/profiles/default.json" in names and "spine_engine/priors/tilt_aasce2019.json" in names
    assert not tops & {"benches", "tests", "tools"}
    assert [n for n in names if n.startswith("spine_engine/experiments")] == []
    kit = ("services/dicom/synthetic.py", "services/dicom/orthanc.py", "services/dicom/bench.py")
    assert not set(kit) & set(names)  # the DICOM test and bench kit is in tools/dicom
