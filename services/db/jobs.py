"""Jobs as clients see them: create (idempotent, single and batch), read, list, cancel, and the
job's JSON view of webhook bodies (``job_json``; the API answers with its ``Job`` model, built from
the row, and tests/api/test_response_models.py checks that the two write the same JSON).

The cancel is a conditional UPDATE (``WHERE status IN (queued, running)``), so it never gives a
job a second outcome; runs (claim, finish, reconcile) are in ``services.db.runs``.

A batch sent with an ``Idempotency-Key`` stores payload ``i`` under the job key ``K#i`` (per owner,
the same unique index as single submissions), so the same key and body return the same jobs; an
entry whose body differs from the one first sent under ``K#i`` is an ``IdempotencyConflict``. A
single submission's key and a batch entry's are apart (``jobs.idempotency_kind``: ``batch`` for an
entry, NULL for a single key), so a single POST keyed ``abc#0`` and entry 0 of the batch keyed ``abc``
never answer for each other; a key with a ``#`` stored before migration 0012 (kind ``either``: the
row does not say which request stored it) still answers both, as it did.

Keys are per client (``jobs.idempotency_client``, migration 0013: the name of the API keys that sent
them), not per owner: an admin key's jobs have no owner (every admin sees them), yet two admin clients'
keys are apart. A key an admin stored before 0013 that the audit trail did not name (client NULL) is
still replayed to every admin key, as it was: a request retried across the upgrade makes no second job.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
import uuid
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    ColumnElement,
    CursorResult,
    and_,
    func,
    insert,
    literal_column,
    or_,
    select,
    update,
)
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from services.core.status import JobStatus
from services.db.clock import db_now
from services.db.job_forms import job_study
from services.db.models import Job, iso_utc

InsertHook = Callable[[Session, list[uuid.UUID]], None]
"""Called with the ids of jobs just inserted, in their transaction (the API's audit rows)."""
AdmitHook = Callable[[int], None]
"""Called with the number of new jobs about to be inserted, after the Idempotency-Key lookup and before
the insert, and only when there are new jobs (the API's per-client cap, which may raise): a replay makes
nothing, so it is never refused by the cap."""


class IdempotencyConflict(Exception):
    """The Idempotency-Key was already used with a different body."""

    def __init__(self, job_id: uuid.UUID):
        self.job_id = job_id
        super().__init__(str(job_id))


class JobNotFound(Exception):
    pass


class JobFinished(Exception):
    """The job has already reached succeeded or failed."""

    def __init__(self, job: Job):
        self.job = job
        super().__init__(job.status)


class BadCursor(ValueError):
    pass


def request_hash(payload: Any) -> str:
    """A digest of a JSON body, independent of key order and whitespace."""
    canonical = json.dumps(payload, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return hashlib.sha256(canonical.encode()).hexdigest()


_INSERT_JOBS = insert(Job).values(created_at=db_now(), enqueued_at=db_now()).returning(Job.id, Job.created_at)
"""The insert of new jobs (rows of ``_new_job``), returning each one's id and ``created_at``.
``created_at`` and ``enqueued_at`` are the database's clock (``services.db.clock``): the
reconciler compares ``enqueued_at`` with ``SPINE_QUEUED_TIMEOUT_S``, and ``created_at`` is on the clock
of the worker's ``started_at`` and ``finished_at`` (``services.db.runs``), so that a job's times are
ordered whatever the API host's clock."""


def _insert(session: Session, rows: list[dict[str, Any]]) -> None:
    """Insert the rows of new jobs (``_INSERT_JOBS``; a Core insert: the hot path skips the unit of work)
    and put in each its ``created_at`` as the database wrote it."""
    created: dict[uuid.UUID, datetime] = {row.id: row.created_at for row in session.execute(_INSERT_JOBS, rows)}
    for row in rows:
        row["created_at"] = created[row["id"]]


def _new_job(payload: dict[str, Any], owner: str | None, **extra: Any) -> dict[str, Any]:
    """The values of a new queued job, but ``created_at`` and ``enqueued_at`` (``_INSERT_JOBS``)."""
    return {
        "id": uuid.uuid4(),
        "owner": owner,
        "status": JobStatus.queued.value,
        "attempts": 0,
        "payload": payload,
        "callback_url": callback_url_of(payload),
        **study_columns(payload),
        **extra,
    }


STUDY_COLUMNS = ("study_instance_uid", "accession_number", "patient_id")
"""The payload's study identifiers kept as indexed columns for the list filters."""


def dicom_identifier(value: str) -> str:
    """A DICOM identifier as the columns hold it and the filters compare it: without leading and
    trailing spaces, which are padding in an LO or SH value (PS3.5 §6.2), so "P " and "P" are one
    Patient ID. The payload and the result keep the text as it was sent."""
    return value.strip(" ")


def study_column_values(study: Any) -> dict[str, str | None]:
    """The identifier columns of a study's JSON (the payload's ``study``, or what the DICOM layer read):
    each of ``STUDY_COLUMNS`` that is text, without its padding (``dicom_identifier``); None when it is
    absent or only spaces."""
    study = study if isinstance(study, dict) else {}
    values = {name: study.get(name) for name in STUDY_COLUMNS}
    return {name: (dicom_identifier(v) or None) if isinstance(v, str) else None for name, v in values.items()}


def study_columns(payload: Any) -> dict[str, str | None]:
    """``study_instance_uid``, ``accession_number``, ``patient_id`` of the payload's ``study`` (None when absent)."""
    return study_column_values(payload.get("study") if isinstance(payload, dict) else None)


def callback_url_of(payload: Any) -> str | None:
    """The payload's ``callback_url`` (already checked by the API), stored in its own column."""
    url = payload.get("callback_url") if isinstance(payload, dict) else None
    return url if isinstance(url, str) else None


def create_job(
    session: Session,
    payload: dict[str, Any],
    *,
    owner: str | None = None,
    client: str | None = None,
    idempotency_key: str | None = None,
    on_insert: InsertHook | None = None,
    dicom: dict[str, Any] | None = None,
    admit: AdmitHook | None = None,
) -> tuple[Job, bool]:
    """Store a queued job; return it and whether it is new (False: an idempotent replay). ``dicom``:
    what the client read from its image files (``jobs.dicom``, as the worker stores its PACS reads).

    ``client``: whose ``idempotency_key`` it is (the API key's name; ``owner`` when not given).
    Raises ``IdempotencyConflict`` when ``idempotency_key`` was used by this client with another body.
    ``admit(1)`` runs only when the job is new, before the insert (the API's cap: a replay is not
    counted against it); ``on_insert(session, [job id])`` runs in the inserting transaction (the API's
    audit row).
    """
    body = payload if dicom is None else {**payload, "dicom": dicom}
    digest = request_hash(body) if idempotency_key is not None else None
    client = owner if client is None else client
    if idempotency_key is not None:
        existing = _by_idempotency_key(session, owner, client, idempotency_key)
        if existing is not None:
            return _replay(existing, digest)
    if admit is not None:
        admit(1)
    extra: dict[str, Any] = {"dicom": dicom} if dicom is not None else {}
    if idempotency_key is not None:
        extra["idempotency_client"] = client
    values = _new_job(payload, owner, idempotency_key=idempotency_key, request_hash=digest, **extra)
    try:
        _insert(session, [values])
        if on_insert is not None:
            on_insert(session, [values["id"]])
        session.commit()
    except IntegrityError:
        session.rollback()
        if idempotency_key is None:
            raise
        existing = _by_idempotency_key(session, owner, client, idempotency_key)
        if existing is None:
            raise
        return _replay(existing, digest)
    return _detached(values), True


def _detached(values: dict[str, Any]) -> Job:
    """A Job object holding what was just inserted (``created_at`` as the insert returned it); its
    ``enqueued_at``, the database's clock, is not known here (None; nothing shows it)."""
    row = {"started_at": None, "finished_at": None, "result": None, "error": None, "engine_version": None,
           "idempotency_key": None, "idempotency_kind": None, "idempotency_client": None, "request_hash": None,
           "callback_url": None, "lease_expires_at": None, "dicom": None, "enqueued_at": None, **values}  # fmt: skip
    return Job(**row)


def _owner_match(owner: str | None) -> ColumnElement[bool]:
    """The jobs of ``owner`` (None: the admin's, owner NULL), written twice: as the unique index
    ``uq_jobs_owner_idempotency_key`` keys them (``coalesce(owner, '')``), so that a lookup by key is
    a search of that index, not a scan of all of it (``owner = :owner`` alone cannot use the index's
    first column: 4 ms and 700 pages at 300,000 jobs), and exactly (an owner named ``''``). The
    ``''`` is a literal, as in the index's expression: a bound parameter there would not match it."""
    exact = Job.owner.is_(None) if owner is None else Job.owner == owner
    return and_(func.coalesce(Job.owner, literal_column("''")) == (owner or ""), exact)


BATCH_ENTRY = "batch"
"""``jobs.idempotency_kind`` of a batch entry's key ``K#i`` (NULL: a single submission's key)."""
EITHER = "either"
"""``jobs.idempotency_kind`` of a key with a ``#`` stored before migration 0012: a single's or an entry's."""


def _key_scope(owner: str | None, client: str | None) -> ColumnElement[bool]:
    """The jobs whose Idempotency-Keys ``client`` replays: its own (``owner``'s, and of its name), written
    as ``_owner_match`` writes the owner, for the unique index's first two columns. An admin client (no
    owner) also replays the keys stored before migration 0013 that no client was found for (client NULL,
    owner NULL), as every admin did then; its own is taken first (``_OWN_FIRST``). ``client`` None: the
    keys stored without a client (a caller of this module that names none, and no owner)."""
    named = func.coalesce(Job.idempotency_client, literal_column("''"))
    if client is None:
        return and_(_owner_match(owner), named == "", Job.idempotency_client.is_(None))
    own = and_(named == client, Job.idempotency_client == client)
    if owner is not None:
        return and_(_owner_match(owner), own)
    unnamed = Job.idempotency_client.is_(None)
    return and_(_owner_match(None), named.in_([client, ""]), or_(Job.idempotency_client == client, unnamed))


_OWN_FIRST = Job.idempotency_client.is_(None)
"""The order of ``_key_scope``'s rows of one key: the client's own (false sorts first), then one stored
without a client for every admin (the two meet only when a caller of this module that names no client
stores a key an admin client holds)."""


def _by_idempotency_key(session: Session, owner: str | None, client: str | None, key: str) -> Job | None:
    """The job stored under a single submission's ``key`` (one stored as ``either`` included)."""
    single = or_(Job.idempotency_kind.is_(None), Job.idempotency_kind == EITHER)
    query = select(Job).where(_key_scope(owner, client), Job.idempotency_key == key, single).order_by(_OWN_FIRST)
    return session.scalars(query).first()


def _replay(existing: Job, digest: str | None) -> tuple[Job, bool]:
    if existing.request_hash != digest:
        raise IdempotencyConflict(existing.id)
    return existing, False


def create_jobs(
    session: Session,
    payloads: Sequence[dict[str, Any]],
    *,
    owner: str | None = None,
    on_insert: InsertHook | None = None,
) -> list[Job]:
    """Store many queued jobs in one transaction (the batch endpoint)."""
    rows = [_new_job(p, owner) for p in payloads]
    _insert(session, rows)
    if on_insert is not None:
        on_insert(session, [row["id"] for row in rows])
    session.commit()
    return [_detached(row) for row in rows]


def get_job(session: Session, job_id: uuid.UUID, *, owner: str | None = None) -> Job:
    """The job ``job_id``, of ``owner`` when given (a client reads only its own). The owner is in the
    query, so another client's job is not loaded: it costs what an unknown id costs, and its answer's
    time does not tell that it exists."""
    query = select(Job).where(Job.id == job_id)
    if owner is not None:
        query = query.where(Job.owner == owner)
    job = session.scalars(query).first()
    if job is None:
        raise JobNotFound(str(job_id))
    return job


def encode_cursor(job: Job) -> str:
    raw = f"{job.created_at.isoformat()}|{job.id}"
    return base64.urlsafe_b64encode(raw.encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[datetime, uuid.UUID]:
    try:
        raw = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)).decode()
        created, job_id = raw.split("|")
        when = datetime.fromisoformat(created)
        if when.tzinfo is None:
            raise ValueError("naive")
        return when.astimezone(UTC), uuid.UUID(job_id)
    except (binascii.Error, UnicodeDecodeError, ValueError, OverflowError) as exc:  # overflow: beyond year 9999 in UTC
        raise BadCursor("the cursor is not one this API returned") from exc


def list_jobs(
    session: Session,
    *,
    statuses: Sequence[str] = (),
    created_after: datetime | None = None,
    created_before: datetime | None = None,
    cursor: str | None = None,
    limit: int = 50,
    owner: str | None = None,
    study_instance_uid: str | None = None,
    accession_number: str | None = None,
    patient_id: str | None = None,
) -> tuple[list[Job], str | None]:
    """Jobs newest first (created_at, then id, descending) and the cursor of the next page; the
    DICOM filters match the study's columns exactly but for padding spaces (``dicom_identifier``:
    "P " finds the jobs of "P"), indexed with the owner."""
    query = select(Job)
    if statuses:
        query = query.where(Job.status.in_(list(statuses)))
    if owner is not None:
        query = query.where(Job.owner == owner)
    if study_instance_uid is not None:
        query = query.where(Job.study_instance_uid == dicom_identifier(study_instance_uid))
    if accession_number is not None:
        query = query.where(Job.accession_number == dicom_identifier(accession_number))
    if patient_id is not None:
        query = query.where(Job.patient_id == dicom_identifier(patient_id))
    if created_after is not None:
        query = query.where(Job.created_at >= created_after)
    if created_before is not None:
        query = query.where(Job.created_at < created_before)
    if cursor is not None:
        at, job_id = decode_cursor(cursor)
        query = query.where(or_(Job.created_at < at, and_(Job.created_at == at, Job.id < job_id)))
    query = query.order_by(Job.created_at.desc(), Job.id.desc()).limit(limit + 1)
    jobs = list(session.scalars(query))
    next_cursor = encode_cursor(jobs[limit - 1]) if len(jobs) > limit else None
    return jobs[:limit], next_cursor


MAX_PATIENT_JOBS = 1000
"""At most this many succeeded jobs of one patient are read for a follow-up, the newest (a patient
filmed every 4 months for 20 years has 60 visits); the follow-up says when older ones were left out."""


def succeeded_jobs_of_patient(session: Session, patient_id: str, *, owner: str | None = None) -> tuple[list[Job], bool]:
    """The newest ``MAX_PATIENT_JOBS`` succeeded jobs of a patient (the ``patient_id`` column: the
    payload's study, or the one the DICOM layer read from the header, compared without padding:
    ``dicom_identifier``), of ``owner`` (None: every owner's, for an admin), returned oldest first by
    creation (the caller orders them by study date, which lives in the payload or the header reads);
    and whether older succeeded jobs of the patient were left out. Uses the ``(owner, patient_id,
    created_at)`` index, read backwards."""
    query = select(Job).where(Job.patient_id == dicom_identifier(patient_id), Job.status == JobStatus.succeeded.value)
    if owner is not None:
        query = query.where(Job.owner == owner)
    limit = MAX_PATIENT_JOBS
    query = query.order_by(Job.created_at.desc(), Job.id.desc()).limit(limit + 1)
    newest = list(session.scalars(query))
    return newest[:limit][::-1], len(newest) > limit


def cancel_job(session: Session, job_id: uuid.UUID, *, owner: str | None = None) -> tuple[Job, bool]:
    """Move a queued or running job to cancelled; return it and whether this call cancelled it
    (False: it already was, and is returned as it is).

    Raises ``JobNotFound``, or ``JobFinished`` when it already succeeded or failed.
    """
    get_job(session, job_id, owner=owner)
    outcome: CursorResult[Any] = session.execute(  # type: ignore[assignment]
        update(Job)
        .where(Job.id == job_id, Job.status.in_([JobStatus.queued.value, JobStatus.running.value]))
        .values(status=JobStatus.cancelled.value, finished_at=db_now())  # the clock of created_at and started_at
    )
    session.commit()
    job = get_job(session, job_id, owner=owner)
    session.refresh(job)
    if job.status in (JobStatus.succeeded.value, JobStatus.failed.value):
        raise JobFinished(job)
    return job, outcome.rowcount == 1


MAX_BATCH_KEY_LENGTH = 240
"""Longest Idempotency-Key of a batch: ``#<index>`` is appended per job (the column holds 255)."""


def entry_key(key: str, index: int) -> str:
    return f"{key}#{index}"


Outcome = tuple[Job, bool] | IdempotencyConflict
"""Per payload: (job, created) or the conflict with the job first stored under its key."""


def create_jobs_idempotent(
    session: Session,
    payloads: Sequence[tuple[int, dict[str, Any]]],
    *,
    owner: str | None,
    key: str,
    client: str | None = None,
    on_insert: InsertHook | None = None,
    admit: AdmitHook | None = None,
) -> list[Outcome]:
    """Store the (index, payload) pairs under ``key#index`` (kind ``batch``) of ``client`` (the API key's
    name; ``owner`` when not given); replay those already stored. ``admit(n)`` runs with the number of
    new jobs before they are inserted, in the inserting transaction (replays are not counted).

    When a concurrent request stored some of the keys first (the insert breaks the unique index), the
    keys are looked up again and the rest inserted, admitted again: every job made here passes
    ``admit``. Each such round inserts fewer rows than the one before (a key it lost is now stored);
    an insert refused with as many rows as the round before is not a concurrent key, and is raised."""
    keys = [entry_key(key, i) for i, _ in payloads]
    client = owner if client is None else client
    digests = [request_hash(payload) for _, payload in payloads]
    entries = or_(Job.idempotency_kind == BATCH_ENTRY, Job.idempotency_kind == EITHER)
    scope = _key_scope(owner, client)
    refused_with: int | None = None
    while True:
        stored = session.scalars(select(Job).where(scope, Job.idempotency_key.in_(keys), entries).order_by(_OWN_FIRST))
        existing: dict[str | None, Job] = {}
        for job in stored:
            existing.setdefault(job.idempotency_key, job)
        outcomes: list[Outcome | None] = []
        rows: list[dict[str, Any]] = []
        slots: list[int] = []
        for (_, payload), job_key, digest in zip(payloads, keys, digests, strict=True):
            found = existing.get(job_key)
            if found is not None:
                outcomes.append((found, False) if found.request_hash == digest else IdempotencyConflict(found.id))
                continue
            slots.append(len(outcomes))
            outcomes.append(None)
            rows.append(_new_job(payload, owner, idempotency_key=job_key, idempotency_kind=BATCH_ENTRY,
                                 idempotency_client=client, request_hash=digest))  # fmt: skip
        if rows:
            if admit is not None:
                admit(len(rows))
            try:
                _insert(session, rows)
                if on_insert is not None:
                    on_insert(session, [row["id"] for row in rows])
                session.commit()
            except IntegrityError:
                session.rollback()
                if refused_with is not None and len(rows) >= refused_with:
                    raise
                refused_with = len(rows)
                continue
            for slot, row in zip(slots, rows, strict=True):
                outcomes[slot] = _detached(row), True
        return [o for o in outcomes if o is not None]


# ------------------------------------------------------------------ the job's JSON view


def _ts(value: datetime | None) -> str | None:
    return iso_utc(value) if value is not None else None


def job_members(job: Job) -> dict[str, Any]:
    """The members every view of a job has, from its row's columns: the API's ``Job.summary`` and
    ``Job.detail`` are built from them (``services.api.schemas``), and a webhook's ``data`` is their
    JSON (``job_json``)."""
    return {
        "id": job.id,
        "status": job.status,
        "owner": job.owner,
        "created_at": job.created_at,
        "started_at": job.started_at,
        "finished_at": job.finished_at,
        "attempts": job.attempts,
        "engine_version": job.engine_version,
        "result": job.result,
        "error": job.error,
        "study": job_study(job),
    }


def job_json(job: Job) -> dict[str, Any]:
    """A job as the ``data`` of a webhook body: ``job_members`` as JSON (the id as text, the times in
    ISO 8601 UTC), what the API's ``Job.summary`` answers."""
    members = job_members(job)
    times = {key: _ts(members[key]) for key in ("created_at", "started_at", "finished_at")}
    return {**members, "id": str(job.id), **times}
