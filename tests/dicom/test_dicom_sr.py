"""The result as DICOM: the SR (TID 1500) passes dcmtk's dsrdump and dicom3tools' dciodvfy without
errors, its Cobb items equal the result's, highdicom reads it back; the figure as a Secondary Capture
is valid; both in new series of the source study, with UIDs derived from the job."""

from __future__ import annotations

import copy
import dataclasses
import io
import shutil
import subprocess
import uuid
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import highdicom as hd
import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset

from services.db.job_forms import JobForms
from services.dicom.results import job_figure_sc, job_sr
from services.dicom.sc import build_sc
from services.dicom.sr import (
    COBB_ANGLE,
    PRIVATE_SCHEME,
    VERTEBRA_CODES,
    PrivateCodes,
    SourceImage,
    StudyIdentity,
    build_sr,
)
from services.dicom.sr import (
    CORNERSTONE_COBB_ANGLE as COBB_TOOL,
)
from spine_client.dicom.header import read_header
from spine_engine import register
from spine_engine.figures import render_figure
from tests.conftest import spine_payload
from tools.dicom import synthetic

SPACING = 0.15
JOB = uuid.UUID("0b4f6c1e-8f7a-4a77-9a53-7d6ad0a3f0c1")


@pytest.fixture(scope="module")
def case() -> dict[str, Any]:
    image = synthetic.radiograph(imager_pixel_spacing=(SPACING, SPACING), rows=3200, columns=1200)
    header = read_header(image)
    payload = spine_payload(spacing_mm=SPACING)
    payload["pa"]["pixel_spacing"] = [SPACING, SPACING]
    result = register(payload)
    identity = StudyIdentity(
        study_instance_uid=header.study_instance_uid, patient_id=header.patient_id,
        patient_name=header.patient_name, accession_number=header.accession_number, study_date=header.study_date,
    )  # fmt: skip
    source = SourceImage(header.sop_instance_uid, str(header.sop_class_uid), header.series_instance_uid,
                         header.study_instance_uid, pixel_spacing=(SPACING, SPACING))  # fmt: skip
    return {"image": image, "payload": payload, "result": result, "identity": identity, "source": source}


def _sr(case: dict[str, Any], result: dict[str, Any] | None = None, job: uuid.UUID = JOB) -> Dataset:
    return build_sr(result or case["result"], case["payload"], job, case["identity"], {"pa": case["source"]},
                    content_datetime=datetime(2026, 12, 1, 12, 0, 0))  # fmt: skip


def _write(ds: Dataset, path: Path) -> Path:
    ds.save_as(path, enforce_file_format=True)
    return path


