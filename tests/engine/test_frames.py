"""frames_from_centreline and axial_rotation_deg: orthonormal right-handed directors, conventions."""

import numpy as np
import pytest

from spine_engine.frames import axial_rotation_deg, frames_from_centreline


def _vertical(n: int = 17, step: float = 25.0) -> np.ndarray:
    return np.column_stack([np.zeros(n), np.zeros(n), -step * np.arange(n)])


def _wavy(n: int = 17) -> np.ndarray:
    s = np.linspace(0.0, 1.0, n)
    return np.column_stack([30 * np.sin(2 * np.pi * s), 25 * np.sin(np.pi * s), -420 * s])


def _assert_orthonormal_right_handed(R: np.ndarray) -> None:
    eye = np.broadcast_to(np.eye(3), R.shape)
    np.testing.assert_allclose(np.swapaxes(R, -1, -2) @ R, eye, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.cross(R[:, :, 0], R[:, :, 1]), R[:, :, 2], atol=1e-12)


def test_vertical_spine_has_the_reference_directors() -> None:
    R = frames_from_centreline(_vertical())
    expected = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # columns d1, d2, d3
    np.testing.assert_allclose(R, np.broadcast_to(expected, R.shape), atol=1e-15)
    np.testing.assert_allclose(axial_rotation_deg(R), 0.0, atol=1e-12)


def test_directors_orthonormal_right_handed_with_and_without_rotation() -> None:
    p = _wavy()
    _assert_orthonormal_right_handed(frames_from_centreline(p))
    _assert_orthonormal_right_handed(frames_from_centreline(p, np.radians(np.linspace(-30, 30, 17))))


def test_d3_is_the_caudal_central_difference_and_d1_the_gram_schmidt_of_left() -> None:
    p = _wavy()
    R = frames_from_centreline(p)
    t = np.empty_like(p)
    t[1:-1], t[0], t[-1] = p[2:] - p[:-2], p[1] - p[0], p[-1] - p[-2]
    np.testing.assert_allclose(R[:, :, 2], t / np.linalg.norm(t, axis=1)[:, None], atol=1e-12)
    d1 = R[:, :, 0]
    assert np.all(d1[:, 0] > 0.9)
    # d1 lies in the plane of +x and d3, on the +x side
    np.testing.assert_allclose(np.einsum("ij,ij->i", d1, np.cross([1.0, 0.0, 0.0], R[:, :, 2])), 0.0, atol=1e-12)


def test_axial_rotation_round_trip_and_sign() -> None:
    psi = np.linspace(-40.0, 40.0, 17)
    R = frames_from_centreline(_vertical(), np.radians(psi))
    np.testing.assert_allclose(axial_rotation_deg(R), psi, atol=1e-12)
    # ψ > 0 turns the anterior director d2 toward patient left (+x)
    assert R[-1, 0, 1] > 0 and R[0, 0, 1] < 0
    # d3 is untouched by the axial rotation
    np.testing.assert_allclose(R[:, :, 2], frames_from_centreline(_vertical())[:, :, 2])


def test_inclined_tangent_keeps_zero_and_sign_of_axial_rotation() -> None:
    p = _wavy()
    np.testing.assert_allclose(axial_rotation_deg(frames_from_centreline(p)), 0.0, atol=1e-9)
    psi = np.full(17, 12.0)
    measured = axial_rotation_deg(frames_from_centreline(p, np.radians(psi)))
    assert np.all(measured > 0) and np.all(np.abs(measured - psi) < 3.0)


def test_axial_rotation_of_a_single_matrix() -> None:
    R = frames_from_centreline(_vertical(), np.radians(np.full(17, -20.0)))[5]
    assert axial_rotation_deg(R) == pytest.approx(-20.0)


@pytest.mark.parametrize(
    "points",
    [
        np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [20.0, 0.0, 0.0]]),  # tangent along +x
        np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, -20.0]]),  # coinciding points
        np.zeros((1, 3)),
        np.zeros((4, 2)),
        np.array([[0.0, 0.0, 0.0], [0.0, 0.0, np.nan]]),
    ],
)
def test_degenerate_centrelines_raise(points: np.ndarray) -> None:
    with pytest.raises(ValueError):
        frames_from_centreline(points)
