"""The Python client installs alone: ``pip install ./spine_client`` into a bare venv (no system site
packages, not the project's venv) brings httpx and pydantic only, its import loads neither the engine,
nor the service, nor numba/scipy, and its ``spine submit`` runs a job on a real ``spine serve``."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.cli.test_service_cli import Serve
from tests.conftest import spine_payload

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
FORBIDDEN = ("spine_engine", "services", "benches", "numba", "scipy", "numpy", "pydicom", "rich", "tenacity")
"""Top-level modules a script importing the client must not load: the engine and the service (the
House rules of DESIGN.md), their heavy dependencies, and the client's optional ones."""
IMPORTS = """
import importlib.metadata, json, sys
import spine_client, spine_client.cli, spine_client.client, spine_client.models
print(json.dumps({"modules": sorted({m.split(".")[0] for m in sys.modules}),
                  "requires": importlib.metadata.requires("spine-client"),
                  "version": importlib.metadata.version("spine-client")}))
"""


def test_client_installs_alone_and_submits_to_the_service(tmp_path: Path) -> None:
    started = time.monotonic()
    # a copy, so that pip's in-tree build writes nothing into the repository
    source = tmp_path / "spine_client"
    shutil.copytree(ROOT / "spine_client", source, ignore=shutil.ignore_patterns("__pycache__", "build", "*.egg-info"))
    venv = tmp_path / "venv"
    # bare: no pip either (ensurepip copies pip and setuptools into it, seconds of work); this venv's pip
    # installs into it (--python: pip runs under the venv's interpreter, as the venv's own pip would)
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python, spine = venv / "bin" / "python", venv / "bin" / "spine"
    # with the project's constraints, as `make install`: httpx's and pydantic's own dependencies at the
    # versions the suite runs with
    install = subprocess.Popen([sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet",
                                "-c", str(ROOT / "constraints.txt"), str(source)],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)  # fmt: skip
    (tmp_path / "data").mkdir()
    serve = Serve(tmp_path / "data")  # started while pip installs
    try:
        out, _ = install.communicate(timeout=120)
        assert install.returncode == 0, out

        probe = subprocess.run([str(python), "-c", IMPORTS], capture_output=True, text=True, cwd=tmp_path)
        assert probe.returncode == 0, probe.stderr
        loaded = json.loads(probe.stdout)
        assert not set(FORBIDDEN) & set(loaded["modules"]), set(FORBIDDEN) & set(loaded["modules"])
        required = {r.split("==")[0] for r in loaded["requires"] if "extra ==" not in r}
        assert required == {"httpx", "pydantic"}, loaded["requires"]
        # the installed command's version is the installed package's (spine_client/pyproject.toml)
        shown = subprocess.run([str(spine), "--version"], capture_output=True, text=True, cwd=tmp_path)
        assert (shown.returncode, shown.stdout) == (0, f"spine {loaded['version']}\n"), shown.stderr

        (tmp_path / "payload.json").write_text(json.dumps(spine_payload()), encoding="utf-8")
        argv = ["--url", serve.base, "--api-key", serve.api_key]
        done = subprocess.run([str(spine), "submit", str(tmp_path / "payload.json"), "--timeout", "60", *argv],
                              capture_output=True, text=True, cwd=tmp_path)  # fmt: skip
        assert done.returncode == 0, done.stderr + serve.text()[-3000:]
        job = json.loads(done.stdout)
        assert job["status"] == "succeeded" and len(job["result"]["vertebrae"]) == 17

        # without the [dicom] extra, --pa-dicom says which extra reads DICOM files (exit 2: usage)
        (tmp_path / "landmarks.csv").write_text("T1,1,2\n", encoding="utf-8")
        refused = subprocess.run([str(spine), "submit", "--pa-dicom", str(tmp_path / "pa.dcm"),
                                  str(tmp_path / "landmarks.csv"), *argv], capture_output=True, text=True)  # fmt: skip
        assert refused.returncode == 2 and "spine-client[dicom]" in refused.stderr, refused.stderr
    finally:
        if install.poll() is None:
            install.kill()
        serve.interrupt()
    print(f"client installed alone and ran a job in {time.monotonic() - started:.1f} s")
