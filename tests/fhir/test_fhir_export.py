"""The FHIR export's effective time and model-estimate flags: a stored film date-time without a time
zone never fails the Bundle; a value from the model's prior says so, with the reason the result gives,
on the Observation or on the Cobb Observation's component, as the SR marks it MODEL-BASED."""

from __future__ import annotations

import copy
import itertools
import uuid
from datetime import UTC, datetime
from typing import Any

import pytest
from fhir.resources.R4B.bundle import Bundle

from services.dicom.sr import model_based
from services.fhir.export import MODEL_BASED, effective_date_time, model_estimate_reason, observation_bundle
from spine_engine import register
from tests.conftest import spine_payload

FINISHED = datetime(2026, 3, 1, 9, 30, tzinfo=UTC)
CREATED = datetime(2026, 3, 1, 9, 29, 55, tzinfo=UTC)


@pytest.fixture(scope="module")
def given() -> dict[str, Any]:
    """T1 and L5 given, a PA film only, no pedicles: kyphosis and lordosis unreliable by their SD, the
    axial rotations the population's (``fit.assumed`` population_axial_rotation)."""
    out: dict[str, Any] = register(spine_payload(curve_mm=25.0))
    return out


@pytest.fixture(scope="module")
def free() -> dict[str, Any]:
    """No boundary, a PA film only, no pedicles."""
    payload = spine_payload(curve_mm=25.0)
    payload.pop("boundary")
    out: dict[str, Any] = register(payload)
    return out


@pytest.fixture(scope="module")
def short() -> dict[str, Any]:
    """T1 and L5 given, PA landmarks on T1–T7 only: the frontal Cobb angles depend on levels the film does not
    show (``fit.unreliable`` ``cobb``, their SDs the population's floor)."""
    payload = spine_payload(curve_mm=25.0)
    payload["pa"]["landmarks"] = payload["pa"]["landmarks"][:7]
    out: dict[str, Any] = register(payload)
    assert "cobb" in out["fit"]["unreliable"]
    return out


def _observations(result: dict[str, Any]) -> dict[str, dict[str, Any]]:
    bundle = observation_bundle(uuid.uuid4(), result, finished_at=FINISHED, created_at=CREATED)
    Bundle.model_validate(bundle)
    return {e["resource"]["code"]["text"]: e["resource"] for e in bundle["entry"]}


def _estimate_notes(obs: dict[str, Any]) -> list[str]:
    return [n["text"] for n in obs.get("note", []) if n["text"].startswith("Model estimate")]


@pytest.mark.parametrize(
    ("film", "expected"),
    [
        ("2024-05-06T10:11:12", "2024-05-06"),  # no zone: the date alone (FHIR R4 §2.24.0.1)
        ("2024-05-06T10:11:12+02:00", "2024-05-06T10:11:12+02:00"),
        ("2024-05-06", "2024-05-06"),
        ("not a date", "2026-03-01T09:29:55+00:00"),  # skipped: the job's creation
        ("2024-02-30", "2026-03-01T09:29:55+00:00"),
    ],
)
def test_a_stored_film_date_time_is_read_as_a_fhir_date_time(film: str, expected: str) -> None:
    """A job stored before admission refused them: its film date-time never makes the Bundle fail."""
    assert effective_date_time(None, film, CREATED) == expected
    bundle = observation_bundle(uuid.uuid4(), register(spine_payload(curve_mm=25.0)), finished_at=FINISHED,
                                created_at=CREATED, film_datetime=film)  # fmt: skip
    Bundle.model_validate(bundle)
    assert {e["resource"]["effectiveDateTime"] for e in bundle["entry"]} == {expected.replace("+00:00", "Z")}


def test_population_axial_rotation_is_a_model_estimate(given: dict[str, Any]) -> None:
    assert "population_axial_rotation" in [a["name"] for a in given["fit"]["assumed"]]
    obs = _observations(given)
    rotation = obs["Apical vertebral axial rotation of the major curve"]
    [note] = _estimate_notes(rotation)
    assert "no pedicles" in note and "population_axial_rotation" in note
    assert rotation["interpretation"] == [MODEL_BASED]
    cobb = obs["Cobb angle, frontal plane, major curve"]
    parts = {c["code"]["text"]: c for c in cobb["component"]}
    assert parts["Apical vertebral axial rotation"]["interpretation"] == [MODEL_BASED]
    assert "interpretation" not in cobb and "interpretation" not in parts["Upper end vertebra"]
    assert any("Apical vertebral axial rotation" in n for n in _estimate_notes(cobb))


