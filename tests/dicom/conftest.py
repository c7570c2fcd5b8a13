"""The DICOM tests. Their payloads are ``tests.conftest.spine_payload`` (with ``spacing_mm`` for pixel
landmarks); their throwaway Orthanc with its DICOMweb plugin is the session
fixture ``orthanc`` of ``tests/conftest.py`` (``tools.dicom.orthanc``: Debian's ``orthanc`` and
``orthanc-dicomweb``, storage in a temporary folder, a free loopback port, stopped by its PID), shared
with the page tests. When Orthanc or the plugin is missing the tests that need it are skipped, saying
why (CI counts skips as failures). ``dcmtk`` (dsrdump) and ``dicom3tools`` (dciodvfy) check the SR.
"""

from __future__ import annotations

from tools.dicom.orthanc import OrthancServer, free_port

__all__ = ["OrthancServer", "free_port"]
