"""The ``spine`` command: serve, worker, migrate, openapi, loadtest, bench; submit, get, list… (client).

``main`` hands a client command (``client_commands.CLIENT_COMMANDS``) to the client (``spine_client.cli``:
httpx and its models) and every other to the service's commands (``service_commands``: SQLAlchemy,
alembic, psycopg, Celery), each loaded only for its own commands, so that a script's client command
costs what the client alone costs (docs/client.md).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from services.cli.client_commands import CLIENT_COMMANDS


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``spine`` with ``argv`` (default: the process's arguments); return its exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in CLIENT_COMMANDS:
        from spine_client.cli import main as client_main  # lazy: the client (httpx, its models) only for its commands

        return client_main(argv)
    from services.cli.service_commands import main as service_main  # lazy: not for a client command

    return service_main(argv)
