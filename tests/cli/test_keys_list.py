"""`spine keys list --format json`: the keys as one JSON array a script reads (the table stays the default),
on the embedded default database of a data dir of the test's own."""

from __future__ import annotations

import json
import os
from contextlib import redirect_stderr, redirect_stdout
from datetime import datetime
from io import StringIO
from pathlib import Path
from unittest import mock

from services.cli import main as spine_main
from services.core.config import get_settings


def _spine(tmp_path: Path, *args: str) -> tuple[int, str]:
    clean = {k: v for k, v in os.environ.items() if k not in ("DATABASE_URL", "CELERY_BROKER_URL")}
    out, err = StringIO(), StringIO()
    with mock.patch.dict(os.environ, {**clean, "SPINE_DATA_DIR": str(tmp_path)}, clear=True), \
            redirect_stdout(out), redirect_stderr(err):  # fmt: skip
        get_settings.cache_clear()
        try:
            code = spine_main(list(args))
        finally:
            get_settings.cache_clear()
    assert "Traceback" not in err.getvalue(), err.getvalue()
    return code, out.getvalue()


def test_keys_list_as_json(tmp_path: Path) -> None:
    assert _spine(tmp_path, "keys", "create", "--name", "ris-a")[0] == 0
    assert _spine(tmp_path, "keys", "create", "--name", "ops", "--role", "admin")[0] == 0
    assert _spine(tmp_path, "keys", "revoke", "ris-a")[0] == 0
    code, out = _spine(tmp_path, "keys", "list", "--format", "json")
    assert code == 0
    keys = {k["name"]: k for k in json.loads(out)}
    assert set(keys) == {"ris-a", "ops"}
    assert (keys["ops"]["role"], keys["ops"]["revoked_at"]) == ("admin", None)
    assert keys["ris-a"]["role"] == "client" and keys["ris-a"]["revoked_at"] is not None
    for key in keys.values():
        assert set(key) == {"id", "name", "role", "created_at", "revoked_at"}
        datetime.fromisoformat(key["created_at"])
    code, table = _spine(tmp_path, "keys", "list")
    assert code == 0 and table.splitlines()[0].split() == ["id", "name", "role", "created", "revoked"]
