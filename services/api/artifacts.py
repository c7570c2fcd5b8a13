"""A succeeded job's built artifacts (``figure.png``, ``figure.svg``, ``sr.dcm``, ``figure.dcm``,
``fhir``): their strong entity tags, the conditional GET, and a bounded in-process cache of their bytes.

Once a job has succeeded, what its artifacts are built from never changes: the payload (stored as
posted), the DICOM provenance (``jobs.dicom``, written only while the job runs, fenced by attempt),
the result, ``finished_at`` and ``engine_version`` (written once, by the run that finished it; a
finished job keeps its one outcome, ``db.runs.finish_job``). The bytes are then a function of the
job's id, its ``finished_at`` and ``engine_version``, the kind of artifact, the settings it is
built with (``variant``: the FHIR export's ``SPINE_PATIENT_ID_SYSTEM``), and the code and libraries
that build it (``BUILD``): an artifact's entity tag is a digest of exactly these.

- ``ETag`` (RFC 9110 §8.8.3): a strong validator, sent on every 200 and 304 of an artifact; equal
  tags mean equal bytes (§8.8.1), since everything that determines them is in the digest. Different
  API replicas of one release give the same tag (nothing in it is per process).
- ``If-None-Match`` (RFC 9110 §13.1.2): ``*`` or a list of entity tags, compared with the weak
  comparison function (§8.8.3.2) as §13.1.2 requires; a match answers 304 (§15.4.5) with no body,
  the ``ETag`` and the cache headers a 200 would have had, before the artifact is built. Evaluated
  only once the answer without the condition would be a 200 (§13.2.1): the job is looked up with
  the caller's access first (another client's job is a 404 whatever the condition) and a job
  without a result is a 409. An unparsable field never matches (the full answer is always right).
- ``Cache-Control``: every answer under ``/v1`` carries ``no-store`` (``security.py``: patients'
  data, no copy in any HTTP cache), these included, on 200 and 304 alike. A client that keeps an
  artifact itself (a PACS integrator, a script) revalidates it with ``If-None-Match``.
- ``ArtifactCache``: the built bytes by entity tag, least recently used out first, bounded in bytes
  (``SPINE_ARTIFACT_CACHE_MB``, 0 disables it), thread-safe, one build at a time per tag.
"""

from __future__ import annotations

import hashlib
import re
import threading
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from importlib import metadata
from typing import Annotated, Any, Literal

from fastapi import Depends, Header, Request
from fastapi.responses import Response

import spine_engine
from services.api.schemas import problem_responses
from services.db.models import Job

ArtifactKind = Literal["figure.png", "figure.svg", "sr.dcm", "figure.dcm", "fhir"]

ARTIFACT_REVISION = "7"
"""Bump when the service's code builds different bytes for the same job (the SR's content tree, the
figure's drawing, the Bundle's shape) without a new version of a library listed in ``BUILD``."""


def _version(distribution: str) -> str:
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return "-"


BUILD = ";".join(
    [f"revision={ARTIFACT_REVISION}", f"spine_engine={spine_engine.__version__}"]
    + [f"{d}={_version(d)}" for d in ("spine-reconstruction", "matplotlib", "pydicom", "highdicom")]
)
"""What builds the bytes besides the job: this service's artifact revision, the engine (its figure
renderer) and the libraries that write PNG, SVG and DICOM."""


def entity_tag(kind: ArtifactKind, job: Job, variant: str = "") -> str:
    """The strong ETag (RFC 9110 §8.8.3) of a succeeded job's artifact: ``"<kind>-<32 hex>"``, the
    digest (SHA-256, 128 bits) of the kind, the job's id, ``finished_at``, ``engine_version``, ``BUILD``
    and ``variant`` (the settings the bytes depend on, if any)."""
    finished = job.finished_at.isoformat() if job.finished_at is not None else "-"
    parts = (kind, str(job.id), finished, job.engine_version or "-", BUILD, variant)
    digest = hashlib.sha256("\x1f".join(parts).encode()).hexdigest()[:32]
    return f'"{kind.replace(".", "-")}-{digest}"'


# entity-tag = [ weak ] opaque-tag; opaque-tag = DQUOTE *etagc DQUOTE; etagc = %x21 / %x23-7E / obs-text
# (RFC 9110 §8.8.3): a comma may be inside a tag, so the list is read tag by tag, not split on commas.
_TAG = re.compile(r'[ \t]*(W/)?("[\x21\x23-\x7e\x80-\xff]*")[ \t]*(,|$)')
_EMPTY = re.compile(r"[ \t]*(,|$)")  # empty list elements are allowed (RFC 9110 §5.6.1)


def parse_if_none_match(value: str) -> Literal["*"] | list[str] | None:
    """``If-None-Match`` (RFC 9110 §13.1.2: ``"*" / #entity-tag``) as ``"*"`` or its opaque tags
    (quoted, without ``W/``); None when the field is not valid."""
    if value.strip(" \t") == "*":
        return "*"
    tags: list[str] = []
    position = 0
    while position < len(value):
        match = _TAG.match(value, position) or _EMPTY.match(value, position)
        if match is None or match.end() == position:
            return None
        if match.re is _TAG:
            tags.append(match.group(2))
        position = match.end()
    return tags


def none_match_matches(if_none_match: str, etag: str) -> bool:
    """Whether the condition ``If-None-Match`` is false for a current representation tagged ``etag``
    (then a GET answers 304, RFC 9110 §13.1.2): ``*``, or one of its tags equal to ``etag`` by the weak
    comparison (§8.8.3.2: the opaque tags are equal, ``W/`` or not)."""
    parsed = parse_if_none_match(if_none_match)
    if parsed is None:
        return False
    return parsed == "*" or etag.removeprefix("W/") in parsed


