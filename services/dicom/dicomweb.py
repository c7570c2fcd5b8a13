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
import io
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

import requests
from dicomweb_client.api import DICOMwebClient
from pydantic import BaseModel, ConfigDict, Field
from pydicom import dcmread
from pydicom.datadict import tag_for_keyword
from pydicom.dataset import Dataset
from pydicom.errors import InvalidDicomError
from pydicom.uid import ExplicitVRLittleEndian

from services.core.config import DicomwebConfig
from spine_client.dicom.header import RadiographHeader, check_uid, read_header

from .errors import (
    DicomwebError,
    InstanceNotFound,
    PacsUnavailable,
    StoreRefused,
    StudyNotFound,
    TransferSyntaxUnavailable,
)

SERIES_INSTANCE_UID = "0020000E"
SOP_INSTANCE_UID = "00080018"
FAILED_SOP_SEQUENCE = "FailedSOPSequence"

IMAGE_FIELDS = ("SeriesInstanceUID", "SOPInstanceUID", "SOPClassUID", "Modality", "ViewPosition",
                "ImageLaterality", "Rows", "Columns", "SeriesDescription", "SeriesNumber", "InstanceNumber",
                "PatientID", "PatientName", "StudyDate", "AccessionNumber")  # fmt: skip
"""What QIDO-RS is asked to include (``includefield``) for each instance of a study listed to open one."""
RADIOGRAPH_MODALITIES = frozenset({"DX", "CR", "DR", "RG", "MG", "RF", "XA", "IO", "PX"})
"""Projection-radiograph modalities (PS3.3 §C.7.3.1.1.1); an instance of another modality is listed only
when it has Rows and Columns (an image: a Secondary Capture, say), never an SR, KO or PR."""


class StudyImage(BaseModel):
    """One image of a study as QIDO-RS lists it (an attribute the PACS did not return is null)."""

    model_config = ConfigDict(frozen=True)

    series_instance_uid: str
    sop_instance_uid: str
    sop_class_uid: str | None
    modality: str | None
    view_position: str | None = Field(description="View Position (0018,5101), e.g. PA, AP, LL, RL.")
    image_laterality: str | None
    rows: int | None
    columns: int | None
    series_description: str | None
    series_number: int | None
    instance_number: int | None
    patient_id: str | None
    patient_name: str | None = Field(description="Patient's Name, its alphabetic form (e.g. Doe^Jane).")
    study_date: str | None = Field(description="Study Date as DICOM DA (YYYYMMDD).")
    accession_number: str | None

    @classmethod
    def from_json(cls, item: dict[str, Any]) -> StudyImage | None:
        """The image of one QIDO-RS result (DICOM JSON, PS3.18 §F.2), or None when it is not an image."""
        values = {keyword: _json_value(item, keyword) for keyword in IMAGE_FIELDS}
        series, sop = values["SeriesInstanceUID"], values["SOPInstanceUID"]
        if not series or not sop:
            return None
        rows, columns = _int(values["Rows"]), _int(values["Columns"])
        modality = _str(values["Modality"])
        if modality not in RADIOGRAPH_MODALITIES and not (rows and columns):
            return None
        return cls(series_instance_uid=str(series), sop_instance_uid=str(sop),
                   sop_class_uid=_str(values["SOPClassUID"]), modality=modality,
                   view_position=_str(values["ViewPosition"]),
                   image_laterality=_str(values["ImageLaterality"]), rows=rows, columns=columns,
                   series_description=_str(values["SeriesDescription"]), series_number=_int(values["SeriesNumber"]),
                   instance_number=_int(values["InstanceNumber"]), patient_id=_str(values["PatientID"]),
                   patient_name=_str(values["PatientName"]), study_date=_str(values["StudyDate"]),
                   accession_number=_str(values["AccessionNumber"]))  # fmt: skip

    def sort_key(self) -> tuple[int, str, int, str]:
        """Series by number (then UID), then instances by number (then UID); unnumbered ones last."""
        big = 1 << 62
        series = self.series_number if self.series_number is not None else big
        instance = self.instance_number if self.instance_number is not None else big
        return (series, self.series_instance_uid, instance, self.sop_instance_uid)


@dataclass(frozen=True)
class StoreOutcome:
    stored: tuple[str, ...]
    """SOP Instance UIDs the PACS stored (Referenced SOP Sequence of the STOW response)."""
    status: int
    """HTTP status of the STOW response (200; 202 when some were stored with warnings)."""


