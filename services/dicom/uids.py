"""UIDs derived from the job id, so that a result sent twice is the same DICOM instance.

PS3.5 §B.2: a UID may be ``2.25.`` followed by the decimal value of a UUID (ISO/IEC 9834-8); a
name-based UUID version 5 (RFC 9562 §5.5) of ``"<job id>/<role>"`` gives one UID per job and role,
the same on every build. 2.25 + at most 39 digits = at most 44 characters (≤ 64).
"""

from __future__ import annotations

import uuid

NAMESPACE = uuid.UUID("6f0e3c52-6c83-5b7e-9d1e-2f5b0c1a9e47")
"""Fixed namespace of this service's derived UIDs (any constant UUID; changing it changes every UID)."""


def derived_uid(job_id: uuid.UUID | str, role: str) -> str:
    """``2.25.<int of uuid5(NAMESPACE, "<job id>/<role>")>``: e.g. role ``sr-series``, ``sr``, ``sc``."""
    return f"2.25.{uuid.uuid5(NAMESPACE, f'{uuid.UUID(str(job_id))}/{role}').int}"


def job_uids(job_id: uuid.UUID | str) -> dict[str, str]:
    """Every UID the service gives a job's results: the SR's and SC's series and instances, the device
    observer and, for a job without a source study, the new study."""
    roles = ("study", "sr-series", "sr", "sc-series", "sc", "device")
    return {role: derived_uid(job_id, role) for role in roles}
