"""Fixtures of the worker's tests: a broker of the test's own, and settings on it."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from services.core.config import Settings
from services.db.migrate import upgrade
from tests.conftest import start_own_redis
from tools.loadbench import OwnRedis


@pytest.fixture
def own_redis(tmp_path: Path) -> Iterator[OwnRedis]:
    """A throwaway redis-server of the test's own (no persistence: a restart loses every message)."""
    own = start_own_redis(tmp_path / "redis")
    yield own
    own.stop()


@pytest.fixture
def own_broker_settings(tmp_path: Path, fresh_postgres_url: str, own_redis: OwnRedis) -> Settings:
    """Settings of a migrated PostgreSQL database of the test's own, with ``own_redis`` as the broker."""
    made = Settings(DATABASE_URL=fresh_postgres_url, CELERY_BROKER_URL=own_redis.url, data_dir=tmp_path)
    upgrade(made, quiet=True)
    return made