def test_the_sagittal_estimate_note_gives_the_results_reason(given: dict[str, Any], free: dict[str, Any]) -> None:
    """T1 and L5 given: the note does not say they were not (no lateral film, the SD rule); without
    boundary it says what ``fit.assumed`` says (population_sagittal_shape)."""
    assert given["fit"]["boundary"] == "given" and {"kyphosis", "lordosis"} <= set(given["fit"]["unreliable"])
    for result, must, must_not in (
        (given, ["no lateral film", "T1 and L5 given", "fit.unreliable: kyphosis"], ["not given"]),
        (free, ["no lateral film", "population prior", "population_sagittal_shape"], []),
    ):
        [note] = _estimate_notes(_observations(result)["Thoracic kyphosis T4–T12 (sagittal Cobb angle)"])
        assert all(m in note for m in must), note
        assert not any(m in note for m in must_not), note


def test_cobb_components_from_the_model_are_flagged_as_in_the_sr(free: dict[str, Any]) -> None:
    """No boundary: apical rotation, plane of maximum curvature and the Cobb angle in it are MODEL-BASED
    in the SR; the FHIR Cobb Observation flags the same components (interpretation, note)."""
    cobb = _observations(free)["Cobb angle, frontal plane, major curve"]
    flagged = {c["code"]["text"] for c in cobb["component"] if c.get("interpretation") == [MODEL_BASED]}
    assert flagged == {"Apical vertebral axial rotation",
                       "Plane of maximum curvature, azimuth from the frontal plane toward anterior",
                       "Cobb angle in the plane of maximum curvature"}  # fmt: skip
    notes = _estimate_notes(cobb)
    assert len(notes) == 2 and any("plane_of_max_curvature" in n for n in notes)
    assert "interpretation" not in cobb  # the Cobb angle itself is measured


FITS = [
    {"boundary": boundary, "unreliable": unreliable, "assumed": assumed, "lateral": lateral}
    for boundary, unreliable, assumed, lateral in itertools.product(
        ("given", "soft", "estimated"),
        ([], ["kyphosis", "lordosis"], ["scale", "depth", "kyphosis", "lordosis", "plane_of_max_curvature",
                                        "axial_rotation", "twist"]),
        ([], [{"name": "population_axial_rotation", "view": None, "reason": "no pedicles: ..."},
              {"name": "population_sagittal_shape", "view": None, "reason": "no lateral film: ..."}]),
        (None, {"scale": 1.1}),
    )
]  # fmt: skip


@pytest.mark.parametrize("fit", FITS)
def test_sr_and_fhir_decide_model_estimates_by_one_rule(fit: dict[str, Any]) -> None:
    """``sr.model_based`` and ``model_estimate_reason`` (``services.core.estimates``, which the FHIR
    export notes by) agree on every quantity and level, on every kind of fit block."""
    for quantity in ("axial_rotation", "kyphosis", "lordosis", "plane_of_max_curvature", "twist", "depth"):
        for level in ("T1", "T8", "L5", None):
            assert model_based(fit, quantity, level) == (model_estimate_reason(fit, quantity, level) is not None), (
                quantity, level)  # fmt: skip


def test_sr_and_fhir_flag_the_same_values_of_real_results(given: dict[str, Any], free: dict[str, Any]) -> None:
    for result in (given, free, copy.deepcopy(given) | {"fit": {**given["fit"], "assumed": []}}):
        cobb = _observations(result)["Cobb angle, frontal plane, major curve"]
        parts = {c["code"]["coding"][0]["code"]: c for c in cobb["component"] if "coding" in c["code"]}
        major = next(c for c in result["measures"]["cobb"] if c["major"])
        fit = result["fit"]
        assert ("interpretation" in parts["APEX-AXROT"]) == model_based(fit, "axial_rotation", major["apex"])
        assert ("interpretation" in parts["PMC-ORIENT"]) == model_based(fit, "plane_of_max_curvature")


ENDPLATES = "Cobb angle between end plates, frontal plane"
PLANE = ("Plane of maximum curvature, azimuth from the frontal plane toward anterior",
         "Cobb angle in the plane of maximum curvature")  # fmt: skip


