"""Database engines and sessions, one engine per URL and process (safe across fork)."""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, Final, TypeVar

import psycopg
from psycopg.abc import PQGen
from psycopg.connection import _WAIT_INTERVAL
from psycopg.errors import _WaitTimeout
from sqlalchemy import Connection, Engine, create_engine, event, make_url
from sqlalchemy.engine.interfaces import Dialect
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.pool import ConnectionPoolEntry

from services.core.config import Settings, TcpKeepalive

_LOCK = threading.Lock()
_ENGINES: dict[tuple[str, int], tuple[Engine, sessionmaker[Session]]] = {}


PSYCOPG_CACHED_PARAMS = 50
"""The most parameters of a statement whose conversion psycopg caches (``MAX_CACHED_STATEMENT_PARAMS``)."""


class SerializedJSON(str):
    """A JSON document already written (by pydantic's ``model_dump_json``, in Rust): a JSON column
    bound to it stores the text as it is. ``json.dumps`` of a 17 kB result's dict took 0.8 ms of the
    worker's CPU per job, ``model_dump_json`` 0.05 ms (docs/performance.md)."""


def json_dumps(value: Any) -> str:
    """The engines' JSON serializer: a ``SerializedJSON`` as it is, anything else by ``json.dumps``."""
    return value if isinstance(value, SerializedJSON) else json.dumps(value)


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.execute("PRAGMA busy_timeout=30000")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.close()


def sqlite_write_lock(session: Session) -> None:
    """On SQLite, take the database's write lock now, until the session's transaction ends: SQLite has no
    row locks (``FOR UPDATE`` is left out) and one writer at a time, and ``BEGIN IMMEDIATE`` takes the
    write lock at once instead of at the first write ("BEGIN TRANSACTION", sqlite.org/lang_transaction.html),
    so a read and the write that follows run with no other writer in between. Python's sqlite3 driver opens
    a transaction only before an INSERT, UPDATE or DELETE (Python 3.11 docs, sqlite3, "Transaction
    control"): a transaction already open has written, so it holds the lock already. Nothing elsewhere."""
    connection = session.connection()
    if connection.dialect.name != "sqlite":
        return
    if not getattr(connection.connection.dbapi_connection, "in_transaction", False):
        connection.exec_driver_sql("BEGIN IMMEDIATE")


def create_db_engine(url: str, pool_size: int = 10, **postgres_options: Any) -> Engine:
    """An engine for ``url``: WAL and a busy timeout on SQLite, a sized pool on PostgreSQL
    (``postgres_options`` go to ``create_engine`` there, e.g. an isolation level)."""
    if url.startswith("sqlite"):
        engine = create_engine(
            url,
            connect_args={"timeout": 30, "check_same_thread": False},
            hide_parameters=True,
            json_serializer=json_dumps,
        )
        event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    # No pre-ping (a round trip per checkout): after a database restart, a stale pooled
    # connection fails one request (503 problem / task retry) and the pool is refreshed.
    # hide_parameters: a database error never carries a job's payload into the logs.
    engine = create_engine(
        url,
        pool_size=pool_size,
        max_overflow=pool_size,
        hide_parameters=True,
        json_serializer=json_dumps,
        **postgres_options,
    )
    # Many rows inserted at once (a batch's jobs and their audit rows) go as multi-row INSERT …
    # VALUES statements (SQLAlchemy's "insertmanyvalues", as its psycopg2 dialect does by default)
    # instead of one INSERT per row pipelined by psycopg's executemany: the same rows, 25 statements
    # instead of 200 for a batch of 100 jobs and their audit rows. Each statement holds at most
    # PSYCOPG_CACHED_PARAMS parameters (7 job rows, 10 audit rows): psycopg converts a statement's
    # placeholders once and caches the result only up to 50 parameters and 4,096 bytes
    # (``psycopg._queries``); one statement of 100 rows was converted again at every batch, which
    # cost the API process 0.13-0.18 ms a job, more than the 0.05-0.09 the server saved
    # (docs/performance.md). Set before the engine compiles anything (the choice is compiled in).
    engine.dialect.use_insertmanyvalues_wo_returning = True
    engine.dialect.insertmanyvalues_max_parameters = PSYCOPG_CACHED_PARAMS
    return engine