def part10(ds: Dataset) -> bytes:
    """A dataset as a DICOM Part 10 file: the 128-byte preamble, ``DICM`` and the complete File Meta
    Information, group length included (PS3.10 §7.1), what the media type ``application/dicom`` holds
    (RFC 3240)."""
    out = io.BytesIO()
    ds.save_as(out, enforce_file_format=True)
    return out.getvalue()


def as_part10(ds: Dataset) -> Dataset:
    """``ds`` as dicomweb-client will write it as a Part 10 file: itself when it has a preamble and a
    complete File Meta Information (highdicom's SR and SC have), else as read back from ``part10``.
    dicomweb-client writes each STOW-RS part as its dataset stands, with no preamble nor group length
    for a dataset built in memory, which a PACS may store as is and later serve as a part no DICOM
    reader takes."""
    meta = getattr(ds, "file_meta", None)
    if getattr(ds, "preamble", None) is not None and meta is not None and "FileMetaInformationGroupLength" in meta:
        return ds
    return dcmread(io.BytesIO(part10(ds)))


def shown_url(url: str) -> str:
    """``url`` as an error message may show it, to an API client, in a job's error or a webhook: without
    the user name and password (RFC 3986 §3.2.1 userinfo, which the HTTP client sends as basic
    credentials) nor the query (where a token may be)."""
    parts = urlsplit(url)
    host = parts.netloc.rpartition("@")[2]
    return parts._replace(netloc=host, query="", fragment="").geturl()


