"""The migrations equal the models: an empty SQLite and an empty PostgreSQL database
upgraded to head show no difference with ``Base.metadata`` (Alembic's ``compare_metadata``), and
every revision goes down and up again."""

from __future__ import annotations

import uuid
import warnings
from pathlib import Path
from typing import Any

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Engine, create_engine, insert, inspect, select
from sqlalchemy.orm import Session

from services.core.config import Settings
from services.db import jobs as repo
from services.db.migrate import alembic_config, downgrade, upgrade
from services.db.models import Base, Job, utcnow
from tests.conftest import spine_payload

EXPECTED_TABLES = {"jobs", "job_measures", "vertebra_strains", "api_keys", "job_audit", "webhook_deliveries"}


@pytest.fixture(params=["sqlite", "postgresql"])
def empty_db(request: pytest.FixtureRequest, tmp_path: Path) -> Settings:
    """Settings of an empty database (nothing migrated)."""
    if request.param == "postgresql":
        ctx = request.getfixturevalue("fresh_postgres_url")
        return Settings(DATABASE_URL=ctx, data_dir=tmp_path)
    return Settings(data_dir=tmp_path)


def _differences(settings: Settings) -> list[Any]:
    engine = create_engine(settings.sqlalchemy_url)
    try:
        with engine.connect() as conn, warnings.catch_warnings():
            # SQLite cannot reflect the expression index uq_jobs_owner_idempotency_key; checked below.
            warnings.filterwarnings("ignore", message="Skipped unsupported reflection of expression-based index")
            return list(compare_metadata(MigrationContext.configure(conn), Base.metadata))
    finally:
        engine.dispose()


def test_every_model_is_in_the_one_metadata() -> None:
    assert set(Base.metadata.tables) == EXPECTED_TABLES


def test_head_equals_the_models(empty_db: Settings) -> None:
    upgrade(empty_db, quiet=True)
    assert _differences(empty_db) == []
    engine = create_engine(empty_db.sqlalchemy_url)
    try:
        indexes = {ix["name"] for ix in inspect(engine).get_indexes("jobs")}
    finally:
        engine.dispose()
    assert {"ix_jobs_owner_queued", "ix_jobs_running_lease"} <= indexes


def test_a_drift_is_found(empty_db: Settings) -> None:
    """compare_metadata sees a missing index (so that the test above can fail)."""
    upgrade(empty_db, quiet=True)
    engine = create_engine(empty_db.sqlalchemy_url)
    try:
        with engine.begin() as conn:
            conn.exec_driver_sql("DROP INDEX ix_jobs_owner_queued")
    finally:
        engine.dispose()
    found = _differences(empty_db)
    assert any(d[0] == "add_index" and d[1].name == "ix_jobs_owner_queued" for d in found), found


def test_every_revision_goes_down_and_up(empty_db: Settings) -> None:
    script = ScriptDirectory.from_config(alembic_config(empty_db, quiet=True))
    revisions = [r.revision for r in reversed(list(script.walk_revisions()))]  # base → head
    assert len(revisions) >= 6
    for revision in revisions:
        upgrade(empty_db, revision, quiet=True)
        downgrade(empty_db, "-1")
        upgrade(empty_db, revision, quiet=True)
    assert _differences(empty_db) == []
    downgrade(empty_db, "base")
    engine = create_engine(empty_db.sqlalchemy_url)
    try:
        assert set(inspect(engine).get_table_names()) <= {"alembic_version"}
    finally:
        engine.dispose()


def test_results_are_compressed_with_lz4_where_the_server_has_it(fresh_postgres_url: str, tmp_path: Path) -> None:
    """Revision 0009: jobs.result uses LZ4 on a PostgreSQL built with it, the default again after
    its downgrade (``attcompression``: 'l' LZ4, '' the server's default)."""
    settings = Settings(DATABASE_URL=fresh_postgres_url, data_dir=tmp_path)
    upgrade(settings, quiet=True)
    engine = create_engine(settings.sqlalchemy_url)
    query = "SELECT attcompression FROM pg_attribute WHERE attrelid = 'jobs'::regclass AND attname = 'result'"
    has_lz4 = "SELECT 'lz4' = ANY(enumvals) FROM pg_settings WHERE name = 'default_toast_compression'"
    try:
        with engine.connect() as conn:
            lz4 = bool(conn.exec_driver_sql(has_lz4).scalar())
            assert conn.exec_driver_sql(query).scalar() == ("l" if lz4 else "")
        downgrade(settings, "0008_webhook_attempt_unique")
        with engine.connect() as conn:
            assert conn.exec_driver_sql(query).scalar() == ""
    finally:
        engine.dispose()


def _predicates(engine: Engine) -> dict[str, str | None]:
    """Index name -> its WHERE text (None: not partial) of every index of ``jobs``, from the catalog
    (SQLite cannot reflect the expression index, so its ``CREATE INDEX`` text is read instead)."""
    with engine.connect() as conn:
        if engine.dialect.name == "sqlite":
            query = "SELECT name, sql FROM sqlite_master WHERE type = 'index' AND tbl_name = 'jobs'"
            rows = conn.exec_driver_sql(query)
        else:
            rows = conn.exec_driver_sql("SELECT indexname, indexdef FROM pg_indexes WHERE tablename = 'jobs'")
        found = {name: sql for name, sql in rows if sql is not None}  # SQLite's automatic indexes have none
    return {name: sql.split(" WHERE ", 1)[1] if " WHERE " in sql else None for name, sql in found.items()}