def postgres_connect_args(settings: Settings, *server_settings: str) -> dict[str, Any]:
    """The libpq connection parameters that bound every wait of a PostgreSQL connection of the service
    (PostgreSQL 15 documentation, §34.1.2 "Parameter Key Words"), from the settings:

    - ``connect_timeout`` = ``SPINE_DB_CONNECT_TIMEOUT_S`` (whole seconds; libpq takes 1 as 2): a
      server that does not complete the connection and its authentication in time is an error;
    - ``tcp_user_timeout`` = ``SPINE_DB_TCP_TIMEOUT_S`` in ms: the kernel closes the connection when
      data sent stays unacknowledged that long (a server gone without closing its connections);
    - ``keepalives``: an idle connection is probed after ``idle`` = T/3 s, every ``interval`` = T/6 s,
      and dropped after ``count`` unanswered probes, idle + count·interval ≈ T = ``SPINE_DB_TCP_TIMEOUT_S``
      (``TcpKeepalive.within``; each at least 1 s: libpq takes whole seconds), so that a pooled
      connection whose server vanished is found dead before it is used;
    - ``options`` ``-c statement_timeout=`` ``SPINE_DB_STATEMENT_TIMEOUT_S`` in ms (PostgreSQL 15
      documentation, §20.11.1 "Statement Behavior"; none when 0), then ``server_settings``
      (``name=value``, e.g. ``synchronous_commit=off``).

    A parameter that ``DATABASE_URL``'s query string gives wins (the operator's choice); its
    ``options`` come after these, so that its ``-c`` settings win too.
    """
    tcp_s = settings.db_tcp_timeout_s
    keepalive = TcpKeepalive.within(tcp_s)
    gucs = list(server_settings)
    if settings.db_statement_timeout_s:
        gucs.insert(0, f"statement_timeout={int(settings.db_statement_timeout_s * 1000)}")
    args: dict[str, Any] = {
        "connect_timeout": settings.db_connect_timeout_s,
        "tcp_user_timeout": int(tcp_s * 1000),
        "keepalives": 1,
        "keepalives_idle": keepalive.idle_s,
        "keepalives_interval": keepalive.interval_s,
        "keepalives_count": keepalive.count,
    }
    given = make_url(settings.sqlalchemy_url).query
    options = [f"-c {guc}" for guc in gucs]
    if isinstance(given.get("options"), str):
        options.append(str(given["options"]))
    if options:
        args["options"] = " ".join(options)
    return {name: value for name, value in args.items() if name == "options" or name not in given}


def answer_timeout_s(settings: Settings) -> float | None:
    """The longest the service waits for PostgreSQL's answer on an open connection, in seconds:
    ``SPINE_DB_STATEMENT_TIMEOUT_S + SPINE_DB_TCP_TIMEOUT_S`` (default 30 + 30 = 60 s); None (no bound)
    when the statement timeout is 0 (no limit).

    A statement the server gets ends by the statement timeout (PostgreSQL 15 documentation, §20.11.1
    "Statement Behavior"), and its answer then takes a round trip and, for a commit, the WAL flush, which
    the statement timeout does not count (the server disarms it before committing, ``finish_xact_command``
    in ``postgres.c``). The margin is the stall the service already tolerates from the path at the TCP
    level (``tcp_user_timeout``): an answer later than both is not coming; the path acknowledges and does
    not forward (a hung pooler or proxy), where no libpq parameter ends the wait (§34.1.2 bounds the
    connection, TCP and idle keepalives only)."""
    if not settings.db_statement_timeout_s:
        return None
    return settings.db_statement_timeout_s + settings.db_tcp_timeout_s


class _OwnBound:
    """``AnswerBoundConnection.wait``'s default timeout: the connection's ``answer_timeout_s``."""


_OWN_BOUND: Final = _OwnBound()
_RV = TypeVar("_RV")


class AnswerBoundConnection(psycopg.Connection[Any]):
    """A psycopg connection whose every wait for the server (a statement's execute and results, a commit,
    a rollback) ends after ``answer_timeout_s`` seconds (None: no bound): the connection is then closed
    (``PGconn.finish``: ``closed`` and ``broken``, which SQLAlchemy's psycopg dialect takes for a
    disconnect, so that the pool discards it and the engine's other pooled connections are replaced)
    and the wait is a ``psycopg.OperationalError`` (an ``OperationalError`` past SQLAlchemy: the API's
    503 ``service-unavailable``, a transient fault that the worker retries).

    The bound is psycopg's own: ``Connection.wait``'s ``timeout``, handed to its wait function (the C
    ``wait_c``, a poll() with a deadline), which raises ``_WaitTimeout`` and leaves the connection in an
    unknown state, closed then as psycopg closes a connection whose cancelled query never ends
    (``Connection.wait``; https://github.com/psycopg/psycopg/issues/1371). It runs in the thread that
    waits: no watchdog thread, no race with the connection's next use, nothing per statement but a
    deadline. A cancel request (``cancel_safe(timeout=…)``) would not help: it goes through a new
    connection to the same hung path, and the server never got the statement. ``_WaitTimeout`` and
    ``_WAIT_INTERVAL`` are psycopg's internal names (3.3.9, pinned in pyproject.toml):
    tests/db/test_hung_database_path.py fails if they stop doing this. A caller's explicit ``timeout``
    (``notifies(timeout=…)``; None there: wait for notifications without end) is its own."""

    answer_timeout_s: float | None = None

    def wait(
        self, gen: PQGen[_RV], interval: float = _WAIT_INTERVAL, timeout: float | _OwnBound | None = _OWN_BOUND
    ) -> _RV:
        if not isinstance(timeout, _OwnBound):
            return super().wait(gen, interval, timeout)
        try:
            return super().wait(gen, interval, self.answer_timeout_s)
        except _WaitTimeout:
            self.pgconn.finish()
            raise psycopg.OperationalError(
                f"no answer from the database within {self.answer_timeout_s:g} s (SPINE_DB_STATEMENT_TIMEOUT_S + "
                "SPINE_DB_TCP_TIMEOUT_S): the connection is closed"
            ) from None