async def get_if_none_match(
    request: Request,
    if_none_match: Annotated[
        str | None,
        Header(
            alias="If-None-Match",
            description="Entity tags of copies the client holds (RFC 9110 §13.1.2), or `*`: when one matches "
            "the artifact's `ETag`, the answer is 304 with no body, and nothing is built.",
        ),
    ] = None,
) -> str | None:
    """The request's ``If-None-Match``, its field lines joined as one list (RFC 9110 §5.3); the
    parameter documents the header in the contract."""
    lines = request.headers.getlist("if-none-match")
    return ", ".join(lines) if lines else None


IfNoneMatchDep = Annotated[str | None, Depends(get_if_none_match)]


@dataclass
class _Flight:
    """One build of one tag in progress, and how many requests wait on it."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    waiters: int = 0


class ArtifactCache:
    """Built artifacts by entity tag, at most ``max_bytes`` of them, least recently used out first.
    Thread-safe (the sync routes run in the thread pool); ``get_or_build`` builds one tag once at a time,
    so that simultaneous GETs of a new SR wait for one build instead of each building it. An artifact
    larger than the bound is returned, not kept; a bound of 0 keeps nothing."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max(0, int(max_bytes))
        self._items: OrderedDict[str, bytes] = OrderedDict()
        self._size = 0
        self._lock = threading.Lock()
        self._flights: dict[str, _Flight] = {}
        self.hits = 0
        self.misses = 0

    @property
    def size_bytes(self) -> int:
        return self._size

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: object) -> bool:
        return key in self._items

    def get(self, key: str) -> bytes | None:
        with self._lock:
            value = self._items.get(key)
            if value is None:
                self.misses += 1
                return None
            self._items.move_to_end(key)
            self.hits += 1
            return value

    def put(self, key: str, value: bytes) -> None:
        if len(value) > self.max_bytes:
            return
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self._size -= len(old)
            self._items[key] = value
            self._size += len(value)
            while self._size > self.max_bytes:
                _, evicted = self._items.popitem(last=False)
                self._size -= len(evicted)

    def get_or_build(self, key: str, build: Callable[[], bytes]) -> bytes:
        """The bytes of ``key``, built by ``build`` (outside the cache's lock) when they are not kept."""
        value = self.get(key)
        if value is not None:
            return value
        if self.max_bytes == 0:
            return build()
        with self._lock:
            flight = self._flights.setdefault(key, _Flight())
            flight.waiters += 1
        try:
            with flight.lock:
                with self._lock:  # built meanwhile by the request this one waited for
                    value = self._items.get(key)
                    if value is not None:
                        self._items.move_to_end(key)
                if value is None:
                    value = build()
                    self.put(key, value)
                return value
        finally:
            with self._lock:
                flight.waiters -= 1
                if flight.waiters == 0:
                    del self._flights[key]


async def get_artifact_cache(request: Request) -> ArtifactCache:
    cache: ArtifactCache = request.app.state.artifact_cache
    return cache


ArtifactCacheDep = Annotated[ArtifactCache, Depends(get_artifact_cache)]


def artifact_response(
    kind: ArtifactKind, job: Job, if_none_match: str | None, cache: ArtifactCache, build: Callable[[], bytes],
    media_type: str, headers: Mapping[str, str] | None = None, variant: str = "",
) -> Response:  # fmt: skip
    """A succeeded job's artifact, its access already checked: 304 when ``If-None-Match`` matches its
    ETag (RFC 9110 §13.1.2, §15.4.5: no body, no build), else 200 with the bytes (cached or built).
    ``variant`` names the settings the bytes depend on (``entity_tag``)."""
    etag = entity_tag(kind, job, variant)
    if if_none_match is not None and none_match_matches(if_none_match, etag):
        return Response(status_code=304, headers={"ETag": etag})
    body = cache.get_or_build(etag, build)
    return Response(body, media_type=media_type, headers={**(headers or {}), "ETag": etag})


CONDITIONAL = (
    " The answer carries a strong `ETag` (its bytes never change once the job has succeeded); a GET whose "
    "`If-None-Match` matches it is answered 304 with no body, without building the artifact again."
)
"""Appended to each artifact route's description."""

ETAG_HEADER = {
    "description": "Strong entity tag of the artifact (RFC 9110 §8.8.3): the same for the same bytes, which "
    "never change once the job has succeeded; send it back in `If-None-Match`.",
    "schema": {"type": "string"},
}


def artifact_responses(
    media_type: str, description: str, schema: Mapping[str, Any]
) -> dict[int | str, dict[str, Any]]:
    """The OpenAPI ``responses`` of an artifact route: 200 (``schema`` under ``media_type``:
    ``schemas.BINARY_SCHEMA`` for bytes, ``TEXT_SCHEMA`` for a text document, or a JSON schema) and
    304 with their ``ETag``, and the problems."""
    content: dict[str, Any] = {media_type: {"schema": dict(schema)}}
    return {
        200: {"content": content, "description": description, "headers": {"ETag": ETAG_HEADER}},
        304: {
            "description": "Not Modified (RFC 9110 §15.4.5): `If-None-Match` matched the artifact's `ETag`; no body.",
            "headers": {"ETag": ETAG_HEADER},
        },
        **problem_responses(404, 409, 422),
    }
