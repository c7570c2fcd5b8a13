"""The bottom layer of the service: settings, logging, problem types, the job queue and its retry policy, job statuses.

Imports nothing else of ``services`` (enforced by the import-linter contract in pyproject.toml)."""
