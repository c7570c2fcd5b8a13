"""Alembic migrations of the service's database; they run on SQLite and PostgreSQL alike."""