def test_the_partial_indexes_of_the_models_are_partial_in_the_database(empty_db: Settings) -> None:
    """compare_metadata does not compare index predicates: the migrated ``jobs`` indexes have a WHERE
    exactly where the models give one, naming the same column (revision 0010), and lose the new ones
    when it goes down."""
    dialect = "sqlite" if empty_db.sqlalchemy_url.startswith("sqlite") else "postgresql"
    models = {
        str(ix.name): ix.dialect_options[dialect]["where"] for ix in Base.metadata.tables["jobs"].indexes
    }
    upgrade(empty_db, quiet=True)
    engine = create_engine(empty_db.sqlalchemy_url)
    try:
        found = _predicates(engine)
        assert {n for n, w in found.items() if w is not None} == {n for n, w in models.items() if w is not None}
        for name, where in models.items():
            if where is not None:
                column = str(where).split()[0]
                assert column in str(found[name]), (name, found[name])
        assert "idempotency_key IS NOT NULL" in str(found["uq_jobs_owner_idempotency_key"])
        downgrade(empty_db, "0009_result_lz4")
        partial = {n for n, w in _predicates(engine).items() if w is not None}
        assert partial == {"ix_jobs_owner_queued", "ix_jobs_running_lease"}
    finally:
        engine.dispose()


def test_the_bending_columns_keep_their_values_across_the_rename(tmp_path: Path) -> None:
    """Revision 0011 renames ``vertebra_strains``' bending columns by plane (pa → sagittal, lateral →
    frontal) and back, each value staying in its column (SQLite: no foreign keys enforced, so a strain
    row needs no job here)."""
    settings = Settings(data_dir=tmp_path)
    upgrade(settings, "0010_jobs_partial_indexes", quiet=True)
    engine = create_engine(settings.sqlalchemy_url)
    insert = "INSERT INTO vertebra_strains (job_id, level, pa_bending_deg, lateral_bending_deg, axial_rotation_deg) "
    try:
        with engine.begin() as conn:
            conn.exec_driver_sql(insert + "VALUES ('00000000000000000000000000000001', 'T3', 1.5, -0.25, 0.0)")
        upgrade(settings, quiet=True)
        with engine.connect() as conn:
            by_plane = "SELECT sagittal_bending_deg, frontal_bending_deg FROM vertebra_strains"
            assert conn.exec_driver_sql(by_plane).one() == (1.5, -0.25)
        downgrade(settings, "0010_jobs_partial_indexes")
        with engine.connect() as conn:
            by_view = "SELECT pa_bending_deg, lateral_bending_deg FROM vertebra_strains"
            assert conn.exec_driver_sql(by_view).one() == (1.5, -0.25)
    finally:
        engine.dispose()


def test_keys_stored_before_0012_replay_as_before_and_new_ones_are_apart(empty_db: Settings) -> None:
    """Revision 0012 keeps a single submission's Idempotency-Key and a batch entry's (``K#i``) apart.
    A key with a ``#`` stored before it may be either (the row does not say): it still replays both ways,
    as it did; a key without one is a single's. Keys stored after it are apart, and going down keeps the
    single's key where the two meet (the older unique index allows one)."""
    upgrade(empty_db, "0011_bending_by_plane", quiet=True)
    engine = create_engine(empty_db.sqlalchemy_url)
    p, q, r = spine_payload(), spine_payload(curve_mm=25.0), spine_payload(curve_mm=5.0)
    legacy = {"K#0": p, "S#1": q, "plain": r}  # a batch's entry 0, a single's key with a '#', a single's
    ids = {key: uuid.uuid4() for key in legacy}
    now = utcnow()
    try:
        with engine.begin() as conn:  # the columns of 0011: no idempotency_kind
            conn.execute(insert(Job), [
                {"id": ids[key], "owner": "c", "status": "queued", "created_at": now, "enqueued_at": now,
                 "attempts": 0, "payload": payload, "idempotency_key": key, "request_hash": repo.request_hash(payload)}
                for key, payload in legacy.items()
            ])  # fmt: skip
        upgrade(empty_db, quiet=True)
        with Session(engine) as s:
            kinds = dict(s.execute(select(Job.idempotency_key, Job.idempotency_kind).where(Job.owner == "c")).all())
            assert kinds == {"K#0": "either", "S#1": "either", "plain": None}
            for key, payload in (("K", p), ("S", q)):  # a batch sent again, and a single, each replayed
                [(job, created)] = repo.create_jobs_idempotent(s, [(int(key == "S"), payload)], owner="c", key=key)
                assert (job.id, created) == (ids[f"{key}#{int(key == 'S')}"], False)
            for key, payload in legacy.items():
                assert repo.create_job(s, payload, owner="c", idempotency_key=key) == (s.get(Job, ids[key]), False)
            [(entry, created)] = repo.create_jobs_idempotent(s, [(0, p)], owner="c", key="N")
            single, made = repo.create_job(s, q, owner="c", idempotency_key="N#0")  # another body: not a 409
            assert created and made and entry.id != single.id
        downgrade(empty_db, "0011_bending_by_plane")
        with engine.connect() as conn:
            keys = dict(conn.execute(select(Job.id, Job.idempotency_key).where(Job.owner == "c")).all())
        assert keys[single.id] == "N#0" and keys[entry.id] is None
        assert {keys[i] for i in ids.values()} == set(legacy)
    finally:
        engine.dispose()