class Pacs:
    """One PACS. Thread-unsafe (one requests session); make one per worker task. Its errors name the
    PACS by ``shown_url``: they reach API clients, jobs' errors and webhooks."""

    def __init__(self, config: DicomwebConfig):
        self.config = config
        self.shown_url = shown_url(config.url)
        session = requests.Session()
        if config.token:
            session.headers["Authorization"] = f"Bearer {config.token}"
        elif config.username is not None:
            session.auth = (config.username, config.password or "")
        self.client = DICOMwebClient(url=config.url.rstrip("/"), session=session, timeout=config.timeout_s)
        self.client.set_http_retry_params(retry=False)

    def _shown(self, exc: Exception) -> str:
        """``exc``'s message with the configured URL (and its credentials) replaced by ``shown_url``."""
        text = str(exc)
        for url in (self.config.url, self.config.url.rstrip("/")):
            text = text.replace(url, self.shown_url)
        return text

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
                raise InstanceNotFound(f"the PACS at {self.shown_url} has no {what} ({_uids_text(uids)})",
                                       uids=uids) from None  # fmt: skip
            raise PacsUnavailable(f"the PACS at {self.shown_url} answered HTTP {status} to the request for {what} "
                                  f"({_uids_text(uids)})", status=status) from None  # fmt: skip
        except (requests.ConnectionError, requests.Timeout) as exc:
            raise PacsUnavailable(
                f"the PACS at {self.shown_url} did not answer ({type(exc).__name__}) the request for {what}"
            ) from None
        except requests.RequestException as exc:
            raise PacsUnavailable(f"the request to the PACS at {self.shown_url} failed: {self._shown(exc)}") from None

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
        raise InstanceNotFound(f"the PACS at {self.shown_url} has no instance {_uids_text(uids)}", uids=uids)

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
            raise InstanceNotFound(f"the PACS at {self.shown_url} has no instance {_uids_text(uids)}", uids=uids)
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

    def study_images(self, study_instance_uid: str) -> list[StudyImage]:
        """The images of a study (QIDO-RS instances with ``includefield``), sorted by series then
        instance number. ``StudyNotFound`` when the PACS lists no instance of the study."""
        check_uid(study_instance_uid, "StudyInstanceUID")
        uids = {"StudyInstanceUID": study_instance_uid}
        try:
            with self._errors("the study's instances", uids):
                found = self.client.search_for_instances(study_instance_uid=study_instance_uid,
                                                         fields=list(IMAGE_FIELDS), get_remaining=True)  # fmt: skip
        except InstanceNotFound:
            found = []
        if not found:
            raise StudyNotFound(f"the PACS at {self.shown_url} has no instance of study {study_instance_uid}",
                                uids=uids)  # fmt: skip
        images = [image for item in found if (image := StudyImage.from_json(item)) is not None]
        return sorted(images, key=StudyImage.sort_key)

    def retrieve_explicit_le(self, study_instance_uid: str, series_instance_uid: str, sop_instance_uid: str) -> Dataset:
        """The instance (WADO-RS, PS3.18 §10.4) in Explicit VR Little Endian, the PACS transcoding it
        when stored otherwise (Accept: ``application/dicom; transfer-syntax=1.2.840.10008.1.2.1``).
        ``TransferSyntaxUnavailable`` when the PACS cannot (406) or answers in another syntax."""
        uids = {"StudyInstanceUID": check_uid(study_instance_uid, "StudyInstanceUID"),
                "SeriesInstanceUID": check_uid(series_instance_uid, "SeriesInstanceUID"),
                "SOPInstanceUID": check_uid(sop_instance_uid, "SOPInstanceUID")}  # fmt: skip
        try:
            with self._errors("the instance", uids):
                accept = (("application/dicom", ExplicitVRLittleEndian),)
                ds = self.client.retrieve_instance(study_instance_uid, series_instance_uid, sop_instance_uid,
                                                   media_types=accept)  # fmt: skip
        except InvalidDicomError:
            raise DicomwebError(
                f"the PACS at {self.shown_url} sent {_uids_text(uids)} as a part that is not a DICOM file (no "
                "preamble and DICM prefix, PS3.10 §7.1), which the media type application/dicom holds (RFC 3240)"
            ) from None
        except PacsUnavailable as exc:
            if exc.status in (406, 415):
                raise TransferSyntaxUnavailable(
                    f"the PACS at {self.shown_url} cannot send {_uids_text(uids)} in Explicit VR Little Endian "
                    f"(HTTP {exc.status}): it is stored compressed and the PACS does not transcode it"
                ) from None
            raise
        syntax = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
        if syntax != ExplicitVRLittleEndian:
            raise TransferSyntaxUnavailable(
                f"the PACS at {self.shown_url} sent {_uids_text(uids)} in transfer syntax {syntax}, not Explicit VR "
                f"Little Endian ({ExplicitVRLittleEndian}) as asked: the page reads uncompressed images only"
            )
        return ds

    def store(self, datasets: Sequence[Dataset]) -> StoreOutcome:
        """STOW-RS the datasets (one request). Raises ``StoreRefused`` when the PACS refuses any."""
        uids = {"SOPInstanceUID": ", ".join(str(ds.SOPInstanceUID) for ds in datasets)}
        try:
            with self._errors("the STOW-RS request", uids):
                response = self.client.store_instances([as_part10(ds) for ds in datasets])
        except PacsUnavailable as exc:
            if exc.status is not None and 400 <= exc.status < 500 and exc.status not in (401, 403, 408, 429):
                raise StoreRefused(f"the PACS at {self.shown_url} refused to store {uids['SOPInstanceUID']} "
                                   f"(HTTP {exc.status})", status=exc.status) from None  # fmt: skip
            raise
        failed = response.get(FAILED_SOP_SEQUENCE) or []
        if failed:
            reasons = ", ".join(f"{item.get('ReferencedSOPInstanceUID')}: failure reason {item.get('FailureReason')}"
                                for item in failed)  # fmt: skip
            raise StoreRefused(f"the PACS at {self.shown_url} refused {reasons} (PS3.18 §10.5.3)", status=None)
        stored = tuple(str(item.ReferencedSOPInstanceUID) for item in response.get("ReferencedSOPSequence") or [])
        return StoreOutcome(stored=stored, status=200)


def _uids_text(uids: dict[str, str]) -> str:
    return ", ".join(f"{k} {v}" for k, v in uids.items())


def _json_value(item: dict[str, Any], keyword: str) -> Any:
    """The first value of ``keyword`` in a DICOM JSON object (a person name's alphabetic form), or None."""
    tag = tag_for_keyword(keyword)
    element = item.get(f"{tag:08X}") if tag is not None else None
    values = (element or {}).get("Value") or []
    if not values:
        return None
    value = values[0]
    if isinstance(value, dict):
        return value.get("Alphabetic")
    return value


def _str(value: Any) -> str | None:
    text = str(value).strip() if value is not None else ""
    return text or None


def _int(value: Any) -> int | None:
    try:
        return int(value) if value is not None else None
    except (TypeError, ValueError):
        return None
