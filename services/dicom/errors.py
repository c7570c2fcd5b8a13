"""Typed refusals of a PACS over DICOMweb; those of a radiograph's header are
``spine_client.dicom.errors`` (the reader the client and the service share).

The API and worker map them to RFC 9457 problem types by ``problem`` (a stable slug); nothing
here knows HTTP.
"""

from __future__ import annotations

from spine_client.dicom.errors import DicomError


class DicomwebError(DicomError):
    """Base of the errors of talking to a PACS over DICOMweb."""

    problem = "dicomweb-error"


class PacsUnavailable(DicomwebError):
    """The PACS did not answer, or answered with a server error (5xx) or an authentication refusal: transient
    from the job's point of view (retry later)."""

    problem = "dicomweb-unavailable"

    def __init__(self, message: str, *, status: int | None = None):
        super().__init__(message)
        self.status = status


class InstanceNotFound(DicomwebError):
    """The PACS answered but does not hold the instance (or study/series) asked for."""

    problem = "dicomweb-instance-not-found"

    def __init__(self, message: str, *, uids: dict[str, str] | None = None):
        super().__init__(message, attributes=tuple((uids or {}).keys()))
        self.uids = dict(uids or {})


class StudyNotFound(InstanceNotFound):
    """The PACS answered but holds no image of the study asked for (QIDO-RS found no instance)."""

    problem = "dicomweb-study-not-found"


class TransferSyntaxUnavailable(DicomwebError):
    """The PACS holds the instance but would not send it in the transfer syntax asked for (it cannot
    transcode it, PS3.18 §8.7.3.5: 406 Not Acceptable, or it answered another one)."""

    problem = "dicomweb-transfer-syntax-unavailable"


class StoreRefused(DicomwebError):
    """STOW-RS answered but refused (some of) the instances (PS3.18 §10.5.3: 409 or a Failed SOP Sequence)."""

    problem = "dicomweb-store-refused"

    def __init__(self, message: str, *, status: int | None = None):
        super().__init__(message)
        self.status = status
