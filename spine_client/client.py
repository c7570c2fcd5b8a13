"""``SpineClient``: the service's HTTP API for scripts (httpx).

Every request is retried with exponential backoff and jitter on connection errors, timeouts,
429 and 5xx, honouring ``Retry-After``: attempt n (n = 1, 2, …) failed waits
min(max_backoff, backoff·2ⁿ⁻¹)·u seconds, u uniform in [0.5, 1), or the ``Retry-After`` (up to
``max_retry_after``). Retrying a POST is safe: ``submit`` and ``submit_batch``
send an ``Idempotency-Key`` (a new UUID unless given), so the service returns the job it already
made instead of making a second one; cancelling twice is a no-op. Errors are typed
(``spine_client.errors``) and carry the server's problem+json.
"""

from __future__ import annotations

import os
import random
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from datetime import datetime
from email.utils import parsedate_to_datetime
from pathlib import Path
from typing import Any, Literal, TypeVar
from urllib.parse import urlsplit

import httpx
from pydantic import BaseModel

from spine_client import optional
from spine_client.errors import InvalidRequest, ServiceUnreachable, UnexpectedResponse, WaitTimeout, error_for
from spine_client.models import BatchEntry, BatchResult, Job, JobPage

ModelT = TypeVar("ModelT", bound=BaseModel)

DEFAULT_URL = "http://127.0.0.1:8000"
URL_ENV = "SPINE_URL"
API_KEY_ENV = "SPINE_API_KEY"
USER_AGENT = "spine-client/1"
BATCH_CHUNK = 500
"""Payloads per POST /v1/jobs/batch request (the service takes up to 1,000 and 16 MiB)."""
LAST_LOOK_S = 1.0
"""Shortest time limit of a request sent before a deadline (``request(deadline=)``), however little time
is left: a look at a job (one GET, answered in milliseconds by a healthy service) is still worth a try."""


def retry_after_seconds(value: str | None) -> float | None:
    """Seconds a ``Retry-After`` header asks to wait (delta-seconds or an HTTP date), or None."""
    if not value:
        return None
    value = value.strip()
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        return max(0.0, parsedate_to_datetime(value).timestamp() - time.time())
    except (TypeError, ValueError):
        return None


def service_url(base_url: str | None = None) -> str:
    """The service's base URL: ``base_url``, else ``$SPINE_URL``, else ``DEFAULT_URL``, without a
    trailing slash."""
    return (base_url or os.environ.get(URL_ENV) or DEFAULT_URL).rstrip("/")


def base_url_problem(url: str) -> str | None:
    """Why ``url`` cannot be the service's base URL, or None. Never repeats the URL (it may hold a
    password)."""
    if any(ch.isspace() or ord(ch) < 32 for ch in url):
        return "it contains spaces or control characters"
    try:
        parts = urlsplit(url)
        parts.port  # noqa: B018 - raises ValueError for a port out of range or not a number
    except ValueError:
        return "it is not a URL (is the port a number from 1 to 65535?)"
    if parts.scheme.lower() not in ("http", "https"):
        return f"it must be an http:// or https:// URL, such as {DEFAULT_URL}"
    if "@" in parts.netloc:
        return ("it must not carry a user name or password (user:password@ would be sent instead of the API key; "
                "give the key as the API key)")  # fmt: skip
    if not parts.hostname:
        return f"it has no host, as in {DEFAULT_URL}"
    return None


