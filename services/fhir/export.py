"""FHIR export of a succeeded job: a Bundle (type collection) of Observations of its clinical measures.

Built and validated with ``fhir.resources``' R4B models (FHIR 4.3.0). fhir.resources has no
separate R4 (4.0.1) package for pydantic 2 (6.4 and older need pydantic 1); R4B changed neither
Observation nor Bundle for the elements written here (status, category, code, issued, value[x]
Quantity, component, note, method, derivedFrom, identifier; Bundle type, timestamp, entry.fullUrl),
so the JSON is valid R4 as well.

Coding: no LOINC or SNOMED CT code is asserted for these measures (none is used unless it is
certain to exist with that meaning), so each Observation's ``code`` is ``text`` only. The codes
that are used are FHIR's own category ``imaging``
(http://terminology.hl7.org/CodeSystem/observation-category) and UCUM ``deg``. The input images'
DICOM Study Instance UID, when the payload had a ``study``, is referenced in ``derivedFrom`` as an
ImagingStudy identifier (system ``urn:dicom:uid``, value ``urn:oid:<uid>``).
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from datetime import datetime
from typing import Any

from fhir.resources.R4B.bundle import Bundle

FHIR_MEDIA_TYPE = "application/fhir+json"
FHIR_VERSION = "4.0.1"
UCUM = "http://unitsofmeasure.org"
OBSERVATION_CATEGORY = "http://terminology.hl7.org/CodeSystem/observation-category"
DICOM_UID = "urn:dicom:uid"
URI = "urn:ietf:rfc:3986"
METHOD = (
    "3D reconstruction of the spine from radiograph landmarks by discrete Cosserat rod registration "
    "(Li, Leow, Huang and Howe, CAIP 2009)"
)
_NAMESPACE = uuid.UUID("6f1c2a57-2a4e-5d0b-8a53-2f3f7c1b9e10")

MODEL_ESTIMATE_NOTE = (
    "Model estimate: T1 and L5 were not given, so this quantity comes from the generic spine model, "
    "not from the images (fit.unreliable)."
)


SD_COMPONENT = (
    "Standard deviation of the value (1 SD from the fit's curvature, calibrated on held-out spines; "
    "a 95 % interval is ±1.96 SD)"
)


def _deg(value: float) -> dict[str, Any]:
    return {"value": round(float(value), 2), "unit": "deg", "system": UCUM, "code": "deg"}


def _text(text: str) -> dict[str, Any]:
    return {"text": text}


def _component(name: str, **value: Any) -> dict[str, Any]:
    return {"code": _text(name), **value}


def _derived_from(study: dict[str, Any] | None) -> list[dict[str, Any]]:
    if not study or not study.get("study_instance_uid"):
        return []
    uid = study["study_instance_uid"]
    return [
        {
            "type": "ImagingStudy",
            "identifier": {"system": DICOM_UID, "value": f"urn:oid:{uid}"},
            "display": f"DICOM study {uid}",
        }
    ]


def _subject(study: dict[str, Any] | None) -> dict[str, Any] | None:
    """The Patient by identifier (DICOM Patient ID (0010,0020); its issuer is not known, so no system),
    with the DICOM Patient's Name as display; None without a patient ID."""
    if not study or not study.get("patient_id"):
        return None
    subject: dict[str, Any] = {"type": "Patient", "identifier": {"value": study["patient_id"]}}
    if study.get("patient_name"):
        subject["display"] = str(study["patient_name"]).replace("^", " ").strip()
    return subject


def _image_note(study: dict[str, Any] | None) -> list[dict[str, Any]]:
    if not study:
        return []
    parts = [
        f"{label} {study[key]}"
        for key, label in (
            ("series_instance_uid", "Series Instance UID"),
            ("pa_sop_instance_uid", "PA image SOP Instance UID"),
            ("lateral_sop_instance_uid", "lateral image SOP Instance UID"),
        )
        if study.get(key)
    ]
    return [{"text": "Measured on DICOM " + "; ".join(parts) + "."}] if parts else []


