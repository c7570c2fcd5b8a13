"""Typed FastAPI dependencies: settings, database session, queue, caller, JSON body."""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import AsyncIterator
from datetime import UTC, datetime
from typing import Annotated, Any

from celery import Celery
from fastapi import Depends, Request
from pydantic import AfterValidator, BeforeValidator
from sqlalchemy.orm import Session

from services.api.access import Access, QueuedCap
from services.api.errors import ProblemError, field_problem
from services.core.config import Settings
from services.core.problems import problem, validation_problem
from services.db.engine import session_factory
from services.db.keys import Caller
from spine_engine.errors import FieldError

# The dependencies are `async def` although they do no I/O: FastAPI runs a plain `def`
# dependency in the thread pool, a thread hop per dependency and request.


async def get_settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


async def get_session(settings: SettingsDep) -> AsyncIterator[Session]:
    """A session for the request; it connects on first use (in the endpoint's thread)."""
    session = session_factory(settings)()
    try:
        yield session
    finally:
        session.close()


SessionDep = Annotated[Session, Depends(get_session)]


async def get_queue(request: Request) -> Celery:
    queue: Celery = request.app.state.celery
    return queue


QueueDep = Annotated[Celery, Depends(get_queue)]


async def get_caller(request: Request) -> Caller:
    """The client of the request, authenticated by the API-key middleware (services/api/security.py).
    A route that asks for it without the middleware having put one there gets a 401, never a guess."""
    caller = getattr(request.state, "caller", None)
    if not isinstance(caller, Caller):
        raise ProblemError(problem("unauthorized", "this endpoint needs an API key"),
                           headers={"WWW-Authenticate": 'Bearer realm="spine"'})  # fmt: skip
    return caller


CurrentCaller = Annotated[Caller, Depends(get_caller)]
"""The authenticated caller, as a typed dependency (the template's ``CurrentUser``)."""


async def get_access(request: Request, caller: CurrentCaller) -> Access:
    """What the route does in the caller's name: audit and the queued-job cap (services/api/access.py)."""
    cap: QueuedCap = request.app.state.queued_cap
    return Access(caller, cap, request.state)


AccessDep = Annotated[Access, Depends(get_access)]


_KNOWN_QUERY: dict[int, frozenset[str]] = {}


async def reject_unknown_query(request: Request) -> None:
    """A /v1 query parameter the operation does not have is a 422, not silently ignored
    (``?stauts=queued`` would otherwise list every job)."""
    if not request.url.path.startswith("/v1/") or not request.query_params:
        return
    route = request.scope.get("route")
    dependant = getattr(route, "dependant", None)
    if dependant is None:
        return
    known = _KNOWN_QUERY.get(id(route))
    if known is None:
        known = _KNOWN_QUERY[id(route)] = frozenset(_query_names(dependant))
    unknown = [name for name in dict.fromkeys(request.query_params.keys()) if name not in known]
    if unknown:
        raise ProblemError(validation_problem(
            [FieldError(("query", name), "unknown query parameter", "extra_forbidden") for name in unknown],
            instance=request.url.path,
        ))  # fmt: skip


def _query_names(dependant: Any) -> set[str]:
    names = {p.alias for p in dependant.query_params}
    for sub in dependant.dependencies:
        names |= _query_names(sub)
    return names


def _iso_only(value: Any) -> Any:
    """A query timestamp is ISO 8601 text: refuse what pydantic would read as Unix seconds."""
    text = str(value).strip()
    try:
        float(text)
    except ValueError:
        return value
    raise ValueError("expected an ISO 8601 date-time, e.g. 2026-11-22T10:00:00Z, not a number")


def _within_utc_years(value: datetime) -> datetime:
    """A timestamp whose UTC time lies in the years 1–9999 (Python's and so the query's range): an
    offset can carry 0001-01-01 or 9999-12-31 beyond it (0001-01-01T00:00:00+14:00 is in year 0)."""
    if value.tzinfo is not None:
        try:
            value.astimezone(UTC)
        except OverflowError:
            raise ValueError("expected a date-time within the years 1 to 9999 in UTC") from None
    return value


IsoDateTime = Annotated[datetime, BeforeValidator(_iso_only), AfterValidator(_within_utc_years)]
"""A date-time query parameter (format: date-time in the contract, and nothing else)."""


def _is_json(content_type: str) -> bool:
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or (media.startswith("application/") and media.endswith("+json"))


