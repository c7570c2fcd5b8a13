"""compute_measures on hand-built spines whose Cobb angles, ends, apex and planes are known."""

import itertools
from collections.abc import Sequence

import numpy as np
import pytest

from spine_engine.frames import axial_rotation_deg, frames_from_centreline
from spine_engine.levels import LEVEL_INDEX
from spine_engine.measures import (
    _plane_cobb_deg,
    compute_measures,
    continuous_tilts,
    frontal_tilt_deg,
    lenke_inputs,
    lenke_modifier,
    major_first_curves,
    most_tilted_pair,
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


def _from_tilts(tilt_deg: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
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
    below = (above.largest_cobb.upper, above.largest_cobb.lower, round(above.largest_cobb.angle_deg, 9))
    assert below == ("T5", "L1", 14.8)
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
    # T1–L4 is a circular arc (the tilt falls evenly): its 14 inner vertebrae T2–L3 are deviated
    # symmetrically, T8 and T9 equally, so its apex is the T8–T9 disc (named T8)
    assert got == [("T1", "L4", 30.0, True), ("L4", "L5", 12.0, True)]
    long, short = m.cobb
    assert LEVEL_INDEX[long.upper] < LEVEL_INDEX[long.apex] < LEVEL_INDEX[long.lower] and long.apex == "T8"
    assert short.apex == "L4" and short.convexity == "right"  # the tilt rises caudally across it


@pytest.mark.parametrize("seed", range(8))
def test_the_apex_lies_strictly_between_the_end_vertebrae(seed: int) -> None:
    """On synthetic spines (3D, one or two structural curves) read with a 5° threshold, so that the small
    curves above and below count too: every curve of two or more segments has its apex strictly
    between its end vertebrae (a disc only when two vertebrae are equally deviated, and then below a
    vertebra strictly inside); a one-segment curve always has an apical disc."""
    s = generate_spine(seed)
    m = compute_measures(s.positions, frames_from_centreline(s.positions), min_cobb_deg=5.0)
    for c in m.cobb:
        upper, apex, lower = LEVEL_INDEX[c.upper], LEVEL_INDEX[c.apex], LEVEL_INDEX[c.lower]
        if lower - upper == 1:
            assert c.apical_disc and apex == upper
        else:
            assert upper < apex < lower and (not c.apical_disc or apex + 1 < lower)


# T1 .. L5: a left curve T1–T10 (8° → −11°), a right curve T10–L2 (−11° → 8°), a left curve L2–L5
# (8° → −30°). T1 and L5 are the most tilted pair (38°), but between them the tilt turns back by 19°.
THREE_CURVES = [8, 6, -2, -6, 0, 0, 0, -3, -6, -11, -7, 2, 7, 8, 1, -12, -30]


def test_a_reversal_of_ten_degrees_inside_a_curve_is_a_curve_of_its_own() -> None:
    """Cobb 1948 / SRS: a curve's end vertebrae are its most tilted ones, where the tilt turns back, and a
    lateral curvature of 10° or more is scoliosis. T1–L5 here holds a 19° right curve T10–L2: the spine
    has three curves, not one of 38° from T1 to L5 (the old engine's, taking the most tilted pair as the
    major curve whatever lay between; the shape is that of an AASCE 2019 training radiograph, 5 of whose
    481 have such a reversal). ``largest_cobb`` is the major curve; the AASCE script's angle, the most
    tilted pair, stays ``most_tilted_pair``'s."""
    p, R = _from_tilts(THREE_CURVES)
    m = compute_measures(p, R)
    got = [(c.upper, c.lower, round(c.angle_deg, 9), c.convexity, c.major) for c in m.cobb]
    assert got == [
        ("T1", "T10", 19.0, "left", False),
        ("T10", "L2", 19.0, "right", False),
        ("L2", "L5", 38.0, "left", True),
    ]
    assert m.largest_cobb is not None and m.largest_cobb.reported_as_curve
    assert (m.largest_cobb.upper, m.largest_cobb.lower, round(m.largest_cobb.angle_deg, 9)) == ("L2", "L5", 38.0)
    assert most_tilted_pair(THREE_CURVES) == (0, 16, 38.0)
    # the curves do not depend on the reporting threshold: at 20° only L2–L5 is listed, still split off
    assert [(c.upper, c.lower) for c in compute_measures(p, R, min_cobb_deg=20.0).cobb] == [("L2", "L5")]


def test_a_wiggle_below_ten_degrees_does_not_split_a_curve() -> None:
    """A spine like ``THREE_CURVES`` whose tilt turns back by 8° only (−9° at T10 to −1° at L1): one left
    curve T1–L5 of 38°, as before (the 4° wiggle of ``TILTS`` inside its major curve likewise stays)."""
    tilts = [8, 6, -2, -6, -4, -5, -6, -7, -8, -9, -6, -3, -1, -1, -5, -12, -30]
    got = [(c.upper, c.lower, round(c.angle_deg, 9)) for c in compute_measures(*_from_tilts(tilts)).cobb]
    assert got == [("T1", "L5", 38.0)]
    assert major_first_curves(tilts, 10.0) == [(0, 16, 38.0)]


def test_split_curves_alternate_and_share_their_end_vertebrae() -> None:
    """Every curve ends where the next begins (SRS: adjacent curves share an end vertebra) and turns the
    other way; the ends of each are its most tilted vertebrae (its angle is max θ − min θ over it)."""
    t = np.array(THREE_CURVES, dtype=float)
    curves = major_first_curves(t, 0.0)
    assert curves[0][0] == 0 and curves[-1][1] == 16
    for (u0, l0, _), (u1, l1, _) in itertools.pairwise(curves):
        assert l0 == u1 and np.sign(t[l0] - t[u0]) == -np.sign(t[l1] - t[u1])
    for u, l, angle in curves:
        assert angle == pytest.approx(np.ptp(t[u : l + 1]))


def test_a_severe_curve_with_an_end_vertebra_tilted_beyond_90_degrees() -> None:
    """A 130° curve whose upper end is tilted −30° and lower end 100° (a collapsing curve with the trunk
    listed to one side): an endplate's tilt is a line's, known up to 180°, so d1 reads L5 at −80°; the
    tilts made continuous along the spine give 130°, T1–L5 (the old engine, reading L4 at −88° next to
    L3 at 84°, reported a major curve of 172° across the one segment L3–L4 and 114° T1–L3)."""
    tilts = np.linspace(-30.0, 100.0, 17)
    p, R = _from_tilts(list(tilts))
    assert frontal_tilt_deg(R)[16] == pytest.approx(-80.0)
    m = compute_measures(p, R)
    got = [(c.upper, c.lower, round(c.angle_deg, 9), c.convexity) for c in m.cobb]
    assert got == [("T1", "L5", 130.0, "right")]
    np.testing.assert_allclose(continuous_tilts(frontal_tilt_deg(R)), tilts, atol=1e-9)


def test_two_equally_deviated_vertebrae_put_the_apex_at_the_disc_between_them() -> None:
    """SRS: the apex is the most deviated vertebra or disc. A symmetric 30° curve T1–T10 (a circular arc)
    has eight vertebrae between its ends, T5 and T6 equally deviated: the disc between them lies farther
    out on the arc than either, so it is the apex (``apical_disc``, named T5). With an odd number of
    vertebrae between the ends (T1–T9) the middle vertebra is."""
    even = compute_measures(*_from_tilts([*np.linspace(-15.0, 15.0, 10), *[15.0] * 7])).cobb
    assert [(c.upper, c.lower, c.apex, c.apical_disc) for c in even] == [("T1", "T10", "T5", True)]
    odd = compute_measures(*_from_tilts([*np.linspace(-15.0, 15.0, 9), *[15.0] * 8])).cobb
    assert [(c.upper, c.lower, c.apex, c.apical_disc) for c in odd] == [("T1", "T9", "T5", False)]


def test_the_convexity_is_the_tilts_even_when_the_positions_disagree() -> None:
    """A 12° curve T1–T5 whose tilt rises caudally (convex right, as its end vertebrae are tilted) but
    whose three middle centres sit 5 mm to the left, about twice the curve's sagitta of 2.6 mm: positions
    and tilts from different sources (a fitted centreline, corner lines) disagree this way for a short
    mild curve. The convexity follows the tilts that define the curve (the old engine said left)."""
    tilts = [-6.0, -3.0, 0.0, 3.0, 6.0, *[6.0] * 12]
    p, R = _from_tilts(tilts)
    p[1:4, 0] += 5.0
    [c] = compute_measures(p, R).cobb
    assert (c.upper, c.lower, round(c.angle_deg, 9), c.convexity) == ("T1", "T5", 12.0, "right")


def test_lenke_inputs_at_their_boundaries() -> None:
    """Lenke et al. 2001 (J Bone Joint Surg Am 83:1169–1181): a minor curve is structural with a bending
    Cobb ≥ 25° or a regional kyphosis ≥ +20° (T2–T5 proximal thoracic, T10–L2 the others); the sagittal
    modifier on T5–T12 is '-' below 10°, 'N' 10–40°, '+' above 40°. Exactly 25°, 20°, 10° and 40° are on
    the inclusive side; regions go by apex (T3 proximal thoracic, T8 main thoracic, L1 thoracolumbar)."""
    assert [lenke_modifier(k) for k in (9.999, 10.0, 40.0, 40.001)] == ["-", "N", "N", "+"]
    # a 25° left curve T1–T5, a 55° right major T5–T11, a 24.999° left curve T11–L3
    thoracic = [*np.linspace(0.0, -25.0, 5), *np.linspace(-25.0, 30.0, 7)[1:]]
    tilts = [*thoracic, *np.linspace(30.0, 5.001, 5)[1:], 5.001, 5.001]
    m = compute_measures(*_from_tilts(tilts))
    assert [(c.upper, c.lower, c.apex, round(c.angle_deg, 9)) for c in m.cobb] == [
        ("T1", "T5", "T3", 25.0), ("T5", "T11", "T8", 55.0), ("T11", "L3", "L1", 24.999)]  # fmt: skip
    beta = np.zeros(17)
    i = LEVEL_INDEX
    beta[i["T2"]], beta[i["T5"]], beta[i["T12"]], beta[i["L2"]] = 10.0, -10.0, -50.0, -19.999
    lenke = lenke_inputs(m.cobb, beta)
    assert (lenke.t2_t5_kyphosis_deg, lenke.t5_t12_kyphosis_deg, lenke.t10_l2_kyphosis_deg) == (20.0, 40.0, 19.999)
    assert lenke.sagittal_thoracic_modifier == "N"
    got = [(c.region, c.apex, c.major, c.structural_by_magnitude, c.structural_by_kyphosis) for c in lenke.curves]
    assert got == [
        ("proximal_thoracic", "T3", False, True, True),  # 25° standing, T2–T5 = +20°
        ("main_thoracic", "T8", True, True, False),  # the major curve; T10–L2 = 19.999°
        ("thoracolumbar_lumbar", "L1", False, False, False),  # 24.999°
    ]


def test_an_apical_t11_t12_disc_is_main_thoracic() -> None:
    """Lenke 2001: the main thoracic region's apex runs from T6 to the T11–T12 disc. A symmetric 30° curve
    T8–L3 has T11 and T12 equally deviated: its apex is the T11–T12 disc, named T11, main thoracic."""
    tilts = [*[-14.0] * 7, *np.linspace(-15.0, 15.0, 8), 14.0, 14.0]
    [c] = compute_measures(*_from_tilts(tilts)).cobb
    assert (c.upper, c.lower, c.apex, c.apical_disc) == ("T8", "L3", "T11", True)
    assert [lc.region for lc in lenke_inputs([c], np.zeros(17)).curves] == ["main_thoracic"]
