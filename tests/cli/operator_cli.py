"""`spine` (the operator's command, services.cli) run in the test's process for the CLI tests."""

from __future__ import annotations

import os
import subprocess
from contextlib import redirect_stderr, redirect_stdout
from io import StringIO
from pathlib import Path
from unittest import mock

from services.cli import main as spine_main
from services.core.config import get_settings


def spine(tmp_path: Path, *args: str, **env: str) -> subprocess.CompletedProcess[str]:
    """``spine <args>`` in this process with ``env`` (e.g. DATABASE_URL) on top of a clean environment."""
    clean = {k: v for k, v in os.environ.items() if k not in ("DATABASE_URL", "CELERY_BROKER_URL")}
    out, err = StringIO(), StringIO()
    with mock.patch.dict(os.environ, {**clean, "SPINE_DATA_DIR": str(tmp_path), **env}, clear=True), \
            redirect_stdout(out), redirect_stderr(err):  # fmt: skip
        get_settings.cache_clear()
        try:
            code = spine_main(list(args))
        finally:
            get_settings.cache_clear()
    return subprocess.CompletedProcess(["spine", *args], code, out.getvalue(), err.getvalue())
