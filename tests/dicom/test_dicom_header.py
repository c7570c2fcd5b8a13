"""Reading a radiograph's header: each pixel-spacing case of PS3.3 §10.7.1.1 as Cornerstone3D reads
it, orientation, acquisition geometry, identity, and each bad input as a typed error naming the
attribute by keyword and tag. Merging header values into a payload: payload wins, conflicts listed."""

from __future__ import annotations

import io
from datetime import date
from typing import Any

import pytest
from pydicom.dataelem import RawDataElement
from pydicom.dataset import Dataset
from pydicom.tag import Tag

from services.db.job_forms import engine_payload
from spine_client.dicom.errors import InvalidAttribute, MissingAttribute, NotDicom, UnsupportedOrientation
from spine_client.dicom.header import read_header
from spine_client.dicom.merge import apply_headers
from spine_engine.models import Study
from tools.dicom import synthetic


def part10(ds: Dataset) -> bytes:
    out = io.BytesIO()
    ds.save_as(out, enforce_file_format=True)
    return out.getvalue()


# (case, radiograph kwargs, expected spacing [row, col], contract calibration, Cornerstone3D type)
SPACING_CASES: list[tuple[str, dict[str, Any], tuple[float, float] | None, str | None, str | None]] = [
    ("geometry", dict(pixel_spacing=(0.14, 0.13), imager_pixel_spacing=(0.15, 0.15), calibration_type="GEOMETRY"),
     (0.14, 0.13), "calibrated", "ERMF"),
    ("fiducial", dict(pixel_spacing=(0.12, 0.12), imager_pixel_spacing=(0.15, 0.15), calibration_type="FIDUCIAL"),
     (0.12, 0.12), "calibrated", "Calibrated"),
    ("ermf", dict(imager_pixel_spacing=(0.15, 0.15), ermf=1.25), (0.12, 0.12), "calibrated", "ERMF"),
    ("sid/sod", dict(imager_pixel_spacing=(0.15, 0.15), sid=1800.0, sod=1500.0), (0.125, 0.125), "calibrated", "ERMF"),
    ("sid/dse", dict(imager_pixel_spacing=(0.15, 0.15), sid=1800.0, dse=1200.0), (0.1, 0.1), "calibrated", "ERMF"),
    ("ps<ips", dict(pixel_spacing=(0.1, 0.1), imager_pixel_spacing=(0.15, 0.15)), (0.1, 0.1), "calibrated", "ERMF"),
    ("ps=ips", dict(pixel_spacing=(0.15, 0.15), imager_pixel_spacing=(0.15, 0.15)), (0.15, 0.15), "projection", "Proj"),
    ("ips only", dict(imager_pixel_spacing=(0.2, 0.15)), (0.2, 0.15), "detector", "Proj"),
    ("illegal ermf", dict(imager_pixel_spacing=(0.15, 0.15), ermf=0.9), (0.15, 0.15), "detector", "Proj"),
    ("ps only", dict(pixel_spacing=(0.18, 0.18), imager_pixel_spacing=None), (0.18, 0.18), "unknown", "Unknown"),
    ("none", dict(imager_pixel_spacing=None), None, None, None),
]  # fmt: skip


@pytest.mark.parametrize(("case", "kwargs", "spacing", "calibration", "cornerstone"), SPACING_CASES,
                         ids=[c[0] for c in SPACING_CASES])  # fmt: skip
def test_spacing_cases(case: str, kwargs: dict[str, Any], spacing: Any, calibration: Any, cornerstone: Any) -> None:
    header = read_header(part10(synthetic.radiograph(**kwargs)))
    if spacing is None:
        assert header.pixel_spacing is None
    else:
        assert header.pixel_spacing is not None
        assert header.pixel_spacing == pytest.approx(spacing, rel=1e-9)
    assert header.pixel_spacing_calibration == calibration
    assert header.cornerstone_calibration_type == cornerstone
    if case == "illegal ermf":
        assert any("EstimatedRadiographicMagnificationFactor (0018,1114)" in w for w in header.warnings)
    if spacing is not None:
        assert "(0028,0030)" in header.sources["pixel_spacing"] or "(0018,1164)" in header.sources["pixel_spacing"]


