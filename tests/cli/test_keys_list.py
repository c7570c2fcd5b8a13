"""`spine keys list --format json`: the keys as one JSON array a script reads (the table stays the default),
on the embedded default database of a data dir of the test's own."""

from __future__ import annotations

import json
from datetime import datetime
from pathlib import Path

from tests.cli.operator_cli import spine


def test_keys_list_as_json(tmp_path: Path) -> None:
    for args in (("create", "--name", "ris-a"), ("create", "--name", "ops", "--role", "admin"), ("revoke", "ris-a")):
        assert spine(tmp_path, "keys", *args).returncode == 0
    listed = spine(tmp_path, "keys", "list", "--format", "json")
    assert listed.returncode == 0 and "Traceback" not in listed.stderr
    keys = {k["name"]: k for k in json.loads(listed.stdout)}
    assert set(keys) == {"ris-a", "ops"}
    assert (keys["ops"]["role"], keys["ops"]["revoked_at"]) == ("admin", None)
    assert keys["ris-a"]["role"] == "client" and keys["ris-a"]["revoked_at"] is not None
    for key in keys.values():
        assert set(key) == {"id", "name", "role", "created_at", "revoked_at"}
        datetime.fromisoformat(key["created_at"])
    table = spine(tmp_path, "keys", "list")
    assert table.returncode == 0
    assert table.stdout.splitlines()[0].split() == ["id", "name", "role", "created", "revoked"]