def observation_bundle(
    job_id: uuid.UUID | str,
    result: dict[str, Any],
    *,
    finished_at: datetime,
    study: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The Bundle of a job's measures as FHIR JSON (validated by fhir.resources)."""
    measures = result.get("measures") or {}
    unreliable = set((result.get("fit") or {}).get("unreliable") or [])
    version = (result.get("engine") or {}).get("version", "unknown")
    issued = finished_at.isoformat()
    derived = _derived_from(study)
    image_note = _image_note(study)
    subject = _subject(study)
    effective = (study or {}).get("study_date")

    def observation(key: str, name: str, value: float, *, notes: Sequence[str] = (),
                    components: Sequence[dict[str, Any]] = (), estimate: bool = False,
                    sd: float | None = None) -> dict[str, Any]:  # fmt: skip
        if sd is not None:
            components = [*components, _component(SD_COMPONENT, valueQuantity=_deg(sd))]
        obs_id = str(uuid.uuid5(_NAMESPACE, f"{job_id}:{key}"))
        texts = [{"text": n} for n in notes] + ([{"text": MODEL_ESTIMATE_NOTE}] if estimate else []) + image_note
        body: dict[str, Any] = {
            "resourceType": "Observation",
            "id": obs_id,
            "identifier": [{"system": URI, "value": f"urn:uuid:{obs_id}"}],
            "status": "final",
            "category": [{"coding": [{"system": OBSERVATION_CATEGORY, "code": "imaging", "display": "Imaging"}]}],
            "code": _text(name),
            "issued": issued,
            "valueQuantity": _deg(value),
            "method": _text(f"{METHOD}; spine_engine {version}"),
        }
        if texts:
            body["note"] = texts
        if derived:
            body["derivedFrom"] = derived
        if subject:
            body["subject"] = subject
        if effective:
            body["effectiveDateTime"] = str(effective)
        if components:
            body["component"] = list(components)
        return body

    observations: list[dict[str, Any]] = []
    curves = sorted(measures.get("cobb") or [], key=lambda c: not c.get("major"))
    for i, curve in enumerate(curves):
        kind = "major curve" if curve.get("major") else "minor curve"
        components = [
            _component("Upper end vertebra", valueString=curve["upper"]),
            _component("Lower end vertebra", valueString=curve["lower"]),
            _component("Apex vertebra", valueString=curve["apex"]),
            _component("Convexity (patient side)", valueString=curve["convexity"]),
            _component("Major curve", valueBoolean=bool(curve.get("major"))),
            _component("Apical vertebral axial rotation", valueQuantity=_deg(curve["apex_axial_rotation_deg"])),
            _component(
                "Plane of maximum curvature, azimuth from the frontal plane toward anterior",
                valueQuantity=_deg(curve["plane_of_max_curvature_deg"]),
            ),
            _component("Cobb angle in the plane of maximum curvature", valueQuantity=_deg(curve["max_curvature_deg"])),
        ]
        if curve.get("endplate_angle_deg") is not None:
            endplates = _deg(curve["endplate_angle_deg"])
            components.append(_component("Cobb angle between end plates, frontal plane", valueQuantity=endplates))
        note = (
            f"{kind.capitalize()} {curve['upper']}–{curve['lower']}, apex {curve['apex']}, "
            f"convex to the patient's {curve['convexity']}."
        )
        observations.append(
            observation(f"cobb:{i}:{curve['upper']}-{curve['lower']}", f"Cobb angle, frontal plane, {kind}",
                        curve["angle_deg"], notes=[note], components=components, sd=curve.get("angle_sd_deg"))
        )  # fmt: skip
    major = next((c for c in curves if c.get("major")), None)
    for key, name, field, flag in (
        ("kyphosis-t4-t12", "Thoracic kyphosis T4–T12 (sagittal Cobb angle)", "thoracic_kyphosis_t4_t12_deg",
         "kyphosis"),
        ("kyphosis-t5-t12", "Thoracic kyphosis T5–T12 (sagittal Cobb angle)", "thoracic_kyphosis_t5_t12_deg",
         "kyphosis"),
        ("lordosis-l1-l5", "Lumbar lordosis L1–L5 (sagittal Cobb angle)", "lumbar_lordosis_l1_l5_deg", "lordosis"),
    ):  # fmt: skip
        if measures.get(field) is not None:
            sign = "positive when convex posteriorly" if flag == "kyphosis" else "positive when convex anteriorly"
            observations.append(observation(key, name, measures[field], notes=[f"Sign: {sign}."],
                                            estimate=flag in unreliable,
                                            sd=measures.get(field.replace("_deg", "_sd_deg"))))  # fmt: skip
    if major is not None:
        apex = [v for v in result.get("vertebrae") or [] if v.get("level") == major["apex"]]
        apex_sd = apex[0].get("axial_rotation_sd_deg") if apex else None
        observations.append(
            observation(
                "apical-axial-rotation",
                "Apical vertebral axial rotation of the major curve",
                major["apex_axial_rotation_deg"],
                notes=[f"Apex {major['apex']}; positive toward the patient's left (SRS sense, seen from above)."],
                components=[_component("Apex vertebra", valueString=major["apex"])],
                estimate="axial_rotation" in unreliable,
                sd=apex_sd,
            )
        )
    bundle = {
        "resourceType": "Bundle",
        "id": str(job_id),
        "identifier": {"system": URI, "value": f"urn:uuid:{job_id}"},
        "type": "collection",
        "timestamp": issued,
        "entry": [{"fullUrl": f"urn:uuid:{o['id']}", "resource": o} for o in observations],
    }
    validated: dict[str, Any] = Bundle.model_validate(bundle).model_dump(mode="json", exclude_none=True)
    return validated