def test_non_projection_sop_class_takes_pixel_spacing_as_unknown() -> None:
    ds = synthetic.radiograph(pixel_spacing=(0.3, 0.3), imager_pixel_spacing=(0.15, 0.15))
    ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.7"  # Secondary Capture
    header = read_header(part10(ds))
    assert header.pixel_spacing == (0.3, 0.3)
    assert header.pixel_spacing_calibration == "unknown" and header.cornerstone_calibration_type == ""


@pytest.mark.parametrize("transfer_syntax", ["explicit", "implicit", "big"])
@pytest.mark.parametrize("photometric", ["MONOCHROME1", "MONOCHROME2"])
@pytest.mark.parametrize("modality", ["DX", "CR"])
def test_transfer_syntaxes_and_photometric_read_the_same(transfer_syntax: Any, photometric: Any, modality: Any) -> None:
    ds = synthetic.radiograph(modality=modality, photometric=photometric, transfer_syntax=transfer_syntax,
                              imager_pixel_spacing=(0.15, 0.15), ermf=1.2, sid=1800.0)  # fmt: skip
    header = read_header(part10(ds))
    assert header.pixel_spacing == pytest.approx((0.125, 0.125))
    assert header.photometric_interpretation == photometric
    assert header.modality == modality
    assert (header.rows, header.columns) == (64, 32)
    assert header.patient_orientation == ("L", "F") and header.view == "pa"
    assert header.study_instance_uid == ds.StudyInstanceUID and header.sop_instance_uid == ds.SOPInstanceUID
    assert header.series_instance_uid == ds.SeriesInstanceUID
    assert (header.patient_id, header.patient_name, header.accession_number) == ("P-0001", "Doe^Jane", "ACC-42")
    assert header.study_date == date(2026, 11, 30)


def test_reads_from_path_dataset_and_dicom_json(tmp_path: Any) -> None:
    ds = synthetic.radiograph(pixel_spacing=(0.14, 0.14), calibration_type="FIDUCIAL")
    path = tmp_path / "pa.dcm"
    synthetic.write(ds, path)
    from_path, from_ds, from_json = read_header(path), read_header(ds), read_header(ds.to_json_dict())
    assert from_path == from_ds == from_json


def test_acquisition_geometry() -> None:
    header = read_header(synthetic.radiograph(imager_pixel_spacing=(0.15, 0.15), ermf=1.2, sid=1800.0, sod=1700.0))
    assert header.acquisition.magnification == pytest.approx(1.2)
    assert header.acquisition.distance_source_to_detector_mm == 1800.0
    assert header.acquisition.distance_source_to_patient_mm == pytest.approx(1500.0)  # SID / ERMF
    both = read_header(synthetic.radiograph(sid=1800.0, sod=1700.0, dse=1500.0)).acquisition
    assert both.distance_source_to_patient_mm == pytest.approx(1600.0)  # mid-plane
    assert both.magnification is None
    only = read_header(synthetic.radiograph(sid=1800.0, sod=1700.0))
    assert only.acquisition.distance_source_to_patient_mm == 1700.0
    assert "DistanceSourceToPatient (0018,1111)" in only.sources["acquisition.distance_source_to_patient_mm"]
    assert read_header(synthetic.radiograph()).acquisition.as_payload() == {}


def test_a_geometry_value_that_is_no_distance_is_left_out_with_a_warning() -> None:
    """A writer's 0 (or a negative value, or one that is not a number) for SID, DSP, DSE or ERMF is no distance
    or ratio: the header is read as without it, and says so."""
    header = read_header(synthetic.radiograph(sid=0.0, sod=1600.0))
    assert header.acquisition.distance_source_to_detector_mm is None
    assert header.acquisition.distance_source_to_patient_mm == 1600.0
    assert "DistanceSourceToDetector (0018,1110) is 0: not a distance, left out" in header.warnings
    both = read_header(synthetic.radiograph(sid=1800.0, sod=-5.0, dse=1450.0, ermf=0.0))
    assert both.acquisition.distance_source_to_patient_mm == 1450.0  # (0040,0306) alone
    assert both.acquisition.magnification is None
    assert both.pixel_spacing == pytest.approx((0.15 * 1450 / 1800, 0.15 * 1450 / 1800))  # SID/SOD
    assert [w.split(" is ")[0] for w in both.warnings if "left out" in w] == [
        "EstimatedRadiographicMagnificationFactor (0018,1114)", "DistanceSourceToPatient (0018,1111)"]
    ds = synthetic.radiograph(sod=1600.0)
    tag = Tag(0x0018, 0x1110)
    ds._dict[tag] = RawDataElement(tag, "DS", 6, b"1800mm", 0, False, True)  # not a DS pydicom would write
    header = read_header(ds)
    assert header.acquisition.distance_source_to_detector_mm is None
    assert any(w.startswith("DistanceSourceToDetector (0018,1110) is") and w.endswith("left out")
               for w in header.warnings), header.warnings


