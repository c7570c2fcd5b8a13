"""What an operator command (``spine migrate``, ``spine keys …``, ``spine serve``, ``spine worker``) says
when the settings or the database are not usable: one plain line naming the problem and what to do,
and an exit code per kind of problem, instead of a Python traceback.

Exit codes (documented in docs/security.md):

- 1: the command's own failure (e.g. no key with that id or name);
- 2: usage error (bad arguments, a malformed key name, a name of the other role);
- 3: the settings are not valid (``DATABASE_URL`` that does not parse, a setting out of range);
- 4: the database is unreachable (server down, database missing, login refused);
- 5: the database's schema does not match the code: not migrated (run ``spine migrate``), or
  migrated by a newer release;
- 130: interrupted by Ctrl-C; 141: stdout's reader closed it (``| head -1``).
"""

from __future__ import annotations

from alembic.util import CommandError
from pydantic import ValidationError
from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError, DBAPIError, InterfaceError, OperationalError

from services.core.retry import schema_not_migrated

EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_SETTINGS = 3
EXIT_DATABASE_UNREACHABLE = 4
EXIT_SCHEMA = 5


def database_name(url: str | None) -> str:
    """The database URL as an operator may see it: the password hidden; "the database" when unparsable."""
    if not url:
        return "the database"
    try:
        return make_url(url).render_as_string(hide_password=True)
    except ArgumentError:
        return "the database"


def _variable(loc: tuple[int | str, ...]) -> str:
    """The environment variable of a setting's error location (``webhook_timeout_s``: ``SPINE_WEBHOOK_TIMEOUT_S``)."""
    name = str(loc[0]) if loc else "settings"
    return f"SPINE_{name.upper()}" if name.islower() else name


def _first_line(exc: BaseException) -> str:
    orig = exc.orig if isinstance(exc, DBAPIError) and exc.orig is not None else exc
    return (str(orig).strip().splitlines() or [type(orig).__name__])[0]


def explain(exc: BaseException, database_url: str | None = None) -> tuple[int, str] | None:
    """The exit code and plain line of an operator's configuration or database problem; None for
    anything else (a bug: its traceback is kept)."""
    where = database_name(database_url)
    if isinstance(exc, ValidationError):
        fields = "; ".join(f"{_variable(e['loc'])}: {e['msg']}" for e in exc.errors())
        return EXIT_SETTINGS, f"the settings are not valid: {fields}"
    if isinstance(exc, ArgumentError):
        return EXIT_SETTINGS, (
            f"DATABASE_URL is not a database URL this service can use ({exc}): give one such as "
            "postgresql+psycopg://USER@HOST:5432/DATABASE, or unset it for the embedded SQLite database"
        )
    if isinstance(exc, CommandError) and "Can't locate revision" in str(exc):
        return EXIT_SCHEMA, (
            f"the schema of {where} was migrated by a newer release of the service ({exc}): run that release, "
            "or point DATABASE_URL at a database of this one"
        )
    if schema_not_migrated(exc):
        return EXIT_SCHEMA, f"{where} is not migrated to this version of the service: run `spine migrate`"
    if isinstance(exc, (OperationalError, InterfaceError)):
        reason = _first_line(exc)
        if 'database "' in reason and "does not exist" in reason:
            todo = "create it (e.g. `createdb`) or fix DATABASE_URL, then run `spine migrate`"
        elif 'role "' in reason or "password" in reason or "authentication" in reason:
            todo = "check the user and password in DATABASE_URL"
        else:
            todo = "check DATABASE_URL and that the database server is running"
        return EXIT_DATABASE_UNREACHABLE, f"cannot use {where}: {reason}; {todo}"
    return None
