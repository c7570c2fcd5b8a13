"""Synthetic spines: deterministic, varied, and measuring as designed."""

import numpy as np
import pytest

from spine_engine.anatomy import rest_segment_lengths
from spine_engine.measures import compute_measures
from spine_engine.synthetic import KINDS, SyntheticSpine, generate_spine, generate_spines


@pytest.fixture(scope="module")
def spines() -> list[SyntheticSpine]:
    return generate_spines(12, seed=2024)


def test_deterministic_for_a_seed(spines: list[SyntheticSpine]) -> None:
    again = generate_spines(4, seed=2024)
    for a, b in zip(spines[:4], again, strict=True):
        np.testing.assert_array_equal(a.positions, b.positions)
        np.testing.assert_array_equal(a.rotations, b.rotations)
        assert (a.kind, a.cobb_target_deg, a.seed) == (b.kind, b.cobb_target_deg, b.seed)
    single = generate_spine(spines[5].seed, spines[5].kind)
    np.testing.assert_array_equal(single.positions, spines[5].positions)
    other = generate_spines(4, seed=2025)
    assert not np.allclose(other[0].positions, spines[0].positions)


def test_covers_single_and_double_curves(spines: list[SyntheticSpine]) -> None:
    assert {s.kind for s in spines} == set(KINDS)
    for s in spines:
        n = 2 if s.kind == "double" else 1
        assert len(s.cobb_target_deg) == len(s.ends) == len(s.convexity) == n
        assert all(10.0 <= t <= 80.0 for t in s.cobb_target_deg)
        if s.kind == "double":
            assert s.convexity[0] != s.convexity[1]


def test_cobb_ends_convexity_and_rotation_as_designed(spines: list[SyntheticSpine]) -> None:
    for s in spines:
        m = compute_measures(s.positions, s.rotations, min_cobb_deg=5.0)
        for (upper, lower), target, side in zip(s.ends, s.cobb_target_deg, s.convexity, strict=True):
            curve = next(c for c in m.cobb if (c.upper, c.lower) == (upper, lower))
            assert curve.angle_deg == pytest.approx(target, abs=3.0)
            assert curve.convexity == side
            # toward the convexity: ψ > 0 (patient left) for a left curve, ψ < 0 for a right one
            toward = curve.apex_axial_rotation_deg if side == "left" else -curve.apex_axial_rotation_deg
            assert 0.1 * target < toward < 0.7 * target
        assert m.thoracic_kyphosis_t4_t12_deg == pytest.approx(s.kyphosis_deg, abs=1e-9)
        assert m.lumbar_lordosis_l1_l5_deg == pytest.approx(s.lordosis_deg, abs=1e-9)
        assert 19.9 < s.kyphosis_deg < 60.1 and 29.9 < s.lordosis_deg < 65.1


def test_geometry_is_realistic(spines: list[SyntheticSpine]) -> None:
    table = rest_segment_lengths()
    for s in spines:
        R = s.rotations
        np.testing.assert_allclose(np.swapaxes(R, 1, 2) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
        ds = np.linalg.norm(np.diff(s.positions, axis=0), axis=1)
        np.testing.assert_allclose(ds, s.ds, rtol=1e-12)
        assert 0.85 <= s.size_scale <= 1.15
        assert np.all(np.abs(ds / (s.size_scale * table) - 1) <= 0.1 + 1e-12)
        assert np.all(R[:, 2, 2] < -0.5)  # tangents run caudally
        assert abs(s.positions[-1, 0] - s.positions[0, 0]) < 12.0  # coronal balance
        assert abs(s.positions[-1, 1] - s.positions[0, 1]) < 21.0  # sagittal balance


def test_unknown_kind_raises() -> None:
    with pytest.raises(ValueError):
        generate_spine(1, "cervical")