@pytest.mark.parametrize(("orientation", "view_position", "expected", "view", "assumed"), [
    (("L", "F"), None, ("L", "F"), "pa", False),
    (("R", "F"), "AP", ("R", "F"), "pa", False),
    (("A", "F"), "LL", ("A", "F"), "lateral", False),
    (("P", "F"), None, ("P", "F"), "lateral", False),
    (("LF", "FR"), None, ("L", "F"), "pa", False),
    (None, "PA", ("L", "F"), "pa", True),
    (None, "AP", ("L", "F"), "pa", True),
    (None, "LL", ("A", "F"), "lateral", True),
    (None, "RL", ("A", "F"), "lateral", True),
])  # fmt: skip
def test_orientation(orientation: Any, view_position: Any, expected: Any, view: Any, assumed: bool) -> None:
    header = read_header(synthetic.radiograph(patient_orientation=orientation, view_position=view_position))
    assert header.patient_orientation == expected
    assert header.view == view
    assert header.orientation_assumed is assumed
    assert ("ViewPosition (0018,5101)" in header.sources["patient_orientation"]) is assumed


def test_oblique_orientation_is_warned() -> None:
    header = read_header(synthetic.radiograph(patient_orientation=("LF", "F")))
    assert header.patient_orientation == ("L", "F")
    assert any("oblique" in w for w in header.warnings)


# ------------------------------------------------------------------ bad input


def test_not_dicom() -> None:
    with pytest.raises(NotDicom, match="not a DICOM file"):
        read_header(b"PNG\x89 this is not a DICOM file" * 10)
    with pytest.raises(NotDicom):
        read_header({"not": "dicom json"})


@pytest.mark.parametrize(("orientation", "view_position", "label"), [
    (("L", "P"), None, "PatientOrientation (0020,0020)"),
    (None, "RLO", "ViewPosition (0018,5101)"),
    (None, "LLD", "ViewPosition (0018,5101)"),
])  # fmt: skip
def test_orientation_not_pa_or_lateral(orientation: Any, view_position: Any, label: str) -> None:
    with pytest.raises(UnsupportedOrientation) as info:
        read_header(synthetic.radiograph(patient_orientation=orientation, view_position=view_position))
    assert label in str(info.value)


@pytest.mark.parametrize(("orientation", "message"), [
    (("L",), "has 1" ), (("L", "L"), "one patient axis"), (("X", "F"), "letters of L, R, A, P, H, F"),
])  # fmt: skip
def test_bad_patient_orientation(orientation: Any, message: str) -> None:
    ds = synthetic.radiograph()
    ds.PatientOrientation = list(orientation)
    with pytest.raises(InvalidAttribute) as info:
        read_header(ds)
    assert "PatientOrientation (0020,0020)" in str(info.value)
    assert info.value.labels == ["PatientOrientation (0020,0020)"]


def test_no_orientation_and_none_given() -> None:
    header = read_header(synthetic.radiograph(patient_orientation=None, view_position=None))
    assert header.patient_orientation is None
    with pytest.raises(MissingAttribute) as info:
        apply_headers({"pa": {"landmarks": []}}, {"pa": header}, source="file")
    assert "PatientOrientation (0020,0020)" in str(info.value) and info.value.field == "pa.patient_orientation"


