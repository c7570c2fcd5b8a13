"""Discrete Cosserat rod strains and energy on shapes with closed-form strains."""

import numpy as np
import pytest

from spine_engine.rod import configuration_from_strains, internal_energy, strains
from spine_engine.rotations import exp_so3

RNG = np.random.default_rng(7)
N = 17


def _frames(d1: np.ndarray, d2: np.ndarray, d3: np.ndarray) -> np.ndarray:
    R = np.stack((d1, d2, d3), axis=-1)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    return R


def _arc_lengths(ds_step: float, n: int = N) -> np.ndarray:
    return np.full(n - 1, ds_step)


def test_frontal_arc_has_constant_lateral_bending_u2():
    # Circle in the frontal (x, z) plane, walked caudally from the origin and turning toward the
    # patient's left (+x). d2 = −y (anterior) throughout, d3 the caudal tangent, d1 = d2 × d3.
    rho, dphi = 250.0, 0.06
    phi = dphi * np.arange(N)
    centre = np.array([rho, 0.0, 0.0])
    r = centre + rho * np.stack((-np.cos(phi), np.zeros(N), -np.sin(phi)), axis=1)
    d3 = np.stack((np.sin(phi), np.zeros(N), -np.cos(phi)), axis=1)
    d2 = np.tile([0.0, -1.0, 0.0], (N, 1))
    R = _frames(np.cross(d2, d3), d2, d3)
    u, v = strains(r, R, _arc_lengths(rho * dphi))
    # Right-hand rule: a rotation about d2 = −y by +Δφ turns d3 = −z toward +x, so u2 = +1/ρ.
    np.testing.assert_allclose(u[:, 1], 1.0 / rho, rtol=1e-12)
    np.testing.assert_allclose(u[:, [0, 2]], 0.0, atol=1e-15)
    # The chord lies in the (d1, d3) plane at half the turning angle: v = (sin, 0, cos)·chord/Δs.
    chord = 2 * rho * np.sin(dphi / 2)
    expected_v = chord / (rho * dphi) * np.array([np.sin(dphi / 2), 0.0, np.cos(dphi / 2)])
    np.testing.assert_allclose(v, np.broadcast_to(expected_v, v.shape), atol=1e-14)

    # Turning toward the patient's right instead flips the sign.
    mirror = np.diag([-1.0, 1.0, 1.0])
    r_m = r @ mirror
    d3_m = d3 @ mirror
    R_m = _frames(np.cross(d2, d3_m), d2, d3_m)
    u_m, _ = strains(r_m, R_m, _arc_lengths(rho * dphi))
    np.testing.assert_allclose(u_m[:, 1], -1.0 / rho, rtol=1e-12)


def test_sagittal_arc_has_constant_u1():
    # Circle in the sagittal (y, z) plane turning posteriorly (+y) going caudally, d1 = +x.
    rho, dphi = 400.0, 0.05
    phi = dphi * np.arange(N)
    r = np.array([0.0, rho, 0.0]) + rho * np.stack((np.zeros(N), -np.cos(phi), -np.sin(phi)), axis=1)
    d3 = np.stack((np.zeros(N), np.sin(phi), -np.cos(phi)), axis=1)
    d1 = np.tile([1.0, 0.0, 0.0], (N, 1))
    R = _frames(d1, np.cross(d3, d1), d3)
    u, _ = strains(r, R, _arc_lengths(rho * dphi))
    # A rotation about d1 = +x by +Δφ turns d3 = −z toward +y: u1 = +1/ρ.
    np.testing.assert_allclose(u[:, 0], 1.0 / rho, rtol=1e-12)
    np.testing.assert_allclose(u[:, 1:], 0.0, atol=1e-15)


def test_straight_rod_with_uniform_twist_has_constant_u3():
    ds, tau = 28.0, 0.004
    r = np.stack((np.zeros(N), np.zeros(N), -ds * np.arange(N)), axis=1)
    angle = tau * ds * np.arange(N)
    d1 = np.stack((np.cos(angle), -np.sin(angle), np.zeros(N)), axis=1)
    d3 = np.tile([0.0, 0.0, -1.0], (N, 1))
    R = _frames(d1, np.cross(d3, d1), d3)
    u, v = strains(r, R, _arc_lengths(ds))
    np.testing.assert_allclose(u[:, 2], tau, rtol=1e-12)
    np.testing.assert_allclose(u[:, :2], 0.0, atol=1e-15)
    np.testing.assert_allclose(v, np.broadcast_to([0.0, 0.0, 1.0], v.shape), atol=1e-15)


def test_uniform_stretch_gives_constant_v3():
    ds = RNG.uniform(24.0, 34.0, N - 1)
    stretch = 1.07
    z = -np.concatenate(([0.0], np.cumsum(stretch * ds)))
    r = np.stack((np.full(N, 3.0), np.full(N, -2.0), z), axis=1)
    R = np.broadcast_to(_frames(np.array([1.0, 0, 0]), np.array([0, -1.0, 0]), np.array([0, 0, -1.0])), (N, 3, 3))
    u, v = strains(r, R, ds)
    np.testing.assert_allclose(v[:, 2], stretch, rtol=1e-14)
    np.testing.assert_allclose(v[:, :2], 0.0, atol=0)
    np.testing.assert_allclose(u, 0.0, atol=0)


def test_strains_are_batched_and_inverted_by_configuration_from_strains():
    ds = RNG.uniform(24.0, 34.0, N - 1)
    u0 = RNG.normal(scale=0.004, size=(N - 1, 3))
    v0 = np.array([0.0, 0.0, 1.0]) + RNG.normal(scale=0.02, size=(N - 1, 3))
    R0 = exp_so3(RNG.normal(size=3))
    r, R = configuration_from_strains(np.array([1.0, 2.0, 3.0]), R0, u0, v0, ds)
    u, v = strains(r, R, ds)
    np.testing.assert_allclose(u, u0, atol=1e-15)
    np.testing.assert_allclose(v, v0, atol=1e-14)
    ub, vb = strains(np.stack((r, r + 5.0)), np.stack((R, R)), ds)
    assert ub.shape == vb.shape == (2, N - 1, 3)
    np.testing.assert_allclose(ub[1], u, atol=0)
    np.testing.assert_allclose(vb[1], v, atol=1e-14)


def test_internal_energy_is_equation_6():
    ds = RNG.uniform(24.0, 34.0, N - 1)
    u0, v0 = RNG.normal(size=(N - 1, 3)), RNG.normal(size=(N - 1, 3))
    alpha, beta = RNG.uniform(1e5, 1e6, (N - 1, 3)), RNG.uniform(1e3, 1e4, (N - 1, 3))
    assert internal_energy(u0, v0, u0, v0, alpha, beta, ds) == 0.0
    du, dv = RNG.normal(size=(N - 1, 3)) * 1e-3, RNG.normal(size=(N - 1, 3)) * 1e-2
    expected = 0.0
    for i in range(N - 1):
        for k in range(3):
            expected += 0.5 * ds[i] * (alpha[i, k] * du[i, k] ** 2 + beta[i, k] * dv[i, k] ** 2)
    e = internal_energy(u0 + du, v0 + dv, u0, v0, alpha, beta, ds)
    assert isinstance(e, float)
    assert e == pytest.approx(expected, rel=1e-13)
    assert internal_energy(u0 + 2 * du, v0 + 2 * dv, u0, v0, alpha, beta, ds) == pytest.approx(4 * e, rel=1e-13)
