"""A succeeded job's artifacts (figure.png|svg, sr.dcm, figure.dcm, fhir) under conditional GET
(RFC 9110 §8.8.3 ETag, §13.1.2 If-None-Match, §15.4.5 304) and the bounded cache of their bytes
(``services/api/artifacts.py``): the real app in process on a fresh embedded database, jobs made
succeeded by writing a real result on their row."""

from __future__ import annotations

import re
import threading
import time
import uuid
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update

from services.api import artifacts
from services.api.app import create_app
from services.api.artifacts import ArtifactCache, none_match_matches, parse_if_none_match
from services.api.routes import dicom as dicom_routes
from services.core.config import Settings
from services.db.engine import session_scope
from services.db.migrate import upgrade
from services.db.models import Job as JobRow
from spine_engine import register
from tests.conftest import make_key, problem_of, spine_payload

KINDS = ["figure.png", "figure.svg", "sr.dcm", "figure.dcm", "fhir"]
ETAG = re.compile(r'^"[a-z-]+-[0-9a-f]{32}"$')


@pytest.fixture(scope="module")
def result() -> dict[str, Any]:
    """A real reconstruction as the worker stores it."""
    return register(spine_payload(curve_mm=25.0))


class App:
    """The API on a fresh embedded database, with two clients' keys."""

    def __init__(self, tmp_path: Path, **settings: Any):
        self.settings = Settings(data_dir=tmp_path, api_key_cache_s=0, **settings)
        upgrade(self.settings, quiet=True)
        self.client = TestClient(create_app(self.settings))
        self.a = {"Authorization": f"Bearer {make_key(self.settings, 'clinic-a')}"}
        self.b = {"Authorization": f"Bearer {make_key(self.settings, 'clinic-b')}"}

    @property
    def cache(self) -> ArtifactCache:
        cache: ArtifactCache = self.client.app.state.artifact_cache  # type: ignore[attr-defined]
        return cache

    def succeeded_job(
        self, result: dict[str, Any], headers: dict[str, str] | None = None, payload: dict[str, Any] | None = None
    ) -> str:
        """A job of clinic a (or of ``headers``' client) made succeeded with ``result``, as the worker leaves it."""
        body = payload or spine_payload(curve_mm=25.0)
        response = self.client.post("/v1/jobs", json=body, headers=headers or self.a)
        job_id = str(response.json()["id"])
        finished = datetime(2026, 12, 2, 9, 30, 0, 123456, tzinfo=UTC)
        with session_scope(self.settings) as session:
            session.execute(update(JobRow).where(JobRow.id == uuid.UUID(job_id)).values(
                status="succeeded", result=result, started_at=finished, finished_at=finished, attempts=1,
                engine_version="test"))  # fmt: skip
        return job_id

    def get(
        self, job_id: str, kind: str, if_none_match: str | None = None, headers: dict[str, str] | None = None
    ) -> Any:
        h = dict(headers or self.a)
        if if_none_match is not None:
            h["If-None-Match"] = if_none_match
        return self.client.get(f"/v1/jobs/{job_id}/{kind}", headers=h)


@pytest.fixture
def app(tmp_path: Path) -> Iterator[App]:
    a = App(tmp_path)
    with a.client:
        yield a


@pytest.fixture
def uncached(tmp_path: Path) -> Iterator[App]:
    """The same with SPINE_ARTIFACT_CACHE_MB=0: every 200 builds its artifact."""
    a = App(tmp_path, artifact_cache_mb=0)
    with a.client:
        yield a


# ------------------------------------------------------------------ the routes


@pytest.mark.parametrize("kind", KINDS)
def test_an_artifact_has_a_stable_strong_etag_and_a_match_is_a_304(app: App, result: dict[str, Any], kind: str) -> None:
    job_id = app.succeeded_job(result)
    first, second = app.get(job_id, kind), app.get(job_id, kind)
    assert first.status_code == second.status_code == 200, first.text
    etag = first.headers["etag"]
    assert ETAG.match(etag) and second.headers["etag"] == etag and second.content == first.content
    assert app.cache.hits >= 1  # the second GET was served from the cache

    for condition in (etag, "*", f'"other", {etag}', f"W/{etag}", f'"a,b" , ,{etag}'):
        not_modified = app.get(job_id, kind, condition)
        assert not_modified.status_code == 304, condition
        assert not_modified.content == b"" and "content-type" not in not_modified.headers
        assert not_modified.headers["etag"] == etag
        assert not_modified.headers["cache-control"] == first.headers["cache-control"] == "no-store"
    for condition in ('"other"', etag.upper(), f"{etag}x", "not a tag", '"unterminated'):
        assert app.get(job_id, kind, condition).status_code == 200, condition
    # two field lines are one list (RFC 9110 §5.3)
    two_lines = app.client.get(f"/v1/jobs/{job_id}/{kind}", headers=[
        *app.a.items(), ("If-None-Match", '"other"'), ("If-None-Match", etag)])  # fmt: skip
    assert two_lines.status_code == 304


