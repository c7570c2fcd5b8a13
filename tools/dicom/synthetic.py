"""Synthetic DX/CR radiographs made with pydicom, for tests, the benchmark and the Orthanc example.

The pixels are a smooth ramp (a few kilobytes at the default size); the header carries whatever
spacing, orientation and geometry attributes the caller asks for. UIDs are random 2.25 UIDs
(PS3.5 §B.2) unless given.
"""

from __future__ import annotations

from datetime import date
from typing import Any, Literal

import numpy as np
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import (
    PYDICOM_IMPLEMENTATION_UID,
    UID,
    ExplicitVRBigEndian,
    ExplicitVRLittleEndian,
    ImplicitVRLittleEndian,
    generate_uid,
)

DX_FOR_PRESENTATION = UID("1.2.840.10008.5.1.4.1.1.1.1")
CR_IMAGE = UID("1.2.840.10008.5.1.4.1.1.1")

TRANSFER_SYNTAXES = {
    "explicit": ExplicitVRLittleEndian,
    "implicit": ImplicitVRLittleEndian,
    "big": ExplicitVRBigEndian,
}


def radiograph(
    *,
    modality: Literal["DX", "CR"] = "DX",
    rows: int = 64,
    columns: int = 32,
    photometric: Literal["MONOCHROME1", "MONOCHROME2"] = "MONOCHROME2",
    transfer_syntax: Literal["explicit", "implicit", "big"] = "explicit",
    study_instance_uid: str | None = None,
    series_instance_uid: str | None = None,
    sop_instance_uid: str | None = None,
    patient_id: str | None = "P-0001",
    patient_name: str | None = "Doe^Jane",
    accession_number: str | None = "ACC-42",
    study_date: date | None = date(2026, 11, 30),
    pixel_spacing: tuple[float, float] | None = None,
    imager_pixel_spacing: tuple[float, float] | None = (0.15, 0.15),
    calibration_type: str | None = None,
    ermf: float | None = None,
    sid: float | None = None,
    sod: float | None = None,
    dse: float | None = None,
    patient_orientation: tuple[str, str] | None = ("L", "F"),
    view_position: str | None = "PA",
    extra: dict[str, Any] | None = None,
) -> Dataset:
    """A DX (or CR) image as a pydicom Dataset with file meta; write it with
    ``save_as(path, enforce_file_format=True)`` (or ``write``)."""
    ds = Dataset()
    sop_class = DX_FOR_PRESENTATION if modality == "DX" else CR_IMAGE
    sop_uid = UID(sop_instance_uid or generate_uid(prefix=None))
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = sop_uid
    meta.TransferSyntaxUID = TRANSFER_SYNTAXES[transfer_syntax]
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds.file_meta = meta
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = sop_uid
    ds.StudyInstanceUID = study_instance_uid or generate_uid(prefix=None)
    ds.SeriesInstanceUID = series_instance_uid or generate_uid(prefix=None)
    ds.Modality = modality
    ds.PatientID = patient_id or ""
    ds.PatientName = patient_name or ""
    ds.PatientBirthDate = "20120412"
    ds.PatientSex = "F"
    ds.AccessionNumber = accession_number or ""
    ds.StudyDate = study_date.strftime("%Y%m%d") if study_date else ""
    ds.StudyTime = "101500"
    ds.StudyID = "1"
    ds.ReferringPhysicianName = ""
    ds.SeriesNumber = 1
    ds.InstanceNumber = 1
    ds.Manufacturer = "spine-tests"
    ds.BodyPartExamined = "SPINE"
    region = Dataset()
    region.CodeValue, region.CodingSchemeDesignator, region.CodeMeaning = "421060004", "SCT", "Spine"
    ds.AnatomicRegionSequence = [region]  # PS3.16 CID 4 Anatomic Region
    if modality == "DX":
        ds.PresentationIntentType = "FOR PRESENTATION"
        ds.ImageType = ["ORIGINAL", "PRIMARY"]
        ds.DetectorType = "DIRECT"
        ds.PixelIntensityRelationship = "LIN"
        ds.PixelIntensityRelationshipSign = 1 if photometric == "MONOCHROME2" else -1
        ds.PresentationLUTShape = "IDENTITY" if photometric == "MONOCHROME2" else "INVERSE"
        ds.BurnedInAnnotation = "NO"
        ds.PositionerType = ""
        ds.AcquisitionContextSequence = []
    ds.ContentDate = ds.StudyDate
    ds.ContentTime = "101500"
    if patient_orientation is not None:
        ds.PatientOrientation = list(patient_orientation)
    if view_position is not None:
        ds.ViewPosition = view_position
    ds.ImageLaterality = "U"
    if pixel_spacing is not None:
        ds.PixelSpacing = [f"{v:.10g}" for v in pixel_spacing]
    if imager_pixel_spacing is not None:
        ds.ImagerPixelSpacing = [f"{v:.10g}" for v in imager_pixel_spacing]
    if calibration_type is not None:
        ds.PixelSpacingCalibrationType = calibration_type
    if ermf is not None:
        ds.EstimatedRadiographicMagnificationFactor = f"{ermf:.10g}"
    if sid is not None:
        ds.DistanceSourceToDetector = f"{sid:.10g}"
    if sod is not None:
        ds.DistanceSourceToPatient = f"{sod:.10g}"
    if dse is not None:
        ds.DistanceSourceToEntrance = f"{dse:.10g}"
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = photometric
    ds.Rows, ds.Columns = rows, columns
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
    ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = "0", "1", "US"
    ds.WindowCenter, ds.WindowWidth = "2048", "4096"
    ds.LossyImageCompression = "00"
    ramp = (np.add.outer(np.arange(rows), np.arange(columns)) * 4095 // max(1, rows + columns - 2)).astype(np.uint16)
    ds.PixelData = ramp.astype(">u2" if transfer_syntax == "big" else "<u2").tobytes()
    for key, value in (extra or {}).items():
        setattr(ds, key, value)
    return ds


def write(ds: Dataset, path: Any) -> None:
    """Write ``ds`` as a DICOM Part 10 file (preamble, ``DICM``, complete file meta; PS3.10 §7.1)."""
    ds.save_as(path, enforce_file_format=True)
