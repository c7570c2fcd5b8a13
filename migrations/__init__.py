"""Alembic migrations of the job store; they run on SQLite and PostgreSQL alike."""
