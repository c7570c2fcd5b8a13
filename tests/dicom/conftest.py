"""The DICOM tests. Their payloads are ``tests.conftest.spine_payload`` (with ``spacing_mm`` for pixel
landmarks); their throwaway Orthanc with its DICOMweb plugin is the session
fixture ``orthanc`` of ``tests/conftest.py`` (``tools.dicom.orthanc``: Debian's ``orthanc`` and
``orthanc-dicomweb``, storage in a temporary folder, a free loopback port, stopped by its PID), shared
with the page tests. When Orthanc or the plugin is missing the tests that need it are skipped, saying
why (CI counts skips as failures). ``dcmtk`` (dsrdump) and ``dicom3tools`` (dciodvfy) check the SR.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from services.core.config import DicomwebConfig
from services.dicom.dicomweb import Pacs
from tests.conftest import Service, spawned_service
from tools.dicom.orthanc import OrthancServer, free_port

__all__ = ["OrthancServer", "free_port", "pacs_of"]


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