def test_sr_passes_dsrdump(case: dict[str, Any], tmp_path: Path) -> None:
    if shutil.which("dsrdump") is None:
        pytest.skip("dcmtk's dsrdump is not installed (apt-get install dcmtk)")
    path = _write(_sr(case), tmp_path / "sr.dcm")
    run = subprocess.run(["dsrdump", "-v", str(path)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert "E:" not in run.stderr and "W:" not in run.stderr, run.stderr
    assert '(285285000,SCT,"Cobb angle")' not in run.stdout  # a NUM's name is shown by its meaning only
    assert 'NUM:(,,"Cobb angle")' in run.stdout
    assert "Measurement Report" in run.stdout


def test_sr_passes_dciodvfy(case: dict[str, Any], tmp_path: Path) -> None:
    if shutil.which("dciodvfy") is None:
        pytest.skip("dicom3tools' dciodvfy is not installed (apt-get install dicom3tools)")
    path = _write(_sr(case), tmp_path / "sr.dcm")
    run = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True, timeout=60)
    errors = [line for line in (run.stdout + run.stderr).splitlines() if line.startswith("Error")]
    assert errors == []
    assert "Comprehensive3DSR" in run.stdout + run.stderr


def test_sr_reads_back_with_cobb_items_equal_to_the_result(case: dict[str, Any], tmp_path: Path) -> None:
    result = copy.deepcopy(case["result"])
    result["measures"]["cobb"][0]["angle_sd_deg"] = 1.5
    sr = hd.sr.srread(_write(_sr(case, result), tmp_path / "sr.dcm"))
    assert isinstance(sr, hd.sr.Comprehensive3DSR)
    groups = sr.content.get_image_measurement_groups() + sr.content.get_planar_roi_measurement_groups()
    cobbs = [(g, m) for g in groups for m in g.get_measurements(name=COBB_ANGLE)]
    expected = result["measures"]["cobb"]
    assert len(cobbs) == len(expected) >= 1
    for (group, m), curve in zip(cobbs, expected, strict=True):
        assert m.value == pytest.approx(curve["angle_deg"], rel=1e-12)
        assert m.unit.value == "deg" and m.unit.scheme_designator == "UCUM"
        sites = [(s.value.value, s.ContentSequence[0].ConceptCodeSequence[0].CodeMeaning) for s in m.finding_sites]
        assert sites == [
            (VERTEBRA_CODES[curve["upper"]][0], "Superior"),
            (VERTEBRA_CODES[curve["lower"]][0], "Inferior"),
            (VERTEBRA_CODES[curve["apex"]][0], "Apical"),
        ]
        assert m.method.value == PrivateCodes.MEASURED.value
        assert group.tracking_identifier == COBB_TOOL  # on the PA image: the adapters' CobbAngle
    first = cobbs[0][1]
    uncertainty = {item.ConceptNameCodeSequence[0].CodeValue: (item.MeasuredValueSequence[0].NumericValue,
                                                               item.MeasuredValueSequence[0].MeasurementUnitsCodeSequence[0].CodeValue)
                   for item in first[0].ContentSequence if item.ValueType == "NUM"}  # fmt: skip
    # upper and lower measurement uncertainty = 1 SD, in the value's unit
    assert uncertainty == {"371886008": (1.5, "deg"), "371885007": (1.5, "deg")}


def test_cobb_lines_on_the_pa_image(case: dict[str, Any], tmp_path: Path) -> None:
    """Each Cobb angle is a planar ROI group on the PA image whose Cobb NUM holds the two end vertebrae's
    lines (one 4-point POLYLINE): in mm (the image's spacing) they meet at the Cobb angle itself."""
    sr = hd.sr.srread(_write(_sr(case), tmp_path / "sr.dcm"))
    groups = [g for g in sr.content.get_planar_roi_measurement_groups() if g.tracking_identifier == COBB_TOOL]
    curves = case["result"]["measures"]["cobb"]
    assert len(groups) == len(curves) >= 1
    for group, curve in zip(groups, curves, strict=True):
        assert (
            group.roi.ContentSequence[0].ReferencedSOPSequence[0].ReferencedSOPInstanceUID
            == case["image"].SOPInstanceUID
        )
        [num] = group.get_measurements(name=COBB_ANGLE)
        [lines] = [item for item in num[0].ContentSequence if item.ValueType == "SCOORD"]
        assert lines.GraphicType == "POLYLINE" and lines.RelationshipType == "INFERRED FROM"
        assert (
            lines.ContentSequence[0].ReferencedSOPSequence[0].ReferencedSOPInstanceUID == case["image"].SOPInstanceUID
        )
        p = np.asarray(lines.GraphicData, dtype=float).reshape(4, 2) * SPACING  # square pixels: mm
        a, b = p[1] - p[0], p[3] - p[2]
        angle = np.degrees(np.arccos(abs(a @ b) / np.linalg.norm(a) / np.linalg.norm(b)))
        assert angle == pytest.approx(curve["angle_deg"], abs=1e-3)  # GraphicData is float32 (FL)


@pytest.fixture(scope="module")
def mild(case: dict[str, Any]) -> tuple[dict[str, Any], Dataset]:
    """A nearly straight spine on the case's film (no frontal curve of 10°): its result and SR."""
    payload = spine_payload(curve_mm=1.5, spacing_mm=SPACING)
    payload["pa"]["pixel_spacing"] = [SPACING, SPACING]
    result = register(payload)
    assert result["measures"]["cobb"] == [] and not result["measures"]["largest_cobb"]["reported_as_curve"]
    sr = build_sr(result, payload, JOB, case["identity"], {"pa": case["source"]},
                  content_datetime=datetime(2026, 12, 1, 12, 0, 0))  # fmt: skip
    return result, sr


def _dsrdump_of_a_valid_sr(ds: Dataset, tmp_path: Path) -> str:
    """dsrdump's listing of the SR ``ds``, once dciodvfy found no error in it and dsrdump neither error nor
    warning."""
    if shutil.which("dciodvfy") is None or shutil.which("dsrdump") is None:
        pytest.skip("dicom3tools' dciodvfy or dcmtk's dsrdump is not installed (apt-get install dicom3tools dcmtk)")
    path = _write(ds, tmp_path / "sr.dcm")
    run = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True, timeout=60)
    assert [line for line in (run.stdout + run.stderr).splitlines() if line.startswith("Error")] == []
    run = subprocess.run(["dsrdump", "-v", str(path)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0 and "E:" not in run.stderr and "W:" not in run.stderr, run.stderr
    return run.stdout


def test_the_sr_of_a_spine_below_the_threshold_passes_dciodvfy_and_dsrdump(
    mild: tuple[dict[str, Any], Dataset], tmp_path: Path
) -> None:
    assert 'NUM:(,,"Cobb angle")' in _dsrdump_of_a_valid_sr(mild[1], tmp_path)


def test_a_spine_below_the_threshold_has_its_largest_angle_drawn(
    mild: tuple[dict[str, Any], Dataset], tmp_path: Path
) -> None:
    """No curve of 10°: one Cobb angle group, ``largest_cobb`` (value, its two end vertebrae, not the
    major curve), drawn on the PA image as the adapters' CobbAngle, its lines meeting at the angle."""
    largest = mild[0]["measures"]["largest_cobb"]
    sr = hd.sr.srread(_write(mild[1], tmp_path / "sr.dcm"))
    groups = [g for g in sr.content.get_planar_roi_measurement_groups() if g.tracking_identifier == COBB_TOOL]
    assert len(groups) == 1
    [num] = groups[0].get_measurements(name=COBB_ANGLE)
    assert num.value == pytest.approx(largest["angle_deg"], rel=1e-12)
    sites = [s.value.value for s in num.finding_sites]
    assert sites == [VERTEBRA_CODES[largest["upper"]][0], VERTEBRA_CODES[largest["lower"]][0]]
    [lines] = [item for item in num[0].ContentSequence if item.ValueType == "SCOORD"]
    p = np.asarray(lines.GraphicData, dtype=float).reshape(4, 2) * SPACING
    a, b = p[1] - p[0], p[3] - p[2]
    angle = np.degrees(np.arccos(abs(a @ b) / np.linalg.norm(a) / np.linalg.norm(b)))
    assert angle == pytest.approx(largest["angle_deg"], abs=1e-3)


def test_sr_identity_series_and_scheme(case: dict[str, Any]) -> None:
    sr = _sr(case)
    image = case["image"]
    assert sr.StudyInstanceUID == image.StudyInstanceUID
    assert sr.SeriesInstanceUID != image.SeriesInstanceUID
    assert (sr.PatientID, str(sr.PatientName), sr.AccessionNumber, sr.StudyDate) == (
        "P-0001", "Doe^Jane", "ACC-42", "20261130")  # fmt: skip
    assert sr.Modality == "SR"
    [scheme] = sr.CodingSchemeIdentificationSequence
    assert scheme.CodingSchemeDesignator == PRIVATE_SCHEME
    evidence = sr.CurrentRequestedProcedureEvidenceSequence[0].ReferencedSeriesSequence[0]
    assert evidence.ReferencedSOPSequence[0].ReferencedSOPInstanceUID == image.SOPInstanceUID


def test_sr_uids_derive_from_the_job(case: dict[str, Any]) -> None:
    a, b, other = _sr(case), _sr(case), _sr(case, job=uuid.uuid4())
    assert (a.SOPInstanceUID, a.SeriesInstanceUID) == (b.SOPInstanceUID, b.SeriesInstanceUID)
    assert a.SOPInstanceUID != other.SOPInstanceUID and a.SeriesInstanceUID != other.SeriesInstanceUID
    assert a.SOPInstanceUID.startswith("2.25.") and len(a.SOPInstanceUID) <= 64


def test_model_based_quantities_are_marked(case: dict[str, Any], tmp_path: Path) -> None:
    result = copy.deepcopy(case["result"])
    result["fit"]["unreliable"] = ["kyphosis", "lordosis", "axial_rotation"]
    result["fit"]["boundary"] = "estimated"  # no vertebra's pose is the payload's
    sr = hd.sr.srread(_write(_sr(case, result), tmp_path / "sr.dcm"))
    methods: dict[str, set[str]] = {}
    for group in sr.content.get_image_measurement_groups() + sr.content.get_planar_roi_measurement_groups():
        for m in group.get_measurements():
            methods.setdefault(m.name.value, set()).add(m.method.value)
    assert methods[COBB_ANGLE.value] == {"MEASURED"}
    assert methods[PrivateCodes.KYPHOSIS_T4_T12.value] == {"MODEL-BASED"}
    assert methods[PrivateCodes.LORDOSIS_L1_L5.value] == {"MODEL-BASED"}
    assert methods[PrivateCodes.AXIAL_ROTATION.value] == {"MODEL-BASED"}
    assert methods[PrivateCodes.FRONTAL_BENDING.value] == {"MEASURED"}


def test_cobb_angles_are_model_based_when_the_pa_film_does_not_reach_every_level(
    case: dict[str, Any], tmp_path: Path
) -> None:
    """``fit.unreliable`` ``cobb`` (PA landmarks short of T1 or L5, or a Cobb SD past half the population's):
    every frontal Cobb angle is MODEL-BASED; the measures it does not name stay MEASURED."""
    result = copy.deepcopy(case["result"])
    result["fit"]["unreliable"] = ["cobb"]
    sr = hd.sr.srread(_write(_sr(case, result), tmp_path / "sr.dcm"))
    methods: dict[str, set[str]] = {}
    for group in sr.content.get_image_measurement_groups() + sr.content.get_planar_roi_measurement_groups():
        for m in group.get_measurements():
            methods.setdefault(m.name.value, set()).add(m.method.value)
    assert methods[COBB_ANGLE.value] == {"MODEL-BASED"}
    assert methods[PrivateCodes.KYPHOSIS_T4_T12.value] == {"MEASURED"}
    assert methods[PrivateCodes.FRONTAL_BENDING.value] == {"MEASURED"}


def test_landmarks_are_scoord_on_the_source_image(case: dict[str, Any], tmp_path: Path) -> None:
    sr = hd.sr.srread(_write(_sr(case), tmp_path / "sr.dcm"))
    regions = [g for g in sr.content.get_planar_roi_measurement_groups() if g.tracking_identifier != COBB_TOOL]
    assert len(regions) == 17
    first = regions[0]
    roi = first.roi
    assert roi.GraphicType == "POINT"
    assert list(roi.GraphicData) == pytest.approx(case["payload"]["pa"]["landmarks"][0]["point"], abs=1e-3)
    ref = roi.ContentSequence[0].ReferencedSOPSequence[0]
    assert ref.ReferencedSOPInstanceUID == case["image"].SOPInstanceUID


def _regions(sr: Dataset, tmp_path: Path) -> list[Any]:
    groups = hd.sr.srread(_write(sr, tmp_path / "sr.dcm")).content.get_planar_roi_measurement_groups()
    return [g for g in groups if g.tracking_identifier != COBB_TOOL]


def test_landmarks_in_mm_are_converted_with_the_spacing(case: dict[str, Any], tmp_path: Path) -> None:
    payload = spine_payload()  # mm
    result = register(payload)
    source = SourceImage(case["source"].sop_instance_uid, case["source"].sop_class_uid, pixel_spacing=(0.2, 0.1))
    groups = _regions(build_sr(result, payload, JOB, case["identity"], {"pa": source}), tmp_path)
    col_mm, row_mm = payload["pa"]["landmarks"][0]["point"]
    assert list(groups[0].roi.GraphicData) == pytest.approx([col_mm / 0.1, row_mm / 0.2], rel=1e-6)
    no_spacing = SourceImage(case["source"].sop_instance_uid, case["source"].sop_class_uid)
    assert _regions(build_sr(result, payload, JOB, case["identity"], {"pa": no_spacing}), tmp_path) == []


def test_sr_without_source_study_opens_a_derived_study(case: dict[str, Any], tmp_path: Path) -> None:
    sr = build_sr(case["result"], case["payload"], JOB, StudyIdentity())
    assert sr.StudyInstanceUID.startswith("2.25.") and sr.StudyInstanceUID != case["image"].StudyInstanceUID
    assert "CurrentRequestedProcedureEvidenceSequence" not in sr
    assert _regions(sr, tmp_path) == []


def test_figure_as_secondary_capture(case: dict[str, Any], tmp_path: Path) -> None:
    png = render_figure(case["result"], case["payload"], dpi=40)
    sc = build_sc(png, JOB, case["identity"])
    sr = _sr(case)
    assert sc.StudyInstanceUID == sr.StudyInstanceUID == case["image"].StudyInstanceUID
    assert sc.SeriesInstanceUID not in (sr.SeriesInstanceUID, case["image"].SeriesInstanceUID)
    assert sc.SOPInstanceUID == build_sc(png, JOB, case["identity"]).SOPInstanceUID
    assert sc.PhotometricInterpretation == "RGB" and sc.SamplesPerPixel == 3 and sc.BitsAllocated == 8
    assert sc.pixel_array.shape[2] == 3 and sc.pixel_array.shape[:2] == (sc.Rows, sc.Columns)
    assert (sc.PatientID, sc.AccessionNumber) == ("P-0001", "ACC-42")
    path = _write(sc, tmp_path / "sc.dcm")
    if shutil.which("dciodvfy") is None:
        pytest.skip("dicom3tools' dciodvfy is not installed (apt-get install dicom3tools)")
    run = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True, timeout=60)
    assert [line for line in (run.stdout + run.stderr).splitlines() if line.startswith("Error")] == []


def test_job_results_are_the_same_bytes_on_every_build(case: dict[str, Any]) -> None:
    image = case["image"]
    payload = {**case["payload"], "study": {"study_instance_uid": image.StudyInstanceUID, "patient_id": "P-0001"}}
    provenance = {"pa": {"sop_instance_uid": image.SOPInstanceUID, "sop_class_uid": str(image.SOPClassUID),
                         "series_instance_uid": image.SeriesInstanceUID}}  # fmt: skip
    finished = datetime(2026, 12, 1, 12, 0, 0)
    forms = JobForms(posted=payload, provenance=provenance, result=case["result"])
    first = job_sr(JOB, forms, finished)
    assert first == job_sr(JOB, JobForms(posted=payload, provenance=provenance, result=case["result"]), finished)
    assert job_figure_sc(JOB, forms, finished) == job_figure_sc(JOB, forms, finished)
    without = JobForms(posted=payload, provenance=None, result=case["result"])
    assert job_sr(JOB, without, finished) != first  # without provenance: no image reference


def test_a_name_beyond_ascii_is_written_in_utf8_and_declared(case: dict[str, Any], tmp_path: Path) -> None:
    """PS3.3 §C.12.1.1.2: a dataset with text beyond the default repertoire (ASCII) declares its
    character set; ISO_IR 192 (UTF-8, PS3.5 §6.1.2.5.3) holds any name. Without it an ideographic
    name was written as "?" and a Latin one in undeclared Latin-1."""
    identity = dataclasses.replace(case["identity"], patient_name="Müller^Jürgen=山田^太郎", patient_id="P-é1")
    sr = build_sr(case["result"], case["payload"], JOB, identity, {"pa": case["source"]})
    sc = build_sc(render_figure(case["result"], case["payload"], dpi=40), JOB, identity)
    for name, ds in (("sr", sr), ("sc", sc)):
        assert ds.SpecificCharacterSet == "ISO_IR 192"
        back = pydicom.dcmread(_write(ds, tmp_path / f"{name}.dcm"))
        assert (str(back.PatientName), back.PatientID) == ("Müller^Jürgen=山田^太郎", "P-é1")
        if shutil.which("dciodvfy") is not None:
            run = subprocess.run(["dciodvfy", str(tmp_path / f"{name}.dcm")], capture_output=True, text=True,
                                 timeout=60)  # fmt: skip
            assert [line for line in (run.stdout + run.stderr).splitlines() if line.startswith("Error")] == []
    assert "SpecificCharacterSet" not in _sr(case)  # ASCII only: the default repertoire, nothing declared


def _methods(sr: Dataset, tmp_path: Path) -> dict[tuple[str, str | None], set[str]]:
    """Each measurement's method by (code value, the vertebra of its group's one finding site)."""
    read = hd.sr.srread(_write(sr, tmp_path / "methods.dcm"))
    methods: dict[tuple[str, str | None], set[str]] = {}
    levels = {code: level for level, (code, _) in VERTEBRA_CODES.items()}
    for group in read.content.get_image_measurement_groups() + read.content.get_planar_roi_measurement_groups():
        for m in group.get_measurements():
            sites = [levels.get(s.value.value) for s in (m.finding_sites or [])]
            methods.setdefault((m.name.value, sites[0] if len(sites) == 1 else None), set()).add(m.method.value)
    return methods


def test_population_axial_rotation_is_model_based(case: dict[str, Any], tmp_path: Path) -> None:
    """No pedicles, T1 and L5 given: ``fit.assumed`` names population_axial_rotation: every axial
    rotation is MODEL-BASED but T1's and L5's, the boundary's own poses."""
    fit = case["result"]["fit"]
    assert fit["boundary"] == "given"
    assert "population_axial_rotation" in [a["name"] for a in fit["assumed"]]
    sr = _sr(case)
    by_level: dict[str, set[str]] = {}
    for group in hd.sr.srread(_write(sr, tmp_path / "sr.dcm")).content.get_image_measurement_groups():
        if group.tracking_identifier.startswith("Vertebra "):
            found = [m for m in group.get_measurements() if m.name.value == PrivateCodes.AXIAL_ROTATION.value]
            by_level[group.tracking_identifier.removeprefix("Vertebra ")] = {m.method.value for m in found}
    assert by_level.pop("T1") == by_level.pop("L5") == {"MEASURED"}
    assert by_level and set().union(*by_level.values()) == {"MODEL-BASED"}
    apex = {k: v for k, v in _methods(sr, tmp_path).items() if k[0] == PrivateCodes.APEX_AXIAL_ROTATION.value}
    assert apex and set().union(*apex.values()) == {"MODEL-BASED"}


def test_sr_and_sc_dates_and_times_are_utc_and_say_so(case: dict[str, Any], tmp_path: Path) -> None:
    """PS3.3 §C.12.1.1.8: DA and TM without Timezone Offset From UTC (0008,0201) read as local time; the
    job's end (23:30 in Paris, 21:30 UTC) is written in UTC with the offset +0000."""
    finished = datetime(2026, 3, 1, 23, 30, tzinfo=timezone(timedelta(hours=2)))
    sr = build_sr(case["result"], case["payload"], JOB, case["identity"], {"pa": case["source"]},
                  content_datetime=finished)  # fmt: skip
    sc = build_sc(render_figure(case["result"], case["payload"], dpi=40), JOB, case["identity"],
                  content_datetime=finished)  # fmt: skip
    for name, ds in (("sr", sr), ("sc", sc)):
        back = pydicom.dcmread(_write(ds, tmp_path / f"{name}.dcm"))
        assert back.TimezoneOffsetFromUTC == "+0000"
        assert (back.ContentDate, back.ContentTime) == ("20260301", "213000")
        assert (back.InstanceCreationDate, back.InstanceCreationTime) == ("20260301", "213000")
        assert back.ContributingEquipmentSequence[0].ContributionDateTime == "20260301213000+0000"
        if shutil.which("dciodvfy") is not None:
            run = subprocess.run(["dciodvfy", str(tmp_path / f"{name}.dcm")], capture_output=True, text=True,
                                 timeout=60)  # fmt: skip
            assert [line for line in (run.stdout + run.stderr).splitlines() if line.startswith("Error")] == []
    assert (str(sc.DateOfSecondaryCapture), str(sc.TimeOfSecondaryCapture)) == ("20260301", "213000")
    naive = build_sr(case["result"], case["payload"], JOB, case["identity"], content_datetime=datetime(2026, 3, 1, 9))
    assert (str(naive.ContentTime), naive.TimezoneOffsetFromUTC) == ("090000", "+0000")  # the job's UTC timestamps


def test_an_end_vertebra_without_a_landmark_is_drawn_where_the_fit_projects_it() -> None:
    """Landmarks on T1..T6 only, the largest angle T1–L5: the L5 line is drawn at the reconstructed L5
    on the film (``spine_engine.figures.model_points``), not across T6's landmark."""
    from spine_engine.figures import model_points
    from spine_engine.levels import LEVELS

    points = [[(100 + 15 * np.sin(np.pi * i / 16)) / SPACING, (50 + 420 * i / 16) / SPACING] for i in range(6)]
    landmarks = [{"level": lv, "point": p} for lv, p in zip(LEVELS, points, strict=False)]
    payload = {"pa": {"units": "px", "pixel_spacing": [SPACING, SPACING], "landmarks": landmarks}}
    result = register(copy.deepcopy(payload))
    largest = result["measures"]["largest_cobb"]
    assert (largest["upper"], largest["lower"]) == ("T1", "L5")
    image = SourceImage("1.2.3.4", "1.2.840.10008.5.1.4.1.1.1.1", "1.2.3", "1.2", (SPACING, SPACING))
    sr = build_sr(result, payload, JOB, StudyIdentity(study_instance_uid="1.2"), {"pa": image})
    [group] = [g for g in sr_groups(sr) if g.tracking_identifier == COBB_TOOL]
    [num] = group.get_measurements(name=COBB_ANGLE)
    [lines] = [item for item in num[0].ContentSequence if item.ValueType == "SCOORD"]
    p = np.asarray(lines.GraphicData, dtype=float).reshape(4, 2)
    projected = model_points(result, payload, "pa") / SPACING  # detector mm → px
    assert p[:2].mean(axis=0) == pytest.approx(points[0], abs=1e-3)  # T1: its landmark
    assert p[2:].mean(axis=0) == pytest.approx(projected[-1], abs=1e-2)  # L5: the model's, on the film
    assert np.linalg.norm(p[2:].mean(axis=0) - points[5]) > 1000  # far below T6 (over 150 mm)
    a, b = (p[1] - p[0]) * SPACING, (p[3] - p[2]) * SPACING
    angle = np.degrees(np.arccos(abs(a @ b) / np.linalg.norm(a) / np.linalg.norm(b)))
    assert angle == pytest.approx(largest["angle_deg"], abs=1e-3)


def sr_groups(sr: Dataset) -> list[Any]:
    buffer = io.BytesIO()
    sr.save_as(buffer, enforce_file_format=True)
    buffer.seek(0)
    return list(hd.sr.srread(buffer).content.get_planar_roi_measurement_groups())


UPPER_UNCERTAINTY, LOWER_UNCERTAINTY = "371886008", "371885007"  # TID 310 (PS3.16), one SD each


def _uncertainty(measurement: Any) -> tuple[float, float] | None:
    """A NUM's TID 310 upper and lower measurement uncertainty (its SD, the value's unit checked), None
    when it has none."""
    found = {item.ConceptNameCodeSequence[0].CodeValue: item.MeasuredValueSequence[0]
             for item in measurement[0].ContentSequence if item.ValueType == "NUM"}  # fmt: skip
    if not found:
        return None
    units = {v.MeasurementUnitsCodeSequence[0].CodeValue for v in found.values()}
    assert units == {measurement.unit.value}
    return float(found[UPPER_UNCERTAINTY].NumericValue), float(found[LOWER_UNCERTAINTY].NumericValue)


def _cobb_groups(sr: Dataset, tmp_path: Path) -> list[dict[str, Any]]:
    """Each Cobb curve's group, its measurements by code value."""
    content: Any = hd.sr.srread(_write(sr, tmp_path / "cobb.dcm")).content  # a MeasurementReport
    return [{m.name.value: m for m in g.get_measurements()} for g in content.get_planar_roi_measurement_groups()
            if g.tracking_identifier == COBB_TOOL]  # fmt: skip


@pytest.fixture(scope="module")
def short_film(case: dict[str, Any]) -> tuple[dict[str, Any], Dataset]:
    """The case's spine with PA landmarks on T1–T7 only: the frontal Cobb angles depend on levels the film
    does not show, so ``fit.unreliable`` names ``cobb`` (the reviewer's job); its result and SR."""
    payload = spine_payload(spacing_mm=SPACING)
    payload["pa"]["pixel_spacing"] = [SPACING, SPACING]
    payload["pa"]["landmarks"] = payload["pa"]["landmarks"][:7]
    result = register(payload)
    assert "cobb" in result["fit"]["unreliable"] and result["measures"]["cobb"]
    sr = build_sr(result, payload, JOB, case["identity"], {"pa": case["source"]},
                  content_datetime=datetime(2026, 12, 1, 12, 0, 0))  # fmt: skip
    return result, sr


def test_the_endplate_variant_of_a_model_estimated_cobb_angle_is_the_same_estimate(
    case: dict[str, Any], short_film: tuple[dict[str, Any], Dataset], tmp_path: Path
) -> None:
    """``fit.unreliable`` ``cobb``: the Cobb angle between the end vertebrae's endplates is the same model
    estimate as the Cobb angle (MODEL-BASED, its SD as TID 310 uncertainty), not a MEASURED value without
    one; on the full film both are MEASURED and the variant has no SD (the result gives none)."""
    result, sr = short_film
    groups = _cobb_groups(sr, tmp_path)
    assert len(groups) == len(result["measures"]["cobb"])
    for group, curve in zip(groups, result["measures"]["cobb"], strict=True):
        cobb, endplates = group[COBB_ANGLE.value], group[PrivateCodes.ENDPLATE_ANGLE.value]
        assert endplates.value == pytest.approx(curve["endplate_angle_deg"], rel=1e-12)
        assert cobb.method.value == endplates.method.value == PrivateCodes.MODEL_BASED.value
        assert _uncertainty(endplates) == _uncertainty(cobb) == pytest.approx((curve["angle_sd_deg"],) * 2, rel=1e-12)
    for group in _cobb_groups(_sr(case), tmp_path):
        endplates = group[PrivateCodes.ENDPLATE_ANGLE.value]
        assert endplates.method.value == PrivateCodes.MEASURED.value and _uncertainty(endplates) is None


def test_each_cobb_groups_apical_rotation_carries_the_apexs_sd(
    case: dict[str, Any], short_film: tuple[dict[str, Any], Dataset], tmp_path: Path
) -> None:
    """The apical axial rotation NUM of every Cobb group has the apex vertebra's ``axial_rotation_sd_deg``
    as its uncertainty, as the vertebra's own group has; the plane of maximum curvature and the Cobb angle
    in it have none (the result gives none) and are MODEL-BASED with the Cobb angle (``cobb``)."""
    for result, sr in ((case["result"], _sr(case)), short_film):
        sds = {v["level"]: v["axial_rotation_sd_deg"] for v in result["vertebrae"]}
        groups = _cobb_groups(sr, tmp_path)
        assert len(groups) == len(result["measures"]["cobb"]) >= 1
        for group, curve in zip(groups, result["measures"]["cobb"], strict=True):
            apex = group[PrivateCodes.APEX_AXIAL_ROTATION.value]
            assert sds[curve["apex"]] is not None
            assert _uncertainty(apex) == pytest.approx((sds[curve["apex"]],) * 2, rel=1e-12)
            expected = "MODEL-BASED" if "cobb" in result["fit"]["unreliable"] else "MEASURED"
            for code in (PrivateCodes.PLANE_MAX_CURVATURE, PrivateCodes.MAX_CURVATURE):
                assert _uncertainty(group[code.value]) is None
                assert group[code.value].method.value == expected


def test_the_sr_of_a_short_pa_film_passes_dciodvfy_and_dsrdump(
    short_film: tuple[dict[str, Any], Dataset], tmp_path: Path
) -> None:
    assert 'NUM:(,,"Cobb angle")' in _dsrdump_of_a_valid_sr(short_film[1], tmp_path)


def test_the_landmark_misfit_ratio_is_a_num_of_no_units(case: dict[str, Any], tmp_path: Path) -> None:
    """``fit.landmark_misfit_ratio`` (above 1: every SD widened by it) reaches the PACS as a NUM of the
    private scheme in UCUM "1" (no units), equal to the result's; a result without it writes none."""

    def misfit_nums(ratio: float | None, name: str) -> list[Any]:
        result = copy.deepcopy(case["result"])
        result["fit"]["landmark_misfit_ratio"] = ratio
        sr = hd.sr.srread(_write(_sr(case, result), tmp_path / name))
        groups = sr.content.get_image_measurement_groups() + sr.content.get_planar_roi_measurement_groups()
        return [m for g in groups for m in g.get_measurements() if m.name.value == PrivateCodes.MISFIT_RATIO.value]

    found = misfit_nums(1.37, "sr.dcm")
    assert len(found) == 1 and found[0].value == pytest.approx(1.37, rel=1e-12)
    assert (found[0].unit.value, found[0].unit.scheme_designator) == ("1", "UCUM")
    assert not misfit_nums(None, "sr-none.dcm")
