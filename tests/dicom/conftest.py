"""The DICOM tests. Their payloads are ``tests.conftest.spine_payload`` (with ``spacing_mm`` for pixel
landmarks); their throwaway Orthanc with its DICOMweb plugin is the session
fixture ``orthanc`` of ``tests/conftest.py`` (``tools.dicom.orthanc``: Debian's ``orthanc`` and
``orthanc-dicomweb``, storage in a temporary folder, a free loopback port, stopped by its PID), shared
with the page tests. When Orthanc or the plugin is missing the tests that need it are skipped, saying
why (CI counts skips as failures). ``dcmtk`` (dsrdump) and ``dicom3tools`` (dciodvfy) check the SR.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest

from services.core.config import DicomwebConfig
from services.dicom.dicomweb import Pacs
from tests.conftest import Service, spawned_service, spine_payload
from tests.faults import PortRelay
from tools.dicom.orthanc import OrthancServer, free_port

__all__ = ["OrthancServer", "PortRelay", "free_port", "pacs_of"]


@pytest.fixture(scope="module")
def pacs_service(
    tmp_path_factory: pytest.TempPathFactory, postgres_url: str, redis_url: str, orthanc: OrthancServer
) -> Iterator[Service]:
    """A `spine serve` of the module's own on PostgreSQL and Redis with its worker, reading from and
    storing its results (SR, SC) in the session's Orthanc."""
    with spawned_service(
        "dicom", tmp_path_factory.mktemp("dicom-service"), postgres_url=postgres_url, redis_url=redis_url,
        SPINE_DICOMWEB_URL=orthanc.dicomweb_url, SPINE_DICOMWEB_USERNAME=orthanc.username,
        SPINE_DICOMWEB_PASSWORD=orthanc.password, SPINE_DICOMWEB_STORE_RESULTS="true",
    ) as service:  # fmt: skip
        yield service


def pacs_of(orthanc: OrthancServer) -> Pacs:
    """A DICOMweb client of the session's Orthanc, with its credentials."""
    return Pacs(DicomwebConfig(orthanc.dicomweb_url, orthanc.username, orthanc.password))


# ---------------------------------------------------------------- a PACS that is down until a test opens it

STORE_TIMEOUT_S = 60.0
"""Seconds for a run of attempts to be recorded: as tests/dicom/test_dicom_service.py's, building the SR and
SC on two loaded cores, here plus a run's delays (a second or so)."""
STORE_SPACING_MM = 0.15
"""Pixel spacing of ``complete_payload``'s films (mm)."""


@pytest.fixture(scope="module")
def relay(orthanc: OrthancServer) -> Iterator[PortRelay]:
    where = urlsplit(orthanc.dicomweb_url)
    made = PortRelay((where.hostname or "127.0.0.1", where.port or 80))
    yield made
    made.close()


def complete_payload(study: dict[str, str] | None) -> dict[str, Any]:
    """px landmarks with the spacing and orientation typed (no header to read: the PACS may be down), and
    ``study`` when given."""
    payload = spine_payload(spacing_mm=STORE_SPACING_MM)
    payload["pa"].update(pixel_spacing=[STORE_SPACING_MM, STORE_SPACING_MM], patient_orientation=["L", "F"])
    if study is not None:
        payload["study"] = study
    return payload


@contextmanager
def relayed_store_service(
    name: str, data_dir: Path, postgres_url: str, redis_url: str, orthanc: OrthancServer, relay: PortRelay,
    max_attempts: int, retry_base_s: float, **env: str,
) -> Iterator[Service]:  # fmt: skip
    """A `spine serve` (``spawned_service``: PostgreSQL, Redis, its worker) storing results in ``orthanc``
    through ``relay`` (closed until a test opens it), runs of ``max_attempts`` attempts ``retry_base_s``
    apart, a 2 s DICOMweb timeout, and ``env`` besides."""
    url = urlsplit(orthanc.dicomweb_url)._replace(netloc=f"127.0.0.1:{relay.port}").geturl()
    with spawned_service(
        name, data_dir, postgres_url=postgres_url, redis_url=redis_url,
        SPINE_DICOMWEB_URL=url, SPINE_DICOMWEB_USERNAME=orthanc.username, SPINE_DICOMWEB_PASSWORD=orthanc.password,
        SPINE_DICOMWEB_STORE_RESULTS="true", SPINE_DICOMWEB_TIMEOUT_S="2",
        SPINE_DICOMWEB_MAX_ATTEMPTS=str(max_attempts), SPINE_DICOMWEB_RETRY_BASE_S=str(retry_base_s), **env,
    ) as service:  # fmt: skip
        yield service