def test_no_spacing_and_none_given() -> None:
    header = read_header(synthetic.radiograph(imager_pixel_spacing=None))
    with pytest.raises(MissingAttribute) as info:
        apply_headers({"pa": {"units": "px", "landmarks": []}}, {"pa": header}, source="file")
    text = str(info.value)
    assert "PixelSpacing (0028,0030)" in text and "ImagerPixelSpacing (0018,1164)" in text
    assert info.value.field == "pa.pixel_spacing"
    merged, _ = apply_headers({"pa": {"units": "px", "pixel_spacing": [0.2, 0.2], "landmarks": []}},
                              {"pa": header}, source="file")  # fmt: skip
    assert merged["pa"]["pixel_spacing"] == [0.2, 0.2]


@pytest.mark.parametrize(("keyword", "value", "label"), [
    ("SOPInstanceUID", "1.2.03", "SOPInstanceUID (0008,0018)"),
    ("StudyInstanceUID", "abc.1", "StudyInstanceUID (0020,000D)"),
    ("SeriesInstanceUID", "1." + "2" * 70, "SeriesInstanceUID (0020,000E)"),
])  # fmt: skip
def test_uid_not_a_uid(keyword: str, value: str, label: str) -> None:
    data = synthetic.radiograph().to_json_dict()
    data[{"SOPInstanceUID": "00080018", "StudyInstanceUID": "0020000D", "SeriesInstanceUID": "0020000E"}[keyword]] = {
        "vr": "UI", "Value": [value]}  # fmt: skip
    with pytest.raises(InvalidAttribute) as info:
        read_header(data)
    assert label in str(info.value) and "not a DICOM UID" in str(info.value)


@pytest.mark.parametrize(("attribute", "value"), [
    ("patient_id", "P\x00-1"), ("patient_name", "Doe\x00^Jane"), ("accession_number", "ACC\n42"),
])  # fmt: skip
def test_a_control_character_inside_a_text_refuses_the_image_naming_it(attribute: str, value: str) -> None:
    """PS3.5 §6.2: LO, PN and SH hold no control character; carried on, a NUL would reach the job's
    PostgreSQL row, which cannot hold it."""
    with pytest.raises(InvalidAttribute) as info:
        read_header(synthetic.radiograph(**{attribute: value}))
    keyword = {"patient_id": "PatientID", "patient_name": "PatientName", "accession_number": "AccessionNumber"}
    assert info.value.attributes == (keyword[attribute],)
    assert "control character" in str(info.value)


@pytest.mark.parametrize(("tag", "element", "keyword", "reason"), [
    ("00100020", {"vr": "LO", "Value": ["P1", "P2"]}, "PatientID", "holds 2 values"),
    ("00080050", {"vr": "SH", "Value": ["A" * 17]}, "AccessionNumber", "17 characters"),
    ("00100010", {"vr": "PN", "Value": [{"Alphabetic": "Doe^Jane"}, {"Alphabetic": "Roe^Ann"}]}, "PatientName",
     "holds 2 values"),
    ("00280010", {"vr": "US", "Value": [3200, 3200]}, "Rows", "2 value(s), expected 1"),
    ("00280011", {"vr": "US", "Value": [0]}, "Columns", "positive"),
])  # fmt: skip
def test_an_identifier_or_size_its_vr_cannot_hold_refuses_the_image_naming_it(
    tag: str, element: dict[str, Any], keyword: str, reason: str
) -> None:
    """PS3.6 §6: these attributes have one value; PS3.5 §6.2: SH holds 16 characters. A list used to
    become the text "['P1', 'P2']" of the patient's ID, and a list of Rows a crash."""
    data = synthetic.radiograph().to_json_dict()
    data[tag] = element
    with pytest.raises(InvalidAttribute) as info:
        read_header(data)
    assert info.value.attributes == (keyword,) and reason in str(info.value), str(info.value)


def test_text_is_read_without_its_space_or_nul_padding() -> None:
    header = read_header(synthetic.radiograph(patient_id="P-1\x00", accession_number=" ACC-42 ",
                                              view_position="PA\x00", patient_orientation=None))  # fmt: skip
    assert (header.patient_id, header.accession_number) == ("P-1", "ACC-42")
    assert header.view == "pa" and header.patient_orientation == ("L", "F")


def test_a_malformed_optional_value_is_skipped_not_refused() -> None:
    header = read_header(synthetic.radiograph(extra={"StudyTime": "10\x0015"}))
    assert header.study_time is None and header.patient_id == "P-0001"


