"""A PACS over DICOMweb (PS3.18), with dicomweb-client: instance metadata by UID (WADO-RS
``/studies/{s}/series/{se}/instances/{i}/metadata``, PS3.18 §10.4), the series found by QIDO-RS
(§10.6) when only study and instance are known, and STOW-RS (§10.5) to store results.

Errors are typed (``errors.py``): ``PacsUnavailable`` (no answer, a timeout, a 5xx, 401/403 or
429: transient for a job, retry later), ``InstanceNotFound`` (the PACS answered and does not hold
the instance), ``StoreRefused`` (STOW answered with a refusal, PS3.18 §10.5.3). dicomweb-client's
own retries are off: the caller (the worker) owns retries and records each attempt.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import requests
from dicomweb_client.api import DICOMwebClient
from pydicom.dataset import Dataset

from .errors import InstanceNotFound, PacsUnavailable, StoreRefused
from .header import RadiographHeader, check_uid, read_header

DEFAULT_TIMEOUT_S = 10.0
"""Connect and read timeout of one DICOMweb request, s: metadata of one instance is a few kB, and a
STOW of an SR and a figure (≈ 0.1–3 MB) takes well under a second on a hospital network; 10 s turns a
hung PACS into a retry without holding a worker long."""

SERIES_INSTANCE_UID = "0020000E"
SOP_INSTANCE_UID = "00080018"
FAILED_SOP_SEQUENCE = "FailedSOPSequence"


@dataclass(frozen=True)
class DicomwebConfig:
    """Where the PACS is and how to authenticate (the service's SPINE_DICOMWEB_* settings)."""

    url: str
    """DICOMweb base URL, e.g. Orthanc's ``http://host:8042/dicom-web``."""
    username: str | None = None
    password: str | None = None
    token: str | None = None
    """Bearer token (sent as ``Authorization: Bearer``); wins over username/password when both are set."""
    timeout_s: float = DEFAULT_TIMEOUT_S


@dataclass(frozen=True)
class StoreOutcome:
    stored: tuple[str, ...]
    """SOP Instance UIDs the PACS stored (Referenced SOP Sequence of the STOW response)."""
    status: int
    """HTTP status of the STOW response (200; 202 when some were stored with warnings)."""


class Pacs:
    """One PACS. Thread-unsafe (one requests session); make one per worker task."""

    def __init__(self, config: DicomwebConfig):
        self.config = config
        session = requests.Session()
        if config.token:
            session.headers["Authorization"] = f"Bearer {config.token}"
        elif config.username is not None:
            session.auth = (config.username, config.password or "")
        self.client = DICOMwebClient(url=config.url.rstrip("/"), session=session, timeout=config.timeout_s)
        self.client.set_http_retry_params(retry=False)

    def close(self) -> None:
        self.client._session.close()

    def __enter__(self) -> Pacs:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    @contextlib.contextmanager
    def _errors(self, what: str, uids: dict[str, str]) -> Iterator[None]:
        try:
            yield
        except requests.HTTPError as exc:
            status = exc.response.status_code if exc.response is not None else None
            if status == 404:
                raise InstanceNotFound(f"the PACS at {self.config.url} has no {what} ({_uids_text(uids)})",
                                       uids=uids) from None  # fmt: skip
            raise PacsUnavailable(f"the PACS at {self.config.url} answered HTTP {status} to the request for {what} "
                                  f"({_uids_text(uids)})", status=status) from None  # fmt: skip
        except (requests.ConnectionError, requests.Timeout) as exc:
            raise PacsUnavailable(
                f"the PACS at {self.config.url} did not answer ({type(exc).__name__}) the request for {what}"
            ) from None
        except requests.RequestException as exc:
            raise PacsUnavailable(f"the request to the PACS at {self.config.url} failed: {exc}") from None

    def find_series(self, study_instance_uid: str, sop_instance_uid: str) -> str:
        """The Series Instance UID of an instance known by study and SOP Instance UID (QIDO-RS)."""
        uids = {"StudyInstanceUID": study_instance_uid, "SOPInstanceUID": sop_instance_uid}
        with self._errors("the instance", uids):
            found = self.client.search_for_instances(
                study_instance_uid=study_instance_uid, search_filters={"SOPInstanceUID": sop_instance_uid},
                fields=["SeriesInstanceUID"],
            )  # fmt: skip
        for item in found:
            values = (item.get(SERIES_INSTANCE_UID) or {}).get("Value") or []
            if values:
                return str(values[0])
        raise InstanceNotFound(f"the PACS at {self.config.url} has no instance {_uids_text(uids)}", uids=uids)

    def instance_metadata(
        self, study_instance_uid: str, sop_instance_uid: str, series_instance_uid: str | None = None
    ) -> dict[str, Any]:
        """The instance's header as DICOM JSON (PS3.18 §F.2), by WADO-RS metadata."""
        check_uid(study_instance_uid, "StudyInstanceUID")
        check_uid(sop_instance_uid, "SOPInstanceUID")
        if series_instance_uid is None:
            series_instance_uid = self.find_series(study_instance_uid, sop_instance_uid)
        check_uid(series_instance_uid, "SeriesInstanceUID")
        uids = {"StudyInstanceUID": study_instance_uid, "SeriesInstanceUID": series_instance_uid,
                "SOPInstanceUID": sop_instance_uid}  # fmt: skip
        with self._errors("the instance", uids):
            found = self.client.retrieve_instance_metadata(study_instance_uid, series_instance_uid, sop_instance_uid)
        items = found if isinstance(found, list) else [found]
        if not items or not items[0]:
            raise InstanceNotFound(f"the PACS at {self.config.url} has no instance {_uids_text(uids)}", uids=uids)
        return dict(items[0])

    def read_header(
        self, study_instance_uid: str, sop_instance_uid: str, series_instance_uid: str | None = None
    ) -> RadiographHeader:
        """``header.read_header`` of the instance's WADO-RS metadata."""
        return read_header(self.instance_metadata(study_instance_uid, sop_instance_uid, series_instance_uid))

    def search_instances(self, study_instance_uid: str, **filters: str) -> list[dict[str, Any]]:
        """QIDO-RS instances of a study (DICOM JSON), e.g. ``SOPInstanceUID=...`` or ``Modality="SR"``."""
        with self._errors("the study's instances", {"StudyInstanceUID": study_instance_uid}):
            return list(self.client.search_for_instances(study_instance_uid=study_instance_uid,
                                                         search_filters=dict(filters) or None))  # fmt: skip

    def store(self, datasets: Sequence[Dataset]) -> StoreOutcome:
        """STOW-RS the datasets (one request). Raises ``StoreRefused`` when the PACS refuses any."""
        uids = {"SOPInstanceUID": ", ".join(str(ds.SOPInstanceUID) for ds in datasets)}
        try:
            with self._errors("the STOW-RS request", uids):
                response = self.client.store_instances(list(datasets))
        except PacsUnavailable as exc:
            if exc.status is not None and 400 <= exc.status < 500 and exc.status not in (401, 403, 408, 429):
                raise StoreRefused(f"the PACS at {self.config.url} refused to store {uids['SOPInstanceUID']} "
                                   f"(HTTP {exc.status})", status=exc.status) from None  # fmt: skip
            raise
        failed = response.get(FAILED_SOP_SEQUENCE) or []
        if failed:
            reasons = ", ".join(f"{item.get('ReferencedSOPInstanceUID')}: failure reason {item.get('FailureReason')}"
                                for item in failed)  # fmt: skip
            raise StoreRefused(f"the PACS at {self.config.url} refused {reasons} (PS3.18 §10.5.3)", status=None)
        stored = tuple(str(item.ReferencedSOPInstanceUID) for item in response.get("ReferencedSOPSequence") or [])
        return StoreOutcome(stored=stored, status=200)


def _uids_text(uids: dict[str, str]) -> str:
    return ", ".join(f"{k} {v}" for k, v in uids.items())
