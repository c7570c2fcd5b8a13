"""Reading an SR as OHIF does, in Node: ``tests/node/read_sr.mjs`` runs ``@cornerstonejs/adapters``'
``MeasurementReport.generateToolState`` (the versions pinned in ``tests/node/package.json``, installed
by ``make node-deps``: ``npm ci``). Used by the DICOM tests and ``tools/cobb_adapter_figure.py``."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

NODE_DIR = Path(__file__).resolve().parents[1] / "tests" / "node"


def adapter_missing() -> str | None:
    """Why the adapter cannot run here (no ``node``, or ``make node-deps`` not run), or None."""
    if shutil.which("node") is None:
        return "node is not installed (Debian's nodejs)"
    if not (NODE_DIR / "node_modules" / "@cornerstonejs" / "adapters").is_dir():
        return "tests/node/node_modules is missing: run `make node-deps` (npm ci in tests/node)"
    return None


def adapter_tool_state(sr_path: Path, sop_instance_uid: str, spacing: tuple[float, float]) -> dict[str, Any]:
    """``{"CobbAngle": [{"angle", "points" (world mm), "imagePoints" (column, row), ...}], "tools": {type: n}}``
    as the adapter reads ``sr_path``, the image ``sop_instance_uid`` given the [row, column] ``spacing``."""
    run = subprocess.run(
        ["node", "read_sr.mjs", str(sr_path), sop_instance_uid, str(spacing[0]), str(spacing[1])],
        cwd=NODE_DIR, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    if run.returncode != 0:
        raise RuntimeError(f"read_sr.mjs failed ({run.returncode}):\n{run.stderr[-3000:]}")
    result: dict[str, Any] = json.loads(run.stdout)
    return result