def test_missing_study_uid() -> None:
    ds = synthetic.radiograph()
    del ds.StudyInstanceUID
    with pytest.raises(MissingAttribute, match=r"StudyInstanceUID \(0020,000D\)"):
        read_header(ds)


@pytest.mark.parametrize(("keyword", "value"), [
    ("PixelSpacing", ["0.1"]), ("PixelSpacing", ["-0.1", "0.1"]), ("ImagerPixelSpacing", ["0", "0.1"]),
    ("ImagerPixelSpacing", ["nan", "0.1"]),
])  # fmt: skip
def test_bad_spacing_values(keyword: str, value: list[str]) -> None:
    """A spacing that is not two positive numbers refuses the image, naming it, when no other gives the spacing;
    beside a usable one it is left out with a warning (the page leaves it out too)."""
    label = {"PixelSpacing": "PixelSpacing (0028,0030)", "ImagerPixelSpacing": "ImagerPixelSpacing (0018,1164)"}
    other = "ImagerPixelSpacing" if keyword == "PixelSpacing" else "PixelSpacing"
    alone = synthetic.radiograph(imager_pixel_spacing=None)
    setattr(alone, keyword, value)
    with pytest.raises(InvalidAttribute) as info:
        read_header(alone)
    assert label[keyword] in str(info.value)
    beside = synthetic.radiograph(imager_pixel_spacing=None)
    setattr(beside, keyword, value)
    setattr(beside, other, ["0.15", "0.15"])
    header = read_header(beside)
    assert header.pixel_spacing == pytest.approx((0.15, 0.15))
    assert any(w.startswith(label[keyword]) and w.endswith(": left out") for w in header.warnings), header.warnings


def test_source_to_patient_beyond_detector() -> None:
    with pytest.raises(InvalidAttribute, match=r"DistanceSourceToDetector \(0018,1110\)"):
        read_header(synthetic.radiograph(sid=1000.0, sod=1200.0))


# ------------------------------------------------------------------ merge


@pytest.mark.parametrize(
    ("film", "expected"),
    [
        ({"modality": "DX"}, "perspective"),
        ({"modality": "CR"}, "perspective"),
        ({"modality": "DX", "pixel_spacing": (0.1, 0.1), "calibration_type": "FIDUCIAL"}, None),
        ({"modality": "DX", "pixel_spacing": (0.1, 0.1), "calibration_type": "FIDUCIAL", "ermf": 1.2}, "perspective"),
        ({"modality": "DX", "extra": {"SOPClassUID": "1.2.840.10008.5.1.4.1.1.7"}}, None),
    ],
)
def test_a_projection_radiograph_is_sent_as_a_point_source_film(film: dict[str, Any], expected: str | None) -> None:
    """A CR or DX film without SID: acquisition.projection_model "perspective", its source the SOP class;
    not for millimetres in the patient plane without an ERMF (their magnification is unknown), nor for a
    Secondary Capture image (not a projection radiograph)."""
    header = read_header(synthetic.radiograph(**film))
    payload = {"pa": {"units": "px", "pixel_spacing": [0.15, 0.15], "landmarks": []}}
    merged, provenance = apply_headers(payload, {"pa": header}, source="file")
    assert (merged["pa"].get("acquisition") or {}).get("projection_model") == expected
    reads = {r.field: r for r in provenance.pa.read}
    if expected is None:
        assert "pa.acquisition.projection_model" not in reads
    else:
        assert reads["pa.acquisition.projection_model"].attribute.startswith("SOPClassUID (0008,0016)")


