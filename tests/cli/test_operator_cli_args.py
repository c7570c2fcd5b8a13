"""`spine serve`'s numbers out of range are usage errors (exit 2) naming the option, before anything
starts: a `--port` beyond TCP's 16 bits (RFC 9293 §3.1) was handed to uvicorn, which announced
"running on http://127.0.0.1:99999" and served nothing a client could reach."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(("option", "value", "says"), [
    ("--port", "99999", "must be a port number from 1 to 65535, not 99999"),
    ("--port", "0", "must be a port number from 1 to 65535, not 0"),
    ("--port", "http", "must be a port number from 1 to 65535, not 'http'"),
    ("--workers", "0", "must be 1 or more, not 0"),
])  # fmt: skip
def test_serve_refuses_numbers_out_of_range(option: str, value: str, says: str, tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("DATABASE_URL", "CELERY_BROKER_URL")}
    env["SPINE_DATA_DIR"] = str(tmp_path)
    # 60 s: a `spine serve` that starts instead never ends by itself; the refusal takes one start-up (~2 s)
    done = subprocess.run([sys.executable, "-m", "services.cli", "serve", "--no-worker", option, value], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 2, done.stderr[-2000:]
    assert done.stderr.splitlines()[-1] == f"spine serve: error: argument {option}: {says}"
    assert not (tmp_path / "spine.db").exists()  # nothing started: not even the embedded database
