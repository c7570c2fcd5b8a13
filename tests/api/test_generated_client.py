"""The published contract serves a client generator: openapi-python-client (a pinned dev dependency)
generates a client from openapi.yaml with no warning, and that client, as generated, submits a job to
the embedded service (API in process, a real worker subprocess), reads a 422 problem's fields, and
downloads the job's figure.png and sr.dcm.

The generator reads JSON bodies (``application/json``, ``+json``) and text (``text/*``) by itself;
the contract's other media types are mapped by its documented ``content_type_overrides`` (README,
"The contract"), the one setting a generator user needs: image/png and application/dicom as bytes,
image/svg+xml as text.
"""

from __future__ import annotations

import importlib
import io
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pydicom
import pytest
import yaml

from tests.conftest import Service, spine_payload

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = "generated_spine_api"
GENERATOR_CONFIG = {
    "post_hooks": [],  # no formatter run over the generated code (none is needed to import it)
    "content_type_overrides": {
        "image/png": "application/octet-stream",
        "application/dicom": "application/octet-stream",
        "image/svg+xml": "text/plain",
    },
}
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"  # PNG (ISO/IEC 15948) §5.2


@pytest.fixture(scope="module")
def generated(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ModuleType]:
    """The client package generated from openapi.yaml, imported; the generator's output is checked
    for warnings (it prints them and still exits 0 unless told to fail on them)."""
    out = tmp_path_factory.mktemp("generated")
    config = out / "config.yaml"
    config.write_text(yaml.safe_dump(GENERATOR_CONFIG))
    run = subprocess.run(
        [sys.executable, "-m", "openapi_python_client", "generate", "--path", str(ROOT / "openapi.yaml"),
         "--meta", "none", "--output-path", str(out / PACKAGE), "--config", str(config), "--fail-on-warning"],
        capture_output=True, text=True, timeout=120, cwd=out,
    )  # fmt: skip
    printed = run.stdout + run.stderr
    assert run.returncode == 0, printed
    assert "warning" not in printed.lower(), printed
    sys.path.insert(0, str(out))
    try:
        yield importlib.import_module(PACKAGE)
    finally:
        sys.path.remove(str(out))
        for name in [n for n in sys.modules if n == PACKAGE or n.startswith(PACKAGE + ".")]:
            del sys.modules[name]


def _module(package: ModuleType, name: str) -> Any:
    return importlib.import_module(f"{package.__name__}.{name}")


def test_a_generated_client_submits_reads_a_problem_and_downloads_artifacts(
    generated: ModuleType, embedded_service: Service
) -> None:
    client_module = _module(generated, "client")
    models = _module(generated, "models")
    submit = _module(generated, "api.jobs.submit_job_v1_jobs_post")
    read = _module(generated, "api.jobs.read_job_v1_jobs_job_id_get")
    png = _module(generated, "api.figures.figure_png_v1_jobs_job_id_figure_png_get")
    sr = _module(generated, "api.dicom.sr_dcm_v1_jobs_job_id_sr_dcm_get")
    # The generated client over the service's own HTTP client (the app in process, its API key set).
    client = client_module.Client(base_url=str(embedded_service.client.base_url))
    client.set_httpx_client(embedded_service.client)

    # a 422: the generated Problem model carries the fields, each with its JSON path (a level given
    # twice: valid for the generated models, which check each landmark alone, refused by the service)
    bad = spine_payload()
    bad["pa"]["landmarks"][3]["level"] = "T3"
    refused = submit.sync_detailed(client=client, body=models.JobPayload.from_dict(bad))
    assert refused.status_code == 422
    problem = refused.parsed
    assert isinstance(problem, models.Problem), refused.content
    assert problem.status == 422 and problem.type_.endswith("/validation-error") and problem.title
    assert [e.path for e in problem.errors] == ["pa.landmarks"] and problem.errors[0].loc == ["pa", "landmarks"]
    assert "T3 is given more than once" in problem.errors[0].msg and "T3" in problem.detail

    # a job: submitted, polled to its end, its figure and SR downloaded as the bytes they are
    accepted = submit.sync(client=client, body=models.JobPayload.from_dict(spine_payload(curve_mm=25.0)))
    assert isinstance(accepted, models.Job), accepted
    deadline = time.monotonic() + 60
    job = read.sync(client=client, job_id=accepted.id)
    while job.status.value not in ("succeeded", "failed", "cancelled") and time.monotonic() < deadline:
        time.sleep(0.1)
        job = read.sync(client=client, job_id=accepted.id)
    assert job.status.value == "succeeded", job
    figure = png.sync(client=client, job_id=accepted.id)
    assert isinstance(figure, _module(generated, "types").File)
    assert figure.payload.read(8) == PNG_SIGNATURE
    report = sr.sync(client=client, job_id=accepted.id)
    dataset = pydicom.dcmread(io.BytesIO(report.payload.read()))
    assert dataset.Modality == "SR" and dataset.ContentSequence