@pytest.mark.parametrize("kind", ["sr.dcm", "figure.dcm"])
def test_a_page_of_another_origin_reads_a_downloads_name(tmp_path: Path, result: dict[str, Any], kind: str) -> None:
    """A page of an allowed origin (``SPINE_CORS_ORIGINS``) downloading a DICOM file may read its
    ``Content-Disposition`` (RFC 6266 §4.3: the file name it saves it under): the header is among those
    the CORS answer exposes (Fetch standard, "CORS-safelisted response-header name" does not include it,
    so a browser hides it from the page unless ``Access-Control-Expose-Headers`` names it)."""
    origin = {"Origin": "https://viewer.example"}
    app = App(tmp_path, cors_origins="https://viewer.example")
    with app.client:
        job_id = app.succeeded_job(result)
        path = f"/v1/jobs/{job_id}/{kind}"
        asks = {"Access-Control-Request-Method": "GET", "Access-Control-Request-Headers": "authorization"}
        preflight = app.client.options(path, headers={**origin, **asks})
        assert preflight.status_code == 200, preflight.text
        answer = app.get(job_id, kind, headers={**origin, **app.a})
    assert answer.status_code == 200, answer.text
    assert answer.headers["access-control-allow-origin"] == "https://viewer.example"
    assert answer.headers["content-disposition"] == f'attachment; filename="{job_id}-{kind}"'
    exposed = {h.strip().lower() for h in answer.headers["access-control-expose-headers"].split(",")}
    assert "content-disposition" in exposed, exposed


def test_every_build_of_an_artifact_is_the_same_bytes(uncached: App, result: dict[str, Any]) -> None:
    """What a strong ETag promises (RFC 9110 §8.8.1): built twice (no cache), the same bytes."""
    job_id = uncached.succeeded_job(result)
    for kind in KINDS:
        first, second = uncached.get(job_id, kind), uncached.get(job_id, kind)
        assert first.content == second.content and first.headers["etag"] == second.headers["etag"], kind
    assert len(uncached.cache) == 0