def bound_answers(engine: Engine, timeout_s: float | None) -> None:
    """Make ``engine`` connect with ``AnswerBoundConnection`` (SQLAlchemy's ``do_connect`` event, with the
    parameters its dialect would give ``psycopg.connect``), each bounding its waits to ``timeout_s``."""

    def connect(_dialect: Dialect, _record: ConnectionPoolEntry, cargs: list[Any], cparams: dict[str, Any]) -> Any:
        connection = AnswerBoundConnection.connect(*cargs, **cparams)
        connection.answer_timeout_s = timeout_s
        return connection

    event.listen(engine, "do_connect", connect)


def _entry(settings: Settings) -> tuple[Engine, sessionmaker[Session]]:
    key = (settings.sqlalchemy_url, os.getpid())
    with _LOCK:
        if key not in _ENGINES:
            settings.ensure_data_dir()
            options: dict[str, Any] = {}
            if settings.sqlalchemy_url.startswith("postgresql"):
                options["connect_args"] = postgres_connect_args(settings)
            engine = create_db_engine(settings.sqlalchemy_url, settings.db_pool_size, **options)
            if engine.dialect.name == "postgresql":
                bound_answers(engine, answer_timeout_s(settings))
            _ENGINES[key] = (engine, sessionmaker(engine, expire_on_commit=False))
        return _ENGINES[key]


def get_engine(settings: Settings) -> Engine:
    return _entry(settings)[0]


def session_factory(settings: Settings) -> sessionmaker[Session]:
    return _entry(settings)[1]


@contextmanager
def _scope(factory: sessionmaker[Session]) -> Iterator[Session]:
    session = factory()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


@contextmanager
def session_scope(settings: Settings) -> Iterator[Session]:
    """A session that commits on success and rolls back on error."""
    with _scope(session_factory(settings)) as session:
        yield session


_WORKER_ENGINES: dict[tuple[str, int, bool], Engine] = {}


def _worker_engine(settings: Settings, durable: bool) -> Engine:
    """The engine of ``worker_connection``: on PostgreSQL one of its own per kind (durable or not),
    in autocommit from its creation (no isolation level set and reset at every checkout); on SQLite
    the main engine."""
    key = (settings.sqlalchemy_url, os.getpid(), durable)
    with _LOCK:
        if key in _WORKER_ENGINES:
            return _WORKER_ENGINES[key]
    engine = get_engine(settings)
    if engine.dialect.name == "postgresql":
        # the claim's commit does not wait for the WAL flush (synchronous_commit=off); the finish's does
        extra = () if durable else ("synchronous_commit=off",)
        engine = create_db_engine(settings.sqlalchemy_url, pool_size=2, isolation_level="AUTOCOMMIT",
                                  connect_args=postgres_connect_args(settings, *extra))  # fmt: skip
        bound_answers(engine, answer_timeout_s(settings))
    with _LOCK:
        return _WORKER_ENGINES.setdefault(key, engine)


@contextmanager
def worker_connection(settings: Settings, *, durable: bool = True) -> Iterator[Connection]:
    """A connection for the worker's one-statement state changes (claim, finish, lease renewals):
    a SQLAlchemy Core connection, no ORM session (the worker runs prebuilt Core statements only).

    On PostgreSQL each statement commits by itself (no BEGIN/COMMIT round trips), and with
    ``durable=False`` its commit does not wait for the WAL flush (``synchronous_commit=off``; a
    crash of the server may lose the last such commits, never corrupt anything). On SQLite it is a
    transaction around the statements, committed at the end, rolled back on an error.
    """
    with _worker_engine(settings, durable).connect() as connection:
        try:
            yield connection
            connection.commit()
        except BaseException:
            connection.rollback()
            raise


def dispose_engines() -> None:
    """Forget every engine of this process (e.g. in a worker child right after fork)."""
    with _LOCK:
        for key, (engine, _) in list(_ENGINES.items()):
            engine.dispose(close=key[1] == os.getpid())
            del _ENGINES[key]
        for wkey, worker_engine in list(_WORKER_ENGINES.items()):
            if worker_engine.dialect.name == "postgresql":  # its own engine (on SQLite, the main one)
                worker_engine.dispose(close=wkey[1] == os.getpid())
            del _WORKER_ENGINES[wkey]