class SpineClient:
    """Client of one service. ``base_url`` defaults to ``$SPINE_URL`` (else http://127.0.0.1:8000)
    and ``api_key`` to ``$SPINE_API_KEY``, sent as ``Authorization: Bearer <key>``.

    ``retries`` is the number of attempts after the first; waits grow as ``backoff``·2ⁿ (with jitter)
    up to ``max_backoff``; a ``Retry-After`` is honoured up to ``max_retry_after`` seconds. A base URL
    that is not http(s), or that carries ``user:password@`` (which httpx would send as Basic
    authentication instead of the key), is a ``ValueError`` (``base_url_problem``).
    """

    def __init__(
        self,
        base_url: str | None = None,
        api_key: str | None = None,
        *,
        timeout: float = 30.0,
        retries: int = 5,
        backoff: float = 0.5,
        max_backoff: float = 30.0,
        max_retry_after: float = 120.0,
        transport: httpx.BaseTransport | None = None,
        sleep: Callable[[float], None] = time.sleep,
    ):
        self.base_url = service_url(base_url)
        problem = base_url_problem(self.base_url)
        if problem is not None:
            raise ValueError(f"the service URL is not usable: {problem}")
        if timeout <= 0 or retries < 0:
            raise ValueError(f"timeout must be above 0 s (not {timeout}) and retries 0 or more (not {retries})")
        key = api_key if api_key is not None else os.environ.get(API_KEY_ENV)
        headers = {"user-agent": USER_AGENT, "accept": "application/json, application/problem+json"}
        if key:
            headers["authorization"] = f"Bearer {key}"
        self.retries = retries
        self.timeout = timeout
        self.backoff = backoff
        self.max_backoff = max_backoff
        self.max_retry_after = max_retry_after
        self._sleep = sleep
        self._http = httpx.Client(base_url=self.base_url, timeout=timeout, headers=headers, transport=transport)

    # -- plumbing
    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> SpineClient:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def retry_wait(self, attempt: int, response: httpx.Response | None) -> float:
        """Seconds to wait after failed attempt ``attempt`` (1, 2, …): the response's ``Retry-After``
        (at most ``max_retry_after``), else min(max_backoff, backoff·2^(attempt−1)) times a jitter
        in [0.5, 1), so that the retries of many clients spread out."""
        asked = retry_after_seconds(response.headers.get("retry-after")) if response is not None else None
        if asked is not None:
            return min(asked, self.max_retry_after)
        delay = min(self.max_backoff, self.backoff * 2 ** (attempt - 1))
        return delay * (0.5 + random.random() / 2)

    def request(
        self,
        method: str,
        path: str,
        *,
        json: Any = None,
        params: Mapping[str, Any] | None = None,
        headers: Mapping[str, str] | None = None,
        deadline: float | None = None,
    ) -> httpx.Response:
        """Send a request with retries; return the 2xx response or raise a typed error.

        ``deadline`` (a ``time.monotonic()`` instant, ``wait``'s) bounds the retries: none waits past it,
        and an attempt's time limit is at most the time left (``LAST_LOOK_S`` at least); the last error
        is raised then, as after the last retry."""
        attempt = 0
        while True:
            attempt += 1
            limit = self.timeout
            if deadline is not None:
                limit = max(LAST_LOOK_S, min(limit, deadline - time.monotonic()))
            try:
                response = self._http.request(method, path, json=json, params=params, headers=headers, timeout=limit)
            except httpx.TransportError as exc:
                pause = None if attempt > self.retries else self.retry_wait(attempt, None)
                if pause is None or not _before(deadline, pause):
                    raise ServiceUnreachable(f"{method} {self.base_url}{path}: {type(exc).__name__}: {exc}") from exc
                self._sleep(pause)
                continue
            if (response.status_code == 429 or response.status_code >= 500) and attempt <= self.retries:
                pause = self.retry_wait(attempt, response)
                if _before(deadline, pause):
                    self._sleep(pause)
                    continue
            if response.status_code >= 400:
                raise error_for(response)
            if response.status_code >= 300:  # not followed: a POST must not turn into a GET elsewhere
                raise UnexpectedResponse(
                    f"{method} {self.base_url}{path} answered {response.status_code}, a redirect to "
                    f"{response.headers.get('location', '(no Location)')}: give the service's URL itself"
                )
            return response

    def _json(self, method: str, path: str, *, expect: type[BaseModel] | None = None, **kwargs: Any) -> Any:
        """The JSON body of a successful request, as sent (checked to be an ``expect`` when given);
        ``UnexpectedResponse`` when it is not JSON, or not that."""
        response = self.request(method, path, **kwargs)
        try:
            body = response.json()
            if expect is not None:
                expect.model_validate(body)
        except ValueError:
            raise self._unexpected(response, f"a {expect.__name__}" if expect is not None else "JSON") from None
        return body

    def _model(self, model: type[ModelT], method: str, path: str, **kwargs: Any) -> ModelT:
        """The body of a successful request as the contract's ``model``; ``UnexpectedResponse`` otherwise."""
        response = self.request(method, path, **kwargs)
        try:
            return model.model_validate_json(response.content)
        except ValueError:
            raise self._unexpected(response, f"a {model.__name__}") from None

    def _content(self, method: str, path: str, media_types: tuple[str, ...], **kwargs: Any) -> bytes:
        """The body of a successful request of one of ``media_types``; ``UnexpectedResponse`` otherwise."""
        response = self.request(method, path, **kwargs)
        media = response.headers.get("content-type", "").split(";", 1)[0].strip().lower()
        if response.status_code >= 300 or media not in media_types:
            raise self._unexpected(response, " or ".join(media_types))
        return response.content

    def _unexpected(self, response: httpx.Response, expected: str) -> UnexpectedResponse:
        media = response.headers.get("content-type", "no content type")
        return UnexpectedResponse(
            f"{response.request.method} {response.request.url} answered {response.status_code} ({media}), not "
            f"{expected} of the spine service's API: is {self.base_url} the service's URL? "
            f"{response.text[:200]!r}"
        )

    # -- jobs
    def submit(self, payload: Mapping[str, Any], *, idempotency_key: str | None = None) -> Job:
        """POST /v1/jobs; the job as queued (or as it is, when the key was used before with this body)."""
        key = idempotency_key or str(uuid.uuid4())
        return self._model(Job, "POST", "/v1/jobs", json=payload, headers={"idempotency-key": key})

    def submit_batch(
        self, payloads: Sequence[Mapping[str, Any]], *, idempotency_key: str | None = None, chunk: int = BATCH_CHUNK
    ) -> BatchResult:
        """POST /v1/jobs/batch in chunks of ``chunk``; entries are indexed in ``payloads``' order.

        A request the service refuses as too large (413: over ``SPINE_MAX_BATCH_BODY_BYTES``) is sent
        again as two halves, down to single payloads; a payload too large alone is a rejected entry
        (status 413, the service's problem), so one oversized payload does not sink the others."""
        key = idempotency_key or str(uuid.uuid4())
        results: list[BatchEntry] = []
        for n, start in enumerate(range(0, len(payloads), chunk)):
            results += self._batch_part(list(payloads[start : start + chunk]), start, f"{key}.{n}")
        accepted = sum(1 for e in results if e.status == 202)
        return BatchResult(accepted=accepted, rejected=len(results) - accepted, results=results)

    def _batch_part(self, part: list[Mapping[str, Any]], start: int, key: str) -> list[BatchEntry]:
        """The entries of one batch request of ``part`` (``payloads[start:]``), halved on a 413; a half's
        Idempotency-Key is its parent's with ``/offset+count`` appended, the same on a rerun."""
        try:
            body = self._model(BatchResult, "POST", "/v1/jobs/batch", json={"jobs": part},
                               headers={"idempotency-key": key})  # fmt: skip
        except InvalidRequest as exc:
            if exc.status != 413:
                raise
            if len(part) == 1:
                return [BatchEntry(index=start, status=exc.status, problem=exc.problem)]
            half = (len(part) + 1) // 2
            return [*self._batch_part(part[:half], start, f"{key}/0+{half}"),
                    *self._batch_part(part[half:], start + half, f"{key}/{half}+{len(part) - half}")]  # fmt: skip
        return [entry.model_copy(update={"index": entry.index + start}) for entry in body.results]

    def get_json(self, job_id: uuid.UUID | str, *, deadline: float | None = None) -> dict[str, Any]:
        """GET /v1/jobs/{id} as the server sent it (checked to be a ``Job``); ``deadline`` as in ``request``."""
        body: dict[str, Any] = self._json("GET", f"/v1/jobs/{job_id}", expect=Job, deadline=deadline)
        return body

    def get(self, job_id: uuid.UUID | str, *, deadline: float | None = None) -> Job:
        """GET /v1/jobs/{id}; ``deadline`` as in ``request``."""
        return self._model(Job, "GET", f"/v1/jobs/{job_id}", deadline=deadline)

    def wait(
        self,
        job_id: uuid.UUID | str,
        timeout: float | None = None,
        *,
        poll_interval: float = 0.2,
        max_poll_interval: float = 2.0,
    ) -> Job:
        """Poll until the job is succeeded, failed or cancelled; ``WaitTimeout`` after ``timeout`` s. A
        look that fails (no answer, 5xx) is retried until then only: past ``timeout`` its error is raised."""
        deadline = None if timeout is None else time.monotonic() + timeout
        interval = poll_interval
        while True:
            job = self.get(job_id, deadline=deadline)
            if job.finished:
                return job
            if deadline is not None and time.monotonic() >= deadline:
                raise WaitTimeout(job, float(timeout or 0))
            pause = interval if deadline is None else max(0.0, min(interval, deadline - time.monotonic()))
            self._sleep(pause)
            interval = min(max_poll_interval, interval * 1.5)

    def list(
        self,
        *,
        status: str | Sequence[str] | None = None,
        created_after: datetime | str | None = None,
        created_before: datetime | str | None = None,
        limit: int = 50,
        cursor: str | None = None,
        study_instance_uid: str | None = None,
        accession_number: str | None = None,
        patient_id: str | None = None,
    ) -> JobPage:
        """One page of GET /v1/jobs, newest first; the DICOM filters match the job's ``study``."""
        params: dict[str, Any] = {"limit": limit}
        if status:
            params["status"] = [status] if isinstance(status, str) else list(status)
        for name, value in (("created_after", created_after), ("created_before", created_before)):
            if value is not None:
                params[name] = value.isoformat() if isinstance(value, datetime) else value
        dicom = {"study_instance_uid": study_instance_uid, "accession_number": accession_number,
                 "patient_id": patient_id}  # fmt: skip
        params.update({k: v for k, v in dicom.items() if v is not None})
        if cursor:
            params["cursor"] = cursor
        return self._model(JobPage, "GET", "/v1/jobs", params=params)

    def iter_jobs(self, *, page_size: int = 100, **filters: Any) -> Iterator[Job]:
        """Every job matching the filters of ``list``, following the cursor."""
        cursor = None
        while True:
            page = self.list(limit=page_size, cursor=cursor, **filters)
            yield from page.jobs
            if not page.next_cursor:
                return
            cursor = page.next_cursor

    def cancel(self, job_id: uuid.UUID | str) -> Job:
        """POST /v1/jobs/{id}/cancel; ``JobNotCancellable`` when it already succeeded or failed."""
        return self._model(Job, "POST", f"/v1/jobs/{job_id}/cancel")

    def store_dicom(self, job_id: uuid.UUID | str) -> Job:
        """POST /v1/jobs/{id}/dicom-store: store a succeeded job's results (SR and figure) in the service's
        PACS again, by a new run of attempts; the job as GET answers it, its ``dicom_stores`` ending with the
        request's entry (``requested_by``, due now). ``DicomStorePending`` while an attempt is due or under
        way (also when a retry of this request finds the first one taken), ``NoPatientIdentity`` for results
        never stored, ``JobHasNoResult`` unless succeeded, ``NotFound`` for no such job or a service that
        stores no results (its problem type says which)."""
        return self._model(Job, "POST", f"/v1/jobs/{job_id}/dicom-store")

    # -- exports
    def fhir(self, job_id: uuid.UUID | str) -> dict[str, Any]:
        """GET /v1/jobs/{id}/fhir: the FHIR R4 Bundle of a succeeded job's measures."""
        body = self._json("GET", f"/v1/jobs/{job_id}/fhir")
        if not isinstance(body, dict) or body.get("resourceType") != "Bundle":
            raise UnexpectedResponse(f"GET {self.base_url}/v1/jobs/{job_id}/fhir answered JSON that is not a FHIR "
                                     f"Bundle: {str(body)[:200]!r}")  # fmt: skip
        return body

    def figure(self, job_id: uuid.UUID | str, fmt: Literal["png", "svg"] = "png") -> bytes:
        media = {"png": ("image/png",), "svg": ("image/svg+xml",)}[fmt]
        return self._content("GET", f"/v1/jobs/{job_id}/figure.{fmt}", media)

    def sr(self, job_id: uuid.UUID | str) -> bytes:
        """GET /v1/jobs/{id}/sr.dcm: the result as a DICOM SR (TID 1500 Measurement Report), Part 10 bytes."""
        return self._content("GET", f"/v1/jobs/{job_id}/sr.dcm", ("application/dicom",),
                             headers={"accept": "application/dicom"})  # fmt: skip

    def figure_dicom(self, job_id: uuid.UUID | str) -> bytes:
        """GET /v1/jobs/{id}/figure.dcm: the figure as a DICOM Secondary Capture, Part 10 bytes."""
        return self._content("GET", f"/v1/jobs/{job_id}/figure.dcm", ("application/dicom",),
                             headers={"accept": "application/dicom"})  # fmt: skip

    def submit_dicom(
        self,
        landmarks_csv: str | Path,
        pa_dicom: str | Path,
        lateral_dicom: str | Path | None = None,
        *,
        units: Literal["px", "mm"] = "px",
        base: Mapping[str, Any] | None = None,
        idempotency_key: str | None = None,
    ) -> tuple[Job, dict[str, Any]]:
        """Submit a landmark CSV with the spacing, orientation, geometry and study read from the
        radiographs' DICOM headers on this machine (``spine_client.dicom_input``, the ``[dicom]`` extra:
        ``MissingExtra`` without pydicom), what was read sent as
        the job's ``dicom`` block; returns the job and what was read (``conflicts`` lists header values
        that differ from ``base``'s)."""
        read = optional.dicom_input().payload_from_dicom
        payload, provenance = read(landmarks_csv, pa_dicom, lateral_dicom, units=units, base=dict(base or {}))
        return self.submit({**payload, "dicom": provenance}, idempotency_key=idempotency_key), provenance


def _before(deadline: float | None, pause: float) -> bool:
    """Whether a retry after ``pause`` seconds still starts before ``deadline`` (always, without one)."""
    return deadline is None or time.monotonic() + pause < deadline