def test_a_match_is_answered_without_building(
    uncached: App, result: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    builds: list[uuid.UUID] = []

    def counting_job_sr(job_id: uuid.UUID, *args: Any) -> bytes:
        builds.append(job_id)
        return b"DICM-stand-in"

    monkeypatch.setattr(dicom_routes, "job_sr", counting_job_sr)
    job_id = uncached.succeeded_job(result)
    etag = uncached.get(job_id, "sr.dcm").headers["etag"]
    assert len(builds) == 1
    for condition in (etag, "*"):
        assert uncached.get(job_id, "sr.dcm", condition).status_code == 304
    assert len(builds) == 1  # no build for a 304
    assert uncached.get(job_id, "sr.dcm").status_code == 200 and len(builds) == 2  # no cache: built again


def test_the_cache_serves_the_second_get(app: App, result: dict[str, Any], monkeypatch: pytest.MonkeyPatch) -> None:
    builds: list[uuid.UUID] = []
    monkeypatch.setattr(dicom_routes, "job_sr", lambda job_id, *args: builds.append(job_id) or b"DICM-stand-in")
    job_id = app.succeeded_job(result)
    assert app.get(job_id, "sr.dcm").content == app.get(job_id, "sr.dcm").content == b"DICM-stand-in"
    assert len(builds) == 1


def test_another_clients_job_is_404_whatever_the_condition(app: App, result: dict[str, Any]) -> None:
    job_id = app.succeeded_job(result)
    unknown = str(uuid.uuid4())
    for kind in ("fhir", "figure.svg"):
        etag = app.get(job_id, kind).headers["etag"]
        for condition in (etag, "*"):
            theirs = app.get(job_id, kind, condition, headers=app.b)
            missing = app.get(unknown, kind, condition, headers=app.b)
            assert theirs.status_code == missing.status_code == 404
            assert problem_of(theirs)["detail"] == problem_of(missing)["detail"].replace(unknown, job_id)
            assert "etag" not in theirs.headers


def test_a_job_without_a_result_is_409_whatever_the_condition(app: App) -> None:
    queued = app.client.post("/v1/jobs", json=spine_payload(), headers=app.a).json()["id"]
    response = app.get(queued, "sr.dcm", "*")
    assert response.status_code == 409 and problem_of(response)["type"].endswith("/job-has-no-result")


def test_another_jobs_or_artifacts_etag_does_not_match(app: App, result: dict[str, Any]) -> None:
    one, other = app.succeeded_job(result), app.succeeded_job(result)
    etags = {(job, kind): app.get(job, kind).headers["etag"] for job in (one, other) for kind in ("fhir", "figure.svg")}
    assert len(set(etags.values())) == 4
    assert app.get(other, "fhir", etags[(one, "fhir")]).status_code == 200
    assert app.get(one, "fhir", etags[(one, "figure.svg")]).status_code == 200


def test_the_fhir_subject_system_is_the_setting_and_in_the_etag(tmp_path: Path, result: dict[str, Any]) -> None:
    """SPINE_PATIENT_ID_SYSTEM is each subject's identifier system; the same job's Bundle under another
    setting is other bytes, so its strong ETag differs too (RFC 9110 §8.8.1). Two API processes on one
    database, one without the setting and one with it."""
    from fhir.resources.R4B.bundle import Bundle

    study = {"study_instance_uid": "1.2.826.0.1.3680043.8.498.1", "patient_id": "P-1", "study_date": "2026-11-30"}
    job_id = ""
    answers = {}
    for system in (None, "urn:oid:1.2.3.4.5"):
        app = App(tmp_path, patient_id_system=system)
        with app.client:
            if not job_id:
                job_id = app.succeeded_job(result, payload={**spine_payload(curve_mm=25.0), "study": study})
            answers[system] = app.get(job_id, "fhir")
    assert answers[None].headers["etag"] != answers["urn:oid:1.2.3.4.5"].headers["etag"]
    for system, response in answers.items():
        assert response.status_code == 200
        bundle = response.json()
        Bundle.model_validate(bundle)
        identifier = {"value": "P-1"} if system is None else {"system": system, "value": "P-1"}
        assert all(e["resource"]["subject"]["identifier"] == identifier for e in bundle["entry"])
        assert {e["resource"]["effectiveDateTime"] for e in bundle["entry"]} == {"2026-11-30"}  # the study's date


def test_a_fhir_bundle_without_study_is_effective_at_the_jobs_creation(app: App, result: dict[str, Any]) -> None:
    job_id = app.succeeded_job(result)
    created = app.client.get(f"/v1/jobs/{job_id}", headers=app.a).json()["created_at"]
    bundle = app.get(job_id, "fhir").json()
    effective = {datetime.fromisoformat(e["resource"]["effectiveDateTime"]) for e in bundle["entry"]}
    assert effective == {datetime.fromisoformat(created)}
    assert all("subject" not in e["resource"] for e in bundle["entry"])


def test_a_patient_id_system_must_be_an_absolute_uri() -> None:
    for value in ("hospital ids", "1.2.3.4", "://x"):
        with pytest.raises(ValueError, match="absolute URI"):
            Settings(patient_id_system=value)
    assert Settings(patient_id_system="").patient_id_system is None


# ------------------------------------------------------------------ the functions


@pytest.mark.parametrize(
    ("field", "parsed"),
    [
        ("*", "*"),
        (" \t* ", "*"),
        ('"a"', ['"a"']),
        ('W/"a", "b"', ['"a"', '"b"']),
        ('"a,b", W/"c"', ['"a,b"', '"c"']),  # a comma inside a tag is part of it
        (', "a" ,, "b",', ['"a"', '"b"']),  # empty list elements (RFC 9110 §5.6.1)
        ("", []),
        ('"a" "b"', None),
        ("a", None),
        ('"a', None),
        ('*, "a"', None),
        ('w/"a"', None),
        ('"a\x7fb"', None),
    ],
)
def test_if_none_match_parsing(field: str, parsed: Any) -> None:
    assert parse_if_none_match(field) == parsed


def test_weak_comparison_and_the_wildcard() -> None:
    assert none_match_matches('W/"x-1"', '"x-1"') and none_match_matches("*", '"x-1"')
    assert not none_match_matches('"x-2"', '"x-1"') and not none_match_matches("x-1", '"x-1"')


def test_the_etag_names_what_determines_the_bytes() -> None:
    job = JobRow(id=uuid.uuid4(), finished_at=datetime(2026, 12, 2, tzinfo=UTC), engine_version="1.0")
    tag = artifacts.entity_tag("sr.dcm", job)
    assert ETAG.match(tag) and tag.startswith('"sr-dcm-') and tag == artifacts.entity_tag("sr.dcm", job)
    assert tag != artifacts.entity_tag("figure.dcm", job)
    for change in ({"id": uuid.uuid4()}, {"finished_at": datetime(2026, 12, 3, tzinfo=UTC)}, {"engine_version": "1.1"}):
        other = JobRow(**{"id": job.id, "finished_at": job.finished_at, "engine_version": "1.0", **change})
        assert artifacts.entity_tag("sr.dcm", other) != tag, change


def test_the_cache_keeps_at_most_its_bound_least_recently_used_out_first() -> None:
    cache = ArtifactCache(100)
    for key in "abcd":
        cache.put(key, key.encode() * 30)  # 30 bytes each: the fourth evicts the first
    assert "a" not in cache and len(cache) == 3 and cache.size_bytes == 90
    assert cache.get("b") == b"b" * 30  # b is now the most recent: e goes in, c goes out
    cache.put("e", b"e" * 30)
    assert [k for k in "abcde" if k in cache] == ["b", "d", "e"] and cache.size_bytes == 90
    cache.put("big", b"x" * 101)  # larger than the bound: not kept, nothing evicted for it
    assert "big" not in cache and len(cache) == 3
    cache.put("d", b"d" * 70)  # replacing a key counts its new size: b, the least recent, goes out
    assert [k for k in "bde" if k in cache] == ["d", "e"] and cache.size_bytes == 100
    assert cache.get_or_build("f", lambda: b"f" * 40) == b"f" * 40 and cache.size_bytes <= 100
    for _ in range(200):
        cache.put(uuid.uuid4().hex, b"z" * 7)
        assert cache.size_bytes <= 100
    off = ArtifactCache(0)
    off.put("a", b"a")
    assert len(off) == 0 and off.get_or_build("a", lambda: b"b") == b"b" and len(off) == 0


def test_simultaneous_gets_of_one_tag_build_it_once() -> None:
    cache = ArtifactCache(1_000_000)
    release = threading.Event()
    builds: list[int] = []

    def build() -> bytes:
        builds.append(1)
        assert release.wait(30)
        return b"sr bytes"

    results: list[bytes] = []
    threads = [threading.Thread(target=lambda: results.append(cache.get_or_build("tag", build))) for _ in range(8)]
    for t in threads:
        t.start()
    deadline = time.monotonic() + 30
    while not (cache._flights.get("tag") and cache._flights["tag"].waiters == 8):  # every thread is in
        assert time.monotonic() < deadline, "the threads did not all reach the build"
        time.sleep(0.01)
    release.set()
    for t in threads:
        t.join(30)
    assert results == [b"sr bytes"] * 8 and len(builds) == 1 and cache._flights == {}


def test_every_artifact_of_a_job_whose_spacing_came_from_its_film(app: App, tmp_path: Path) -> None:
    """A job whose payload has px landmarks and no spacing (the film's header gave it, recorded in the
    job's ``dicom``): every artifact is built from the payload the job ran with (``services.db.job_forms``),
    so the figure does not fail on the missing spacing, and the SR references the film."""
    import highdicom as hd

    from services.dicom.sr import CORNERSTONE_COBB_ANGLE
    from spine_client.dicom_input import payload_from_dicom
    from tools.dicom import synthetic

    film = synthetic.radiograph(imager_pixel_spacing=(0.15, 0.15), rows=3200, columns=1200)  # the landmarks on it
    synthetic.write(film, tmp_path / "pa.dcm")
    points = spine_payload(curve_mm=25.0)["pa"]["landmarks"]
    (tmp_path / "lm.csv").write_text("".join(f"{p['level']},{p['point'][0] / 0.15},{p['point'][1] / 0.15}\n"
                                             for p in points))  # fmt: skip
    payload, dicom = payload_from_dicom(tmp_path / "lm.csv", tmp_path / "pa.dcm")
    del payload["pa"]["pixel_spacing"]
    response = app.client.post("/v1/jobs", json={**payload, "dicom": dicom}, headers=app.a)
    assert response.status_code == 202, response.text
    job_id = str(response.json()["id"])
    run = register({**payload, "pa": {**payload["pa"], "pixel_spacing": [0.15, 0.15]}})
    with session_scope(app.settings) as session:
        finished = datetime(2026, 12, 2, 9, 30, tzinfo=UTC)
        session.execute(update(JobRow).where(JobRow.id == uuid.UUID(job_id)).values(
            status="succeeded", result=run, finished_at=finished, attempts=1))  # fmt: skip
    answers = {kind: app.get(job_id, kind) for kind in KINDS}
    assert {kind: r.status_code for kind, r in answers.items()} == dict.fromkeys(KINDS, 200)
    (tmp_path / "sr.dcm").write_bytes(answers["sr.dcm"].content)
    groups = hd.sr.srread(tmp_path / "sr.dcm").content.get_planar_roi_measurement_groups()
    cobb = [g for g in groups if g.tracking_identifier == CORNERSTONE_COBB_ANGLE]
    assert len(cobb) == len(run["measures"]["cobb"]) >= 1
    assert cobb[0].roi.ContentSequence[0].ReferencedSOPSequence[0].ReferencedSOPInstanceUID == film.SOPInstanceUID