def test_merge_fills_missing_and_reports_conflicts() -> None:
    pa = read_header(synthetic.radiograph(imager_pixel_spacing=(0.15, 0.15), ermf=1.25, sid=1800.0))
    lateral_ds = synthetic.radiograph(patient_orientation=("A", "F"), view_position="LL",
                                      study_instance_uid=pa.study_instance_uid, accession_number="ACC-LAT")  # fmt: skip
    lateral = read_header(lateral_ds)
    payload = {
        "pa": {"units": "px", "landmarks": []},
        "lateral": {"units": "px", "pixel_spacing": [0.2, 0.2], "patient_orientation": ["A", "F"], "landmarks": []},
        "study": {"study_instance_uid": pa.study_instance_uid, "study_id": "TYPED"},
    }
    merged, provenance = apply_headers(payload, {"pa": pa, "lateral": lateral}, source="file")
    assert payload["pa"] == {"units": "px", "landmarks": []}  # the input is not changed
    assert merged["pa"]["pixel_spacing"] == pytest.approx([0.12, 0.12])
    assert merged["pa"]["pixel_spacing_calibration"] == "calibrated"
    assert merged["pa"]["patient_orientation"] == ["L", "F"]
    assert merged["pa"]["acquisition"] == {"magnification": 1.25, "distance_source_to_detector_mm": 1800.0,
                                           "distance_source_to_patient_mm": pytest.approx(1440.0),
                                           "projection_model": "perspective",
                                           "image_size": [32.0, 64.0]}  # fmt: skip
    assert merged["lateral"]["pixel_spacing"] == [0.2, 0.2]  # the payload wins
    assert "pixel_spacing_calibration" not in merged["lateral"]  # the header's calibration is not of this spacing
    assert merged["study"]["study_id"] == "1"  # the film's (merge.FILM_VALUES): the SR goes into its study
    assert merged["study"]["accession_number"] == "ACC-42"  # the PA's, the lateral's a conflict
    assert merged["study"]["patient_id"] == "P-0001" and merged["study"]["patient_name"] == "Doe^Jane"
    assert merged["study"]["study_date"] == "2026-11-30"
    assert merged["study"]["pa_sop_instance_uid"] == pa.sop_instance_uid
    assert merged["study"]["lateral_sop_instance_uid"] == lateral.sop_instance_uid
    assert merged["study"]["series_instance_uid"] == pa.series_instance_uid
    conflicts = {c.field: c for c in provenance.conflicts}
    assert set(conflicts) == {"lateral.pixel_spacing", "study.accession_number", "study.study_id"}
    assert conflicts["lateral.pixel_spacing"].header == [0.15, 0.15]
    assert conflicts["lateral.pixel_spacing"].attribute == "ImagerPixelSpacing (0018,1164)"
    assert (conflicts["study.study_id"].payload, conflicts["study.study_id"].header) == ("TYPED", "1")
    assert conflicts["study.accession_number"].attribute == "lateral image's AccessionNumber (0008,0050)"
    assert next(r for r in provenance.study if r.field == "study.study_id").used  # the PA film's: the job's study
    assert provenance.pa is not None and provenance.pa.cornerstone_calibration_type == "ERMF"
    read = {r.field: r for r in provenance.pa.read}
    assert read["pa.pixel_spacing"].used and "EstimatedRadiographicMagnificationFactor (0018,1114)" in read[
        "pa.pixel_spacing"].attribute  # fmt: skip
    assert provenance.lateral is not None
    assert not {r.field: r for r in provenance.lateral.read}["lateral.pixel_spacing"].used
    Study.model_validate(engine_payload(merged)["study"])  # cut to the contract, a valid payload Study
    # the patient and study attributes the contract has no field for, for the SR and SC (PS3.3 §C.7.1.1, §C.7.2.1)
    extra = {key: merged["study"][key] for key in ("study_time", "study_id", "patient_birth_date", "patient_sex")}
    assert extra == {"study_time": "101500", "study_id": "1", "patient_birth_date": "20120412", "patient_sex": "F"}
    assert provenance.model_dump(mode="json")["conflicts"][0].keys() == {"field", "payload", "header", "attribute"}


@pytest.mark.parametrize(("view", "size"), [
    ({"units": "px"}, [500.0, 1200.0]),  # [Columns, Rows]
    ({"units": "mm", "pixel_spacing": [0.2, 0.15]}, [75.0, 240.0]),  # × column 0.15, row 0.2 mm
    ({"units": "mm"}, [75.0, 240.0]),  # the header's spacing, filled first
])  # fmt: skip
def test_image_size_is_read_from_columns_and_rows(view: dict[str, Any], size: list[float]) -> None:
    """acquisition.image_size is [Columns, Rows] (0028,0011)/(0028,0010) in the view's units."""
    header = read_header(synthetic.radiograph(rows=1200, columns=500, sid=1800.0, sod=1600.0,
                                              imager_pixel_spacing=None, pixel_spacing=(0.2, 0.15)))  # fmt: skip
    merged, provenance = apply_headers({"pa": {**view, "landmarks": []}}, {"pa": header}, source="file")
    assert merged["pa"]["acquisition"]["image_size"] == pytest.approx(size)
    assert provenance.pa is not None
    read = {r.field: r for r in provenance.pa.read}["pa.acquisition.image_size"]
    assert read.used and "Columns (0028,0011)" in read.attribute and "Rows (0028,0010)" in read.attribute


