"""openapi.yaml at the repository root is exactly what `spine openapi` prints."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import yaml

from services.cli.service_commands import openapi_yaml

ROOT = Path(__file__).resolve().parents[2]


def test_openapi_yaml_matches_the_app() -> None:
    published = (ROOT / "openapi.yaml").read_text()
    assert openapi_yaml() == published, "openapi.yaml is stale: run `make openapi` and commit it"


def test_spine_openapi_prints_it(tmp_path: Path) -> None:
    # From the repository under test (not whatever checkout the venv was installed from).
    env = {**os.environ, "SPINE_DATA_DIR": str(tmp_path)}
    out = subprocess.run(
        [sys.executable, "-m", "services.cli", "openapi"],
        capture_output=True, text=True, check=True, cwd=ROOT, env=env, timeout=60,
    )  # fmt: skip
    assert out.stdout == (ROOT / "openapi.yaml").read_text()


def test_contract_shape() -> None:
    schema = yaml.safe_load((ROOT / "openapi.yaml").read_text())
    paths = schema["paths"]
    assert {"/v1/jobs", "/v1/jobs/batch", "/v1/jobs/{job_id}", "/v1/jobs/{job_id}/cancel",
            "/healthz", "/readyz", "/metrics"} <= paths.keys()  # fmt: skip
    body = paths["/v1/jobs"]["post"]["requestBody"]["content"]["application/json"]["schema"]
    assert body == {"$ref": "#/components/schemas/JobPayload"}
    components = schema["components"]["schemas"]
    assert {"JobPayload", "PAView", "Boundary", "Pose", "RegistrationResult", "Job", "Problem"} <= components.keys()
    assert "application/problem+json" in paths["/v1/jobs"]["post"]["responses"]["422"]["content"]


def test_readyz_documents_the_schema_check_and_what_to_do() -> None:
    """/readyz is not ready when the database's schema is not at the code's Alembic head, and its 503
    then says to run `spine migrate`: the contract said only "the database and the broker are reachable"."""
    readyz = yaml.safe_load((ROOT / "openapi.yaml").read_text())["paths"]["/readyz"]["get"]
    assert "schema" in readyz["summary"]
    assert "Alembic head" in readyz["description"] and "spine migrate" in readyz["description"]
    unready = readyz["responses"]["503"]
    assert "spine migrate" in unready["description"] and set(unready["headers"]) == {"Retry-After"}
    assert unready["content"]["application/problem+json"]["schema"] == {"$ref": "#/components/schemas/Problem"}
