"""Storage of jobs: SQLAlchemy models, engine and the job repository."""