def test_the_endplate_variant_of_a_model_estimated_cobb_angle_is_flagged(
    short: dict[str, Any], given: dict[str, Any]
) -> None:
    """``fit.unreliable`` ``cobb``: every Cobb Observation is a model estimate, and so are its end-plate
    variant, plane of maximum curvature and the Cobb angle in it (the SR's MODEL-BASED), named in the
    value's note rather than in a second note repeating its reason; measured on the whole film, none is."""
    cobbs = _cobb_observations(short)
    assert len(cobbs) == len(short["measures"]["cobb"]) >= 1
    for cobb in cobbs:
        parts = {c["code"]["text"]: c for c in cobb["component"]}
        assert cobb["interpretation"] == [MODEL_BASED]
        for name in (ENDPLATES, *PLANE):
            assert parts[name]["interpretation"] == [MODEL_BASED], name
        notes = [n for n in _estimate_notes(cobb) if "fit.unreliable: cobb" in n]
        assert len(notes) == 1 and all(name in notes[0] for name in (ENDPLATES, *PLANE)), notes
        assert notes[0].startswith("Model estimate (the value; components: ")
    measured = _observations(given)["Cobb angle, frontal plane, major curve"]
    assert "cobb" not in given["fit"]["unreliable"] and "interpretation" not in measured
    parts = {c["code"]["text"]: c for c in measured["component"]}
    assert not any("interpretation" in parts[name] for name in (ENDPLATES, *PLANE))


def _cobb_observations(result: dict[str, Any]) -> list[dict[str, Any]]:
    """The frontal Cobb Observations (the minor curves share a text)."""
    bundle = observation_bundle(uuid.uuid4(), result, finished_at=FINISHED, created_at=CREATED)
    return [e["resource"] for e in bundle["entry"] if e["resource"]["code"]["text"].startswith("Cobb angle, frontal")]


def _sd_text(obs: dict[str, Any]) -> str:
    [text] = [c["code"]["text"] for c in obs.get("component", [])
              if c["code"]["text"].startswith("Standard deviation of the value")]  # fmt: skip
    return text


def _sd_texts(result: dict[str, Any]) -> dict[str, str]:
    """Each Observation's SD component text, by the Observation's text (one of the minor curves')."""
    return {text: _sd_text(o) for text, o in _observations(result).items() if o.get("component")
            and any(c["code"]["text"].startswith("Standard deviation") for c in o["component"])}  # fmt: skip


def test_the_sd_component_says_where_the_sd_comes_from(
    short: dict[str, Any], given: dict[str, Any], free: dict[str, Any]
) -> None:
    """An SD that is the population's floor says so, one from the fit says that: a Cobb angle beyond the
    film (``fit.unreliable`` ``cobb``, 18.4°), kyphosis and lordosis without depth (no boundary, one PA film:
    ``fit.unreliable`` ``depth``, 10.1°) name the population's SD; the fit's own SDs (T1 and L5 given: the
    kyphosis is not floored) name the Laplace SD calibrated on VerSe dev, never held-out spines."""
    kyphosis = "Thoracic kyphosis T4–T12 (sagittal Cobb angle)"
    population = "at least the population's SD of the major Cobb angle"
    for result in (short, given, free):
        assert not any("held-out" in text for text in _sd_texts(result).values())
    cobb = [_sd_text(o) for o in _cobb_observations(short)]
    assert len(cobb) == len(short["measures"]["cobb"]) and all(population in t and "fit.unreliable: cobb" in t
                                                                 for t in cobb)  # fmt: skip
    assert [c["angle_sd_deg"] for c in short["measures"]["cobb"]] == pytest.approx([18.42] * len(cobb), abs=0.01)
    # 18.42: the population's SD of the major Cobb angle (docs/engine.md "Honest SDs"), the floor here
    assert "depth" in free["fit"]["unreliable"] and "population's SD (VerSe dev)" in _sd_texts(free)[kyphosis]
    assert free["measures"]["thoracic_kyphosis_t4_t12_sd_deg"] == pytest.approx(10.07, abs=0.01)
    # 10.07: the population's SD of kyphosis T4–T12 (VerSe dev, docs/engine.md "Honest SDs": 10.1°), the floor
    own = _sd_texts(given)
    assert "population" not in own[kyphosis] and "population" not in own["Cobb angle, frontal plane, major curve"]
    assert "Laplace SD" in own[kyphosis] and "VerSe dev" in own[kyphosis]
    assert "population_axial_rotation" in own["Apical vertebral axial rotation of the major curve"]
