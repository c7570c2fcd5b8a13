"""A lateral film read mirrored (its orientation's depth letter the wrong way round, or its image flipped
left to right) is refused naming ``lateral.patient_orientation``; real spines' films are not.

Spines: the VerSe dev split shipped in ``tests/data/verse_dev.csv`` (CC BY-SA 4.0, credited in
``tests/data/README.md``), filmed by ``benches.clinic_films`` (every case with a lateral film) and by
``benches.truth.payload_from_truth``. The rule and its cited bounds: ``spine_engine.lateral_profile``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benches.clinic import truths_of_csv
from benches.clinic_films import CASES, Truth, build_payload, simulate_series
from benches.lateral_mirror import LATERAL_CASES, mirrored_columns, mirrored_labels, profile_spine
from benches.truth import payload_from_truth
from spine_engine import register
from spine_engine.errors import InvalidInput
from spine_engine.lateral_profile import CHECK_NAME, profile_readings
from spine_engine.levels import LEVEL_INDEX, N_LEVELS
from spine_engine.validation import validate_payload

VERSE_DEV = Path(__file__).resolve().parents[1] / "data" / "verse_dev.csv"
ALL = list(range(N_LEVELS))


@pytest.fixture(scope="module")
def dev() -> list[Truth]:
    return truths_of_csv(VERSE_DEV)


def _payload(truth: Truth, case: str = "a", noise_mm: float = 1.0, seed: int = 0) -> dict[str, Any]:
    return build_payload(simulate_series(truth, noise_mm, seed), CASES[case]).model_dump(mode="json", exclude_none=True)


def _refusal(payload: dict[str, Any]) -> list[tuple[str, str, str]]:
    with pytest.raises(InvalidInput) as info:
        register(payload)
    return [(e.path, e.type, e.msg) for e in info.value.errors]


@pytest.mark.parametrize("mirror", [mirrored_labels, mirrored_columns])
def test_a_mirrored_lateral_is_refused_naming_its_orientation(dev: list[Truth], mirror: Any) -> None:
    """verse033 (kyphosis 47°, lordosis 31°), PA + full lateral at 1 mm: its lateral labelled ["P", "F"],
    or flipped left to right under ["A", "F"], reads a lordotic thoracic and a kyphotic lumbar spine and is
    refused before any fit, the message naming both regions' readings and the label to check."""
    payload = mirror(_payload(dev[0]))
    [(path, kind, msg)] = _refusal(payload)
    assert (path, kind) == ("lateral.patient_orientation", CHECK_NAME)
    assert "T4–T12" in msg and "T12–L5" in msg and "mirrored" in msg


def test_a_mirrored_lateral_in_pixels_turned_180_degrees_is_refused(dev: list[Truth]) -> None:
    """The same film in px (spacing 0.2 mm) with rows toward the head: the check works in the patient's
    directions the labels name, whatever the image axes (["P", "H"] is the ["A", "F"] film turned 180°,
    so ["A", "H"] on it is mirrored)."""
    payload = _payload(dev[0])
    lateral = payload["lateral"]
    lateral.update(units="px", pixel_spacing=[0.2, 0.2], patient_orientation=["P", "H"])
    for lm in lateral["landmarks"]:
        lm["point"] = [(1000.0 - lm["point"][0]) / 0.2, (1000.0 - lm["point"][1]) / 0.2]
    validate_payload(payload)  # the same film turned 180°, labelled so: accepted
    lateral["patient_orientation"] = ["A", "H"]
    [(path, kind, _)] = _refusal(payload)
    assert (path, kind) == ("lateral.patient_orientation", CHECK_NAME)


def test_every_verse_dev_spine_passes_in_every_case_noise_and_seed(dev: list[Truth]) -> None:
    """All 24 dev spines, every clinic case with a lateral, 1 and 3 mm of noise, 3 seeds: none refused;
    mirrored, verse033 is refused in every one of them at 1 mm (its readings are far from 0)."""
    for truth in dev:
        for case in LATERAL_CASES:
            for noise in (1.0, 3.0):
                for seed in range(3):
                    validate_payload(_payload(truth, case, noise, seed))
    for case in LATERAL_CASES:
        for seed in range(3):
            with pytest.raises(InvalidInput):
                validate_payload(mirrored_labels(_payload(dev[0], case, 1.0, seed)))


def test_verse_dev_from_truth_passes_and_its_readings_keep_their_signs(dev: list[Truth]) -> None:
    """``payload_from_truth`` (weak perspective, T1 and L5 given) of each dev spine at 2 mm: accepted, and
    the check's noise-free readings are kyphotic and lordotic on every spine (the smallest lordosis,
    verse151's 4.2° on the centreline, reads 2.5°): the check reads a sign that the population keeps."""
    rng = np.random.default_rng(3)
    for truth in dev:
        validate_payload(payload_from_truth(truth.positions, truth.rotations, ALL, ALL, noise_mm=2.0, rng=rng))
        exact = payload_from_truth(truth.positions, truth.rotations, ALL, ALL)["lateral"]
        points = [(LEVEL_INDEX[lm["level"]], *lm["point"]) for lm in exact["landmarks"]]
        thoracic, lumbar = profile_readings(tuple(exact["patient_orientation"]), points, 1.0)
        assert thoracic is not None and lumbar is not None
        assert thoracic.angle_deg > 0.0 and -lumbar.angle_deg > 0.0, truth.spine_id


@pytest.mark.parametrize(("kyphosis", "lordosis"), [(-30.0, 10.0), (-30.0, 0.0), (10.0, -20.0), (0.0, -20.0)])
def test_one_inverted_region_is_never_refused(kyphosis: float, lordosis: float) -> None:
    """A lordotic thoracic spine with a lumbar lordosis (AIS hypokyphosis reaches T4–T12 < 0: 27.1 ± 18.8°
    in 458 patients, doi:10.1186/s13013-018-0156-0), or a kyphotic lumbar spine under a kyphotic or flat
    thoracic one (a flat back), exact landmarks: accepted. Only both regions inverted are refused."""
    truth = profile_spine(kyphosis, lordosis)
    validate_payload(payload_from_truth(truth.positions, truth.rotations, ALL, ALL))


def test_a_lateral_too_short_to_read_a_region_is_not_judged(dev: list[Truth]) -> None:
    """The mirrored lateral of verse033 without L5 (the lumbar reading needs L1 or T12 down to L5), or from
    T7 down (the thoracic one needs T6 to T11): no judgement, accepted."""
    for drop in (("L5",), ("T1", "T2", "T3", "T4", "T5", "T6")):
        payload = mirrored_labels(_payload(dev[0]))
        payload["lateral"]["landmarks"] = [lm for lm in payload["lateral"]["landmarks"] if lm["level"] not in drop]
        validate_payload(payload)


def test_a_stand_in_spacing_is_not_judged(dev: list[Truth]) -> None:
    """A lateral whose spacing is a stand-in until its header is read (``unscaled_views``) is judged when it
    is read: the stand-in may not have the image's aspect."""
    payload = mirrored_labels(_payload(dev[0]))
    validate_payload(payload, unscaled_views=("lateral",))
    with pytest.raises(InvalidInput):
        validate_payload(payload)
