"""Payloads of the DICOM tests. Their throwaway Orthanc with its DICOMweb plugin is the session
fixture ``orthanc`` of ``tests/conftest.py`` (``tools.dicom.orthanc``: Debian's ``orthanc`` and
``orthanc-dicomweb``, storage in a temporary folder, a free loopback port, stopped by its PID), shared
with the page tests. When Orthanc or the plugin is missing the tests that need it are skipped, saying
why (CI counts skips as failures). ``dcmtk`` (dsrdump) and ``dicom3tools`` (dciodvfy) check the SR.
"""

from __future__ import annotations

import math
from typing import Any

from tools.dicom.orthanc import OrthancServer, free_port

__all__ = ["LEVELS", "OrthancServer", "free_port", "spine_payload"]

LEVELS = ["T1", "T2", "T3", "T4", "T5", "T6", "T7", "T8", "T9", "T10", "T11", "T12",
          "L1", "L2", "L3", "L4", "L5"]  # fmt: skip
IDENTITY_LPS = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]


def spine_payload(
    curve_mm: float = 15.0, length_mm: float = 420.0, *, spacing_mm: float | None = None
) -> dict[str, Any]:
    """A PA payload: 17 endplate midpoints on a C-curve (mm, or px when ``spacing_mm`` is given), T1 and L5 given."""
    landmarks = []
    for i, level in enumerate(LEVELS):
        t = i / (len(LEVELS) - 1)
        col, row = 100.0 + curve_mm * math.sin(math.pi * t), 50.0 + length_mm * t
        if spacing_mm:
            col, row = col / spacing_mm, row / spacing_mm
        landmarks.append({"level": level, "point": [round(col, 3), round(row, 3)]})
    pa: dict[str, Any] = {"landmarks": landmarks}
    if spacing_mm:
        pa["units"] = "px"
    return {
        "pa": pa,
        "boundary": {
            "T1": {"position": [0.0, 0.0, 0.0], "directors": IDENTITY_LPS},
            "L5": {"position": [0.0, 0.0, -length_mm], "directors": IDENTITY_LPS},
        },
    }
