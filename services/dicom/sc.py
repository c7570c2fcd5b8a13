"""The job's figure (``spine_engine.figures`` PNG) as a Secondary Capture Image (PS3.3 §A.8.1), built with
highdicom, in its own series of the SR's study (a series holds one modality, PS3.3 §C.7.3.1: the SR
series is ``SR``, this one ``OT``), with the same patient, accession and study, UIDs derived from
the job id (``uids.py``).

The PNG is decoded with Pillow into 8-bit RGB (Photometric Interpretation RGB, PS3.3 §C.7.6.3.1.2),
stored uncompressed (Explicit VR Little Endian). The figure is a chart, not a view of the patient:
its Patient Orientation (0020,0020) is sent empty (a Type 2 value may be empty, PS3.5 §7.4.3; highdicom
requires one for its ``PATIENT`` coordinate system, so it is cleared after). Laterality (0020,0060) is left
out: General Series Module (PS3.3 §C.7.3.1) makes it Type 2C, required only when the body part examined
is a paired structure, and the spine is not; a Type 2C attribute whose condition is not met is not
sent (PS3.5 §7.4.4). Body Part Examined (0018,0015, Type 3) says which: ``SPINE`` (PS3.16 Annex L,
Body Part Examined defined terms), from which dicom3tools' dciodvfy evaluates the condition. The SR
has no Laterality either: its SR Document Series Module (PS3.3 §C.17.1) has none. The patient and
study are the source's (Patient and General Study Modules, PS3.3 §C.7.1.1, §C.7.2.1: a new series of
the same study repeats them, the issuer of the Patient ID included, ``sr.write_patient_id_issuer``); the
General Equipment Module (§C.7.5.1) describes the equipment that made the series, this service, not the
film's modality. Its Content, Instance Creation and Secondary
Capture dates and times are the job's end, in the film's zone with its Timezone Offset From UTC
(0008,0201) when the study gives one, else in UTC with ``+0000`` (``sr.stamp_content_time``; PS3.3
§C.12.1.1.8).
"""

from __future__ import annotations

import io
import uuid
from datetime import datetime

import highdicom as hd
import numpy as np
from PIL import Image

from .sr import MANUFACTURER, StudyIdentity, declare_character_set, stamp_content_time, write_patient_id_issuer
from .uids import job_uids


def png_to_rgb(png: bytes) -> np.ndarray:
    """(rows, columns, 3) uint8 RGB pixels of a PNG (alpha composited on white)."""
    with Image.open(io.BytesIO(png)) as image:
        rgba = image.convert("RGBA")
    background = Image.new("RGBA", rgba.size, (255, 255, 255, 255))
    return np.asarray(Image.alpha_composite(background, rgba).convert("RGB"), dtype=np.uint8)


def build_sc(
    png: bytes, job_id: uuid.UUID | str, identity: StudyIdentity, *, series_number: int = 9902,
    content_datetime: datetime | None = None,
) -> hd.sc.SCImage:  # fmt: skip
    """The figure as a Secondary Capture of the job's study (module docstring)."""
    uids = job_uids(job_id)
    pixels = png_to_rgb(png)
    sc = hd.sc.SCImage(
        pixel_array=pixels, photometric_interpretation="RGB", bits_allocated=8, coordinate_system="PATIENT",
        study_instance_uid=identity.study_instance_uid or uids["study"], series_instance_uid=uids["sc-series"],
        series_number=series_number, sop_instance_uid=uids["sc"], instance_number=1, manufacturer=MANUFACTURER,
        patient_id=identity.patient_id, patient_name=identity.patient_name,
        patient_birth_date=identity.patient_birth_date, patient_sex=identity.patient_sex,
        accession_number=identity.accession_number, study_id=identity.study_id, study_date=identity.study_date,
        study_time=identity.study_time, referring_physician_name=identity.referring_physician_name,
        patient_orientation=("L", "F"), series_description="Spine reconstruction figure",
    )  # fmt: skip
    sc.PatientOrientation = []
    sc.BodyPartExamined = "SPINE"
    if "Laterality" in sc:
        del sc.Laterality
    sc.BurnedInAnnotation = "NO"
    stamp_content_time(sc, content_datetime, ("ContentDate", "InstanceCreationDate", "DateOfSecondaryCapture"),
                       ("ContentTime", "InstanceCreationTime", "TimeOfSecondaryCapture"),
                       identity.timezone_offset_from_utc)  # fmt: skip
    return declare_character_set(write_patient_id_issuer(sc, identity))