def _too_large(limit: int, instance: str) -> ProblemError:
    return ProblemError(problem("payload-too-large", f"the body is larger than {limit} bytes", instance=instance,
                                limit=limit))  # fmt: skip


class _DuplicateKey(Exception):
    """An object of the body has a name twice (found while parsing; ``duplicate_keys`` says where)."""


def _unique_object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """``json.loads``' object hook: the object as a dict, unless a name repeats (``_DuplicateKey``)."""
    obj = dict(pairs)
    if len(obj) != len(pairs):
        raise _DuplicateKey
    return obj


class _Members(list[tuple[str, Any]]):
    """An object's members in their order, repeated names kept."""


def duplicate_keys(raw: bytes) -> list[FieldError]:
    """Every name given twice (or more) in one object of the JSON text ``raw``, by the JSON path of that
    member. RFC 8259 §4: the names of an object SHOULD be unique, and a receiver's behaviour on repeated
    names is unpredictable (Python's ``json`` keeps the last): a body that has them is ambiguous, and
    it is refused rather than read one way."""
    found: dict[tuple[str | int, ...], FieldError] = {}
    stack: list[tuple[Any, tuple[str | int, ...]]] = [(json.loads(raw, object_pairs_hook=_Members), ())]
    while stack:  # depth-first, without recursion (the body may be nested as deep as the parser allows)
        node, loc = stack.pop()
        if isinstance(node, _Members):
            for key, times in Counter(key for key, _ in node).items():
                if times > 1:
                    msg = f"the key {key!r} is given {times} times in this object; give it once"
                    found.setdefault((*loc, key), FieldError((*loc, key), msg, "duplicate_key"))
            stack.extend(((value, (*loc, key)) for key, value in reversed(node)))
        elif isinstance(node, list):
            stack.extend(((value, (*loc, i)) for i, value in reversed(list(enumerate(node)))))
    return sorted(found.values(), key=lambda e: e.path)


async def read_json(request: Request, limit: int) -> Any:
    """The request body as JSON: 415 if not JSON, 413 over ``limit`` bytes, 400 if malformed, 422
    naming every key given twice in one object (``duplicate_keys``)."""
    instance = request.url.path
    content_type = request.headers.get("content-type", "")
    if not _is_json(content_type):
        detail = f"the body must be sent as application/json, not {content_type or 'without a content type'!r}"
        if content_type.split(";", 1)[0].strip().lower() == "application/dicom":
            detail += (
                ": a radiograph is not a job; send the landmarks as JSON and name the film by its UIDs "
                "(study.study_instance_uid and study.pa_sop_instance_uid: the service reads its header from "
                "the PACS), or let the client read the header locally (spine submit --pa-dicom FILE)"
            )
        raise ProblemError(
            problem(
                "unsupported-media-type",
                detail,
                instance=instance,
                errors=[{"path": "", "loc": [], "msg": "content type must be application/json",
                         "type": "content_type"}],
            )
        )  # fmt: skip
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise _too_large(limit, instance)
    chunks: list[bytes] = []
    size = 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise _too_large(limit, instance)
        chunks.append(chunk)
    raw = b"".join(chunks)
    try:
        return json.loads(raw, object_pairs_hook=_unique_object)
    except _DuplicateKey:
        raise ProblemError(field_problem(duplicate_keys(raw), instance=instance)) from None
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError, ValueError) as exc:
        # RecursionError: nested too deeply; ValueError: an integer of more than 4300 digits.
        where = f"line {exc.lineno} column {exc.colno}" if isinstance(exc, json.JSONDecodeError) else "body"
        if isinstance(exc, json.JSONDecodeError):
            msg = exc.msg
        elif isinstance(exc, UnicodeDecodeError):
            msg = "the body is not UTF-8"
        elif isinstance(exc, RecursionError):
            msg = "the body is nested too deeply"
        else:
            msg = "a number has too many digits"
        error = FieldError((), f"{msg} ({where})", "json_invalid")
        raise ProblemError(
            problem(
                "malformed-json",
                f"the body is not valid JSON: {msg} at {where}",
                instance=instance,
                errors=[{"path": error.path, "loc": [], "msg": error.msg, "type": error.type}],
            )
        ) from None


async def job_body(request: Request) -> Any:
    return await read_json(request, request.app.state.settings.max_body_bytes)


async def batch_body(request: Request) -> Any:
    return await read_json(request, request.app.state.settings.max_batch_body_bytes)


JobBody = Annotated[Any, Depends(job_body)]
BatchBody = Annotated[Any, Depends(batch_body)]
