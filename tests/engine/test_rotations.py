"""SO(3) kernels: hat/vee, exp/log round trips at every angle, Jacobians against finite differences."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spine_engine.rotations import (
    cross,
    exp_so3,
    hat,
    left_jacobian_inv,
    log_so3,
    right_jacobian,
    right_jacobian_inv,
    rotation_between,
    slerp,
    vee,
)

RNG = np.random.default_rng(20261122)


def _random_vectors(n: int, angles: np.ndarray) -> np.ndarray:
    axes = RNG.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return axes * angles[:, None]


def _angle_between(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    return np.linalg.norm(log_so3(np.swapaxes(Ra, -1, -2) @ Rb), axis=-1)


def test_hat_is_cross_product_and_vee_inverts_it():
    w = RNG.normal(size=(5, 4, 3))
    x = RNG.normal(size=(5, 4, 3))
    W = hat(w)
    assert W.shape == (5, 4, 3, 3)
    np.testing.assert_allclose((W @ x[..., None])[..., 0], np.cross(w, x), atol=1e-14)
    np.testing.assert_allclose(W, -np.swapaxes(W, -1, -2), atol=0)
    np.testing.assert_allclose(vee(W), w, atol=0)


def test_exp_matches_scipy_and_is_a_rotation():
    phi = RNG.normal(size=(200, 3)) * 2.0
    R = exp_so3(phi)
    np.testing.assert_allclose(R, Rotation.from_rotvec(phi).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    np.testing.assert_array_equal(exp_so3(np.zeros(3)), np.eye(3))


@pytest.mark.parametrize(
    "angles",
    [
        RNG.uniform(0.0, np.pi - 1e-3, 300),
        10.0 ** RNG.uniform(-12, -2, 100),
        np.pi - 10.0 ** RNG.uniform(-10, -2, 100),
        np.array([0.0, 1e-150, 0.05, 0.1, np.pi / 2, 2.3, 2.4]),
    ],
    ids=["random", "small", "near-pi", "special"],
)
def test_log_inverts_exp(angles):
    phi = _random_vectors(len(angles), angles)
    back = log_so3(exp_so3(phi))
    # relative accuracy at every angle, including tiny ones and the near-π branch
    assert np.all(np.abs(back - phi) <= 4e-15 * angles[:, None])
    np.testing.assert_allclose(exp_so3(back), exp_so3(phi), atol=2e-15)


def test_log_at_exactly_pi_and_beyond():
    for axis in (np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([1.0, 2.0, -2.0]) / 3):
        R = exp_so3(np.pi * axis)
        phi = log_so3(R)
        assert np.linalg.norm(phi) == pytest.approx(np.pi, abs=1e-12)
        assert abs(phi @ axis) == pytest.approx(np.pi, abs=1e-12)
        np.testing.assert_allclose(exp_so3(phi), R, atol=1e-15)
    # Angles above π come back as the equivalent rotation with θ ≤ π.
    phi = _random_vectors(50, RNG.uniform(np.pi, 2 * np.pi - 0.1, 50))
    back = log_so3(exp_so3(phi))
    assert np.all(np.linalg.norm(back, axis=1) <= np.pi + 1e-12)
    np.testing.assert_allclose(exp_so3(back), exp_so3(phi), atol=1e-14)
    # log is batched over any leading axes
    assert log_so3(exp_so3(RNG.normal(size=(2, 3, 3)))).shape == (2, 3, 3)


JACOBIAN_ANGLES = [0.0, 1e-7, 0.03, 0.049, 0.051, 0.099, 0.101, 0.5, 1.5, 2.8]


def _fd(f, phi, eps=1e-6):
    cols = []
    for k in range(3):
        e = np.zeros(3)
        e[k] = eps
        cols.append((f(phi, e) - f(phi, -e)) / (2 * eps))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("angle", JACOBIAN_ANGLES)
def test_jacobians_against_finite_differences(angle):
    phi = _random_vectors(1, np.array([angle]))[0]
    # exp(φ + δ) = exp(φ) exp(J_r δ)
    jr = _fd(lambda p, e: log_so3(exp_so3(p).T @ exp_so3(p + e)), phi)
    # log(exp(φ) exp(δ)) = φ + J_r⁻¹ δ ;  log(exp(δ) exp(φ)) = φ + J_l⁻¹ δ
    jr_inv = _fd(lambda p, e: log_so3(exp_so3(p) @ exp_so3(e)), phi)
    jl_inv = _fd(lambda p, e: log_so3(exp_so3(e) @ exp_so3(p)), phi)
    np.testing.assert_allclose(right_jacobian(phi), jr, atol=1e-9)
    np.testing.assert_allclose(right_jacobian_inv(phi), jr_inv, atol=1e-9)
    np.testing.assert_allclose(left_jacobian_inv(phi), jl_inv, atol=1e-9)
    np.testing.assert_allclose(right_jacobian(phi) @ right_jacobian_inv(phi), np.eye(3), atol=1e-14)
    np.testing.assert_allclose(left_jacobian_inv(phi), right_jacobian_inv(phi).T, atol=1e-15)


def test_jacobian_coefficients_are_continuous_at_the_series_switch():
    axis = np.array([0.6, -0.8, 0.0])
    below, above = (0.05 - 1e-12) * axis, (0.05 + 1e-12) * axis  # the Taylor/closed-form switch
    np.testing.assert_allclose(right_jacobian_inv(below), right_jacobian_inv(above), atol=1e-15)
    np.testing.assert_allclose(right_jacobian(below), right_jacobian(above), atol=1e-15)
    phi = RNG.normal(size=(4, 2, 3))
    assert right_jacobian(phi).shape == right_jacobian_inv(phi).shape == (4, 2, 3, 3)


def test_rotation_between_and_slerp():
    a = RNG.normal(size=(20, 3))
    b = RNG.normal(size=(20, 3))
    R = rotation_between(a, b)
    bn = b / np.linalg.norm(b, axis=1, keepdims=True)
    an = a / np.linalg.norm(a, axis=1, keepdims=True)
    np.testing.assert_allclose((R @ an[:, :, None])[:, :, 0], bn, atol=1e-14)
    # the smallest rotation: its angle is the angle between the vectors
    np.testing.assert_allclose(
        np.linalg.norm(log_so3(R), axis=1), np.arccos(np.clip(np.sum(an * bn, axis=1), -1, 1)), atol=1e-7
    )
    np.testing.assert_allclose(rotation_between(a[0], a[0] * 3), np.eye(3), atol=1e-15)
    opposite = rotation_between(a[0], -a[0])
    np.testing.assert_allclose(opposite @ an[0], -an[0], atol=1e-14)

    R0 = exp_so3(RNG.normal(size=3))
    R1 = exp_so3(RNG.normal(size=3) * 0.5) @ R0
    t = np.array([0.0, 0.25, 0.5, 1.0])
    path = slerp(R0, R1, t)
    np.testing.assert_allclose(path[0], R0, atol=1e-15)
    np.testing.assert_allclose(path[-1], R1, atol=1e-14)
    total = _angle_between(R0, R1)
    np.testing.assert_allclose(_angle_between(R0, path), t * total, atol=1e-14)


def test_cross_is_numpys_with_broadcasting() -> None:
    """``rotations.cross`` (the engine's hot paths) equals ``np.cross`` exactly, broadcast."""
    rng = np.random.default_rng(3)
    for a_shape, b_shape in (((3,), (3,)), ((5, 1, 3), (5, 2, 3)), ((4, 3), (3,))):
        a, b = rng.normal(size=a_shape), rng.normal(size=b_shape)
        np.testing.assert_array_equal(cross(a, b), np.cross(a, b))
