"""Typed FastAPI dependencies: settings, database session, queue, caller, JSON body."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from typing import Annotated, Any

from celery import Celery
from fastapi import Depends, Request
from sqlalchemy.orm import Session

from services.api.errors import ProblemError
from services.db.engine import session_factory
from services.problems import problem
from services.settings import Settings
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


async def get_owner() -> str | None:
    """The caller's identity; None until API keys exist (a later issue fills this in)."""
    return None


OwnerDep = Annotated[str | None, Depends(get_owner)]


def _is_json(content_type: str) -> bool:
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or (media.startswith("application/") and media.endswith("+json"))


async def read_json(request: Request, limit: int) -> Any:
    """The request body as JSON: 415 if not JSON, 413 over ``limit`` bytes, 400 if malformed."""
    instance = request.url.path
    content_type = request.headers.get("content-type", "")
    if not _is_json(content_type):
        raise ProblemError(
            problem(
                "unsupported-media-type",
                f"the body must be sent as application/json, not {content_type or 'without a content type'!r}",
                instance=instance,
                errors=[{"path": "", "loc": [], "msg": "content type must be application/json",
                         "type": "content_type"}],
            )
        )  # fmt: skip
    declared = request.headers.get("content-length")
    too_large = problem("payload-too-large", f"the body is larger than {limit} bytes", instance=instance, limit=limit)
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise ProblemError(too_large)
    chunks: list[bytes] = []
    size = 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise ProblemError(too_large)
        chunks.append(chunk)
    raw = b"".join(chunks)
    try:
        return json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        where = f"line {exc.lineno} column {exc.colno}" if isinstance(exc, json.JSONDecodeError) else "body"
        msg = exc.msg if isinstance(exc, json.JSONDecodeError) else "the body is not UTF-8"
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
