"""`spine migrate` and `spine keys …` on settings or a database they cannot use: one plain line
naming the problem and what to do, no traceback, and the exit code of its kind (3 settings, 4
database unreachable, 5 schema not at the code's revision). Real PostgreSQL: an empty database of
the test's own, one that does not exist, a closed port, one migrated by a "newer release"."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from sqlalchemy import create_engine, text

from services.core.config import Settings
from services.db.migrate import upgrade
from tests.cli.operator_cli import spine


def one_line(done: subprocess.CompletedProcess[str], code: int, *words: str) -> str:
    assert done.returncode == code, (done.returncode, done.stderr)
    assert "Traceback" not in done.stderr, done.stderr
    # one line, after any of Alembic's progress lines (`spine migrate`)
    [line] = [line for line in done.stderr.strip().splitlines() if not line.startswith("INFO  [alembic")]
    assert line.startswith("spine "), line
    for word in words:
        assert word in line, (word, line)
    return line


def closed_port_url(fresh_postgres_url: str) -> str:
    return fresh_postgres_url.replace("127.0.0.1:5432", "127.0.0.1:1")


@pytest.mark.parametrize("command", [("migrate",), ("keys", "list"), ("keys", "create", "--name", "x")])
def test_an_unreachable_or_missing_database(tmp_path: Path, fresh_postgres_url: str, command: tuple[str, ...]) -> None:
    prefix = f"spine {' '.join(command[:2] if command[0] == 'keys' else command[:1])}: "
    refused = one_line(spine(tmp_path, *command, DATABASE_URL=closed_port_url(fresh_postgres_url)), 4,
                       "Connection refused", "check DATABASE_URL")  # fmt: skip
    assert refused.startswith(prefix)
    missing = fresh_postgres_url.rsplit("/", 1)[0] + "/spine_test_no_such_database"
    one_line(spine(tmp_path, *command, DATABASE_URL=missing), 4, "does not exist", "createdb")


def test_a_password_is_never_printed(tmp_path: Path, fresh_postgres_url: str) -> None:
    with_password = closed_port_url(fresh_postgres_url).replace("://postgres@", "://postgres:hunter2@")
    line = one_line(spine(tmp_path, "keys", "list", DATABASE_URL=with_password), 4)
    assert "hunter2" not in line and "postgres:***@" in line


@pytest.mark.parametrize("url", ["notaurl", "foo://host/db"])
def test_a_database_url_that_is_not_one(tmp_path: Path, url: str) -> None:
    one_line(spine(tmp_path, "migrate", DATABASE_URL=url), 3, "DATABASE_URL is not a database URL")


def test_invalid_settings(tmp_path: Path) -> None:
    one_line(spine(tmp_path, "keys", "list", SPINE_WEBHOOK_TIMEOUT_S="-1"), 3, "SPINE_WEBHOOK_TIMEOUT_S")


@pytest.mark.parametrize("command", [("keys", "list"), ("keys", "create", "--name", "x"), ("keys", "revoke", "x")])
def test_a_database_not_migrated(tmp_path: Path, fresh_postgres_url: str, command: tuple[str, ...]) -> None:
    one_line(spine(tmp_path, *command, DATABASE_URL=fresh_postgres_url), 5, "not migrated", "run `spine migrate`")


def test_a_database_migrated_by_a_newer_release(tmp_path: Path, fresh_postgres_url: str) -> None:
    upgrade(Settings(DATABASE_URL=fresh_postgres_url, data_dir=tmp_path), quiet=True)
    engine = create_engine(fresh_postgres_url)
    with engine.begin() as connection:
        connection.execute(text("UPDATE alembic_version SET version_num = '0099_from_the_future'"))
    engine.dispose()
    one_line(spine(tmp_path, "migrate", DATABASE_URL=fresh_postgres_url), 5, "newer release", "0099_from_the_future")