def test_image_size_needs_a_spacing_in_mm_and_a_given_one_wins() -> None:
    header = read_header(synthetic.radiograph(rows=1200, columns=500, imager_pixel_spacing=None))
    assert header.pixel_spacing is None
    merged, _ = apply_headers({"pa": {"units": "mm", "landmarks": []}}, {"pa": header}, source="file")
    assert "image_size" not in (merged["pa"].get("acquisition") or {})
    payload = {"pa": {"units": "px", "pixel_spacing": [0.2, 0.2], "acquisition": {"image_size": [400.0, 1200.0]},
                      "landmarks": []}}
    merged, provenance = apply_headers(payload, {"pa": header}, source="file")
    assert merged["pa"]["acquisition"]["image_size"] == [400.0, 1200.0]
    assert [(c.field, c.header) for c in provenance.conflicts] == [("pa.acquisition.image_size", [500.0, 1200.0])]


def test_equal_values_are_no_conflict() -> None:
    header = read_header(synthetic.radiograph(imager_pixel_spacing=(0.15, 0.15)))
    payload = {"pa": {"units": "px", "pixel_spacing": [0.15, 0.15000000001], "patient_orientation": ["L", "F"],
                      "landmarks": []}}  # fmt: skip
    merged, provenance = apply_headers(payload, {"pa": header}, source="dicomweb")
    assert provenance.conflicts == []
    assert merged["pa"]["pixel_spacing_calibration"] == "detector"  # the same spacing as the header's


def test_lateral_image_given_as_pa_is_refused() -> None:
    header = read_header(synthetic.radiograph(patient_orientation=("A", "F"), view_position="LL"))
    with pytest.raises(UnsupportedOrientation) as info:
        apply_headers({"pa": {"landmarks": []}}, {"pa": header}, source="file")
    assert info.value.field == "pa.patient_orientation" and "lateral" in str(info.value)


def test_study_fields_validate() -> None:
    with pytest.raises(ValueError, match="at most 16"):
        Study.model_validate({"study_instance_uid": "1.2", "accession_number": "A" * 17})
    with pytest.raises(ValueError, match="backslash"):
        Study.model_validate({"study_instance_uid": "1.2", "patient_id": "a\\b"})
    study = Study.model_validate({"study_instance_uid": "1.2", "study_date": "2026-11-30", "patient_name": "Doe^J"})
    assert study.study_date == date(2026, 11, 30)


@pytest.mark.parametrize(
    ("attributes", "expected"),
    [
        ({"AcquisitionDateTime": "20261115093012.5+0100"}, "2026-11-15T09:30:12+01:00"),
        ({"AcquisitionDate": "20261115", "AcquisitionTime": "093012", "TimezoneOffsetFromUTC": "-0500"},
         "2026-11-15T09:30:12-05:00"),
        ({"AcquisitionDate": "20261115", "AcquisitionTime": "093012"}, "2026-11-15"),  # no zone: the date
        ({"ContentDate": "20261116", "ContentTime": "101500"}, "2026-11-16"),
        ({"AcquisitionDate": "2026111"}, None),  # malformed DA: skipped
        ({}, None),
    ],
)
def test_the_films_date_time_is_read_for_the_fhir_export(attributes: dict[str, str], expected: str | None) -> None:
    """Acquisition DateTime, else Acquisition or Content Date and Time (PS3.3 C.7.6.1), as ISO 8601 with a
    time only when a zone is known (a FHIR dateTime with a time needs one)."""
    ds = synthetic.radiograph()
    for keyword in ("ContentDate", "ContentTime"):  # the synthetic film dates its content as its study
        if keyword in ds:
            delattr(ds, keyword)
    for keyword, value in attributes.items():
        setattr(ds, keyword, value)
    assert read_header(ds).film_datetime == expected
