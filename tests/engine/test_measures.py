"""compute_measures on hand-built spines whose Cobb angles, ends, apex and planes are known."""

import numpy as np
import pytest

from spine_engine.frames import axial_rotation_deg, frames_from_centreline
from spine_engine.levels import LEVEL_INDEX
from spine_engine.measures import (
    _plane_cobb_deg,
    compute_measures,
    frontal_tilt_deg,
    plane_of_max_curvature,
    tilt_turning_points,
)
from spine_engine.synthetic import generate_spine

DS = 25.0


def _rz(angle_deg: float) -> np.ndarray:
    a = np.radians(angle_deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _frontal_arc(total_deg: float) -> np.ndarray:
    """17 points evenly spaced on a frontal circular arc whose tangent turns from −total/2 to
    +total/2 going caudally (tilt rising: convex to the patient's right)."""
    phi = np.radians(np.linspace(-total_deg / 2, total_deg / 2, 17))
    radius = DS / np.radians(total_deg / 16)
    return np.column_stack([-radius * np.cos(phi), np.zeros(17), -radius * np.sin(phi)])


def _from_tilts(tilt_deg: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """A pure frontal spine with a hand-built tilt sequence: d1 = (cos θ, 0, sin θ), d2 = −y,
    d3 = d1 × d2; chords of length DS along the mean tilt of their two vertebrae."""
    t = np.radians(np.asarray(tilt_deg, dtype=float))
    d1 = np.column_stack([np.cos(t), np.zeros_like(t), np.sin(t)])
    d2 = np.tile([0.0, -1.0, 0.0], (len(t), 1))
    R = np.stack([d1, d2, np.cross(d1, d2)], axis=-1)
    m = 0.5 * (t[:-1] + t[1:])
    chords = DS * np.column_stack([np.sin(m), np.zeros_like(m), -np.cos(m)])
    return np.concatenate([np.zeros((1, 3)), np.cumsum(chords, axis=0)]), R


# T1 .. L5: a 15° curve T1–T5, a 37° major curve T5–L1 (with a 4° wiggle at T6–T7 that must not
# split it), a 16° curve L1–L5.
TILTS = [0, -2, -5, -10, -15, -8, -12, -6, 0, 6, 12, 18, 22, 20, 15, 10, 6]


def test_analytic_frontal_arc() -> None:
    total = 48.0
    p = _frontal_arc(total)
    R = frames_from_centreline(p)
    # interior tangents of an evenly sampled circle are exact; the ends take the end chords,
    # whose tilt is half a step inside: Cobb = total − one step = 15/16 · total
    m = compute_measures(p, R)
    assert len(m.cobb) == 1
    c = m.cobb[0]
    assert c.angle_deg == pytest.approx(total * 15 / 16, abs=1e-9)
    assert (c.upper, c.lower, c.apex) == ("T1", "L5", "T9")
    assert c.convexity == "right" and c.major
    assert p[8, 0] < p[0, 0]  # the apex is on the patient's right (−x)
    assert c.apex_axial_rotation_deg == pytest.approx(0.0, abs=1e-9)
    assert c.plane_of_max_curvature_deg == pytest.approx(0.0, abs=1e-3)
    assert c.max_curvature_deg == pytest.approx(c.angle_deg, abs=1e-6)


def test_mirrored_arc_is_convex_left() -> None:
    p = _frontal_arc(30.0) * np.array([-1.0, 1.0, 1.0])
    c = compute_measures(p, frames_from_centreline(p)).cobb[0]
    assert c.convexity == "left" and c.angle_deg == pytest.approx(30.0 * 15 / 16)


def test_hand_built_tilt_sequence() -> None:
    p, R = _from_tilts(TILTS)
    np.testing.assert_allclose(frontal_tilt_deg(R), TILTS, atol=1e-12)
    m = compute_measures(p, R)
    got = [(c.upper, c.lower, round(c.angle_deg, 9), c.convexity, c.major) for c in m.cobb]
    assert got == [
        ("T1", "T5", 15.0, "left", False),
        ("T5", "L1", 37.0, "right", True),
        ("L1", "L5", 16.0, "left", False),
    ]
    assert m.cobb[1].apex == "T9"
    only_major = compute_measures(p, R, min_cobb_deg=20.0).cobb
    assert [(c.upper, c.lower, c.major) for c in only_major] == [("T5", "L1", True)]


def test_hysteresis_splits_curves_only_beyond_its_threshold() -> None:
    tilts = np.array(TILTS, dtype=float)
    assert tilt_turning_points(tilts) == [0, 4, 12, 16]
    assert tilt_turning_points(tilts, hysteresis_deg=3.0) == [0, 4, 5, 6, 12, 16]
    assert tilt_turning_points(np.full(17, 2.0)) == []


def test_no_curve_and_exactly_one_major() -> None:
    p, R = _from_tilts([0.0] * 17)
    assert compute_measures(p, R).cobb == []
    p, R = _from_tilts([0, -10, -20, -10, 0, 10, 20, 10, 0, -10, -20, -10, 0, 10, 20, 10, 0])
    curves = compute_measures(p, R).cobb
    assert [round(c.angle_deg, 9) for c in curves] == [20, 40, 40, 40, 20]
    assert [c.major for c in curves] == [False, True, False, False, False]  # ties: the upper one


def test_the_largest_angle_is_the_major_curve_or_the_one_below_the_threshold() -> None:
    """``largest_cobb``: the major curve's ends and angle when ``cobb`` lists it; below the
    threshold, the same pair (max θ − min θ), with ``reported_as_curve`` false; on a flat spine 0°
    between T1 and L5 (a largest angle of 0, not a missing one)."""
    p, R = _from_tilts(TILTS)
    largest = compute_measures(p, R).largest_cobb
    assert largest is not None
    got = (largest.upper, largest.lower, round(largest.angle_deg, 9), largest.reported_as_curve)
    assert got == ("T5", "L1", 37.0, True)
    assert largest.tilt_source == "model"
    mild = [0.4 * t for t in TILTS]  # a 14.8° curve T5–L1, the others below 7°
    above = compute_measures(*_from_tilts(mild), min_cobb_deg=15.0)
    assert above.cobb == []
    assert above.largest_cobb is not None
    got = (above.largest_cobb.upper, above.largest_cobb.lower, round(above.largest_cobb.angle_deg, 9))
    assert got == ("T5", "L1", 14.8)
    assert not above.largest_cobb.reported_as_curve
    flat = compute_measures(*_from_tilts([3.0] * 17))
    assert flat.largest_cobb is not None and flat.cobb == []
    assert (flat.largest_cobb.upper, flat.largest_cobb.lower, flat.largest_cobb.angle_deg) == ("T1", "L5", 0.0)
    assert not flat.largest_cobb.reported_as_curve


@pytest.mark.parametrize("alpha", [30.0, 75.0, -45.0])
def test_rigid_rotation_about_vertical_moves_the_plane_of_maximum_curvature(alpha: float) -> None:
    p, R = _from_tilts([0, -2, -5, -10, -15, -12, -9, -6, 0, 6, 12, 18, 22, 20, 15, 10, 6])
    base = compute_measures(p, R).cobb[1]
    assert base.plane_of_max_curvature_deg == pytest.approx(0.0, abs=1e-3)
    # the plane's azimuth turns from patient left toward anterior (−y): a rotation by −α about +z
    Q = _rz(-alpha)
    m = compute_measures(p @ Q.T, Q @ R)
    major = next(c for c in m.cobb if c.major)
    assert (major.upper, major.lower) == ("T5", "L1")
    assert major.plane_of_max_curvature_deg == pytest.approx(alpha % 180.0, abs=0.01)
    assert major.max_curvature_deg == pytest.approx(base.max_curvature_deg, abs=1e-6)


def test_plane_of_max_curvature_of_a_sagittal_curve() -> None:
    # two vertebrae bent only in the sagittal plane, ±20° about d1 = +x: the plane is sagittal
    def tilted(beta_deg: float) -> np.ndarray:
        b = np.radians(beta_deg)
        d3 = np.array([0.0, np.sin(b), -np.cos(b)])
        d1 = np.array([1.0, 0.0, 0.0])
        return np.column_stack([d1, np.cross(d3, d1), d3])

    phi, angle = plane_of_max_curvature(tilted(20.0), tilted(-20.0))
    assert phi == pytest.approx(90.0, abs=1e-3) and angle == pytest.approx(40.0, abs=1e-6)


def test_axial_rotation_of_the_apex_is_reported_with_its_sign() -> None:
    p = _frontal_arc(40.0)  # convex right
    psi = -25.0 * np.sin(np.linspace(0.0, np.pi, 17))  # toward the right: negative
    R = frames_from_centreline(p, np.radians(psi))
    c = compute_measures(p, R).cobb[0]
    assert c.apex == "T9"
    assert c.apex_axial_rotation_deg == pytest.approx(axial_rotation_deg(R)[8]) and c.apex_axial_rotation_deg < -20


def test_kyphosis_and_lordosis_signs() -> None:
    # a sagittal arc convex posteriorly (apex at +y) is kyphotic: positive kyphosis, negative lordosis
    beta = np.radians(np.linspace(30.0, -30.0, 16))
    chords = DS * np.column_stack([np.zeros(16), np.sin(beta), -np.cos(beta)])
    p = np.concatenate([np.zeros((1, 3)), np.cumsum(chords, axis=0)])
    assert np.argmax(p[:, 1]) == 8  # apex posterior (+y)
    m = compute_measures(p, frames_from_centreline(p))
    assert m.thoracic_kyphosis_t4_t12_deg > 0 > m.lumbar_lordosis_l1_l5_deg
    assert m.cobb == []


def test_bad_shapes_raise() -> None:
    with pytest.raises(ValueError):
        compute_measures(np.zeros((16, 3)), np.tile(np.eye(3), (16, 1, 1)))


def test_frontal_plane_value_is_the_frontal_cobb_without_axial_rotation() -> None:
    s = generate_spine(7, "double")  # a 3D spine: frontal curves, kyphosis and lordosis
    R = frames_from_centreline(s.positions)
    m = compute_measures(s.positions, R, min_cobb_deg=5.0)
    assert len(m.cobb) >= 2
    for c in m.cobb:
        at_zero = _plane_cobb_deg(R[LEVEL_INDEX[c.upper]], R[LEVEL_INDEX[c.lower]], [0.0])[0]
        assert at_zero == pytest.approx(c.angle_deg, abs=1e-9)
        assert c.max_curvature_deg >= c.angle_deg - 1e-9


def test_a_curve_of_one_segment_has_its_apex_at_the_disc() -> None:
    """SRS: a curve's apex is its most deviated vertebra or disc. A 30° curve T1–L4 and a 12° curve of
    one segment L4–L5 (a lumbosacral-like take-off): the long curve's apex is a vertebra strictly
    between its ends; the short one has no vertebra between its ends, so its apex is the L4–L5 disc
    (``apical_disc``, named by L4), not an end vertebra of its own (the old engine reported L4, an end
    vertebra, as the apical vertebra)."""
    tilts = [*np.linspace(0.0, -30.0, 16), -18.0]
    m = compute_measures(*_from_tilts(tilts))
    got = [(c.upper, c.lower, round(c.angle_deg, 9), c.apical_disc) for c in m.cobb]
    assert got == [("T1", "L4", 30.0, False), ("L4", "L5", 12.0, True)]
    long, short = m.cobb
    assert LEVEL_INDEX[long.upper] < LEVEL_INDEX[long.apex] < LEVEL_INDEX[long.lower]
    assert short.apex == "L4" and short.convexity == "right"  # the tilt rises caudally across it


@pytest.mark.parametrize("seed", range(8))
def test_the_apex_lies_strictly_between_the_end_vertebrae(seed: int) -> None:
    """On synthetic spines (3D, one or two structural curves) read with a 5° threshold, so that the small
    curves above and below count too: every curve of two or more segments has its apex strictly
    between its end vertebrae; only a one-segment curve has an apical disc."""
    s = generate_spine(seed)
    m = compute_measures(s.positions, frames_from_centreline(s.positions), min_cobb_deg=5.0)
    for c in m.cobb:
        upper, apex, lower = LEVEL_INDEX[c.upper], LEVEL_INDEX[c.apex], LEVEL_INDEX[c.lower]
        assert c.apical_disc == (lower - upper == 1)
        assert upper < apex < lower or (c.apical_disc and apex == upper)
