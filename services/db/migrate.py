"""Apply the Alembic migrations in ``migrations/`` to the service's database."""

from __future__ import annotations

import logging
from pathlib import Path

from alembic import command
from alembic.config import Config

import migrations
from services.core.config import Settings

ALEMBIC_INI = Path(next(iter(migrations.__path__))) / "alembic.ini"


def alembic_config(settings: Settings, quiet: bool = False) -> Config:
    settings.ensure_data_dir()
    config = Config(str(ALEMBIC_INI))
    if quiet:
        config.attributes["configure_logging"] = False
    config.set_main_option("script_location", str(ALEMBIC_INI.parent))
    config.set_main_option("sqlalchemy.url", settings.sqlalchemy_url.replace("%", "%%"))
    return config


def upgrade(settings: Settings, revision: str = "head", *, quiet: bool = False) -> None:
    """Migrate to ``revision``; ``quiet`` leaves the caller's logging alone."""
    if quiet:
        logging.getLogger("alembic").setLevel(logging.WARNING)
    command.upgrade(alembic_config(settings, quiet), revision)


def downgrade(settings: Settings, revision: str) -> None:
    command.downgrade(alembic_config(settings), revision)
