"""The rod's compiled derivative kernels (``fit.rod_rows``) against the array formulas they replaced.

``RodRows.local_jacobian`` and ``RodRows.second_order`` are loops over the segments; the reference
here is the stacked numpy evaluation of the same formulas (as the module had it before), on random
configurations with relative rotations both below and above the Taylor switch θ = 0.1 rad. Their
derivatives themselves are checked against finite differences in ``test_registration_core`` and
``test_observation_derivatives``.
"""

from __future__ import annotations

import numpy as np
import pytest

from spine_engine.fit import RodParameters
from spine_engine.fit.rod_rows import RodCache, RodRows, jr_inv_coefficients, jr_inverse
from spine_engine.fit.types import FloatArray
from spine_engine.rotations import exp_so3, hat, right_jacobian_inv

N = 17


def _reference_coefficients(theta2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    theta = np.sqrt(theta2)
    small = theta < 0.1
    t = np.where(small, 1.0, theta)
    t2 = t * t
    cot = 1.0 / np.tan(0.5 * t)
    d = np.where(
        small,
        1.0 / 12.0 + theta2 * (1.0 / 720.0 + theta2 * (1.0 / 30240.0 + theta2 / 1209600.0)),
        1.0 / t2 - 0.5 * cot / t,
    )
    dp = np.where(
        small,
        1.0 / 360.0 + theta2 * (1.0 / 7560.0 + theta2 * (1.0 / 201600.0 + theta2 / 5987520.0)),
        (-2.0 / t2 + 0.5 * cot / t + 0.25 * (1.0 + cot * cot)) / t2,
    )
    return d, dp


def _reference(rod: RodRows, Rt, phi, v, rho):
    """The stacked array formulas of J (N−1, 6, 12) and of the upper blocks of Σρ∇²ρ (N−1, 12, 12)."""
    theta2 = np.einsum("ij,ij->i", phi, phi)
    d, dp = _reference_coefficients(theta2)
    half_P = hat(0.5 * phi)
    S = d[:, None, None] * (phi[:, :, None] * phi[:, None, :])
    S.reshape(-1, 9)[:, ::4] += (1.0 - d * theta2)[:, None]
    Jr_inv, Jl_inv = S + half_P, S - half_P
    J = np.zeros((len(phi), 6, 12))
    au = rod._au[:, :, None]
    J[:, :3, 3:6] = -au * Jl_inv
    J[:, :3, 9:12] = au * Jr_inv
    J[:, 3:, 0:3] = -rod._cv_ds[:, :, None] * Rt
    J[:, 3:, 6:9] = rod._cv_ds[:, :, None] * Rt
    J[:, 3:, 3:6] = rod._cv[:, :, None] * hat(v)
    lam = rho[:, :3] * rod._au
    mu = rho[:, 3:] * rod._cv
    pl = np.einsum("ij,ij->i", phi, lam)
    P2l = phi * pl[:, None] - theta2[:, None] * lam
    common = dp[:, None, None] * (P2l[:, :, None] * phi[:, None, :]) + d[:, None, None] * (
        phi[:, :, None] * lam[:, None, :] - 2.0 * lam[:, :, None] * phi[:, None, :]
    )
    common.reshape(-1, 9)[:, ::4] += (d * pl)[:, None]
    K_plus, K_minus = common + hat(0.5 * lam), common - hat(0.5 * lam)
    Jr_l = (Jr_inv @ lam[:, :, None])[:, :, 0]
    Jl_l = (Jl_inv @ lam[:, :, None])[:, :, 0]
    mv = mu[:, :, None] * v[:, None, :]
    Sec = np.zeros((len(phi), 12, 12))
    tt = K_minus @ Jl_inv + hat(0.5 * Jr_l) + 0.5 * (mv + np.swapaxes(mv, 1, 2))
    tt.reshape(-1, 9)[:, ::4] -= np.einsum("ij,ij->i", mu, v)[:, None]
    Sec[:, 3:6, 3:6] = tt
    Sec[:, 9:12, 9:12] = K_plus @ Jr_inv - hat(0.5 * Jl_l)
    Sec[:, 3:6, 9:12] = -np.swapaxes(K_plus @ Jl_inv, 1, 2)
    C = (hat(mu) @ Rt) * rod._inv_ds[:, :, None]
    Sec[:, 3:6, 6:9] = C
    Sec[:, 0:3, 3:6] = -np.swapaxes(C, 1, 2)
    return J, Jr_inv, Jl_inv, d, dp, Sec


def _random_rod(seed: int, angle_scale: float) -> tuple[RodRows, RodCache, FloatArray]:
    """A rod of random rest strains and stiffnesses at a random configuration (rotations of about
    ``angle_scale`` rad): the rows, their evaluation cache and the residuals."""
    rng = np.random.default_rng(seed)
    params = RodParameters(
        ds=rng.uniform(15.0, 35.0, N - 1),
        u0=rng.normal(0.0, 0.003, (N - 1, 3)),
        v0=np.column_stack((rng.normal(0.0, 0.02, (N - 1, 2)), np.ones(N - 1))),
        alpha=rng.uniform(1e5, 1e6, (N - 1, 3)),
        beta=rng.uniform(1e2, 1e3, (N - 1, 3)),
    )
    rod = RodRows(params)
    R = exp_so3(rng.normal(0.0, angle_scale, (N, 3)))
    r = np.cumsum(rng.normal(0.0, 20.0, (N, 3)), axis=0)
    res = np.empty(6 * (N - 1))
    cache = rod.evaluate(r, R, res)
    return rod, cache, res


@pytest.mark.parametrize("angle_scale", [0.01, 0.08, 0.3, 1.5])
def test_kernels_match_the_array_formulas(angle_scale):
    rod, cache, res = _random_rod(int(angle_scale * 100), angle_scale)
    rho = res.reshape(N - 1, 6)
    J, Jr_inv, Jl_inv, d, dp, Sec = _reference(rod, cache.Rt, cache.phi, cache.v, rho)
    local = rod.local_jacobian(cache)
    np.testing.assert_allclose(local.J, J, rtol=1e-13, atol=1e-13 * np.abs(J).max())
    np.testing.assert_allclose(local.Jr_inv, Jr_inv, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(local.Jl_inv, Jl_inv, rtol=1e-13, atol=1e-15)
    # d and d'/θ cancel (1/θ² against cot(θ/2)/(2θ)) just above θ = 0.1: a last-bit difference of
    # tan between numpy and the compiled libm grows by ~1/(dθ²) and ~1/(d'θ⁴/θ) there
    np.testing.assert_allclose(local.d, d, rtol=1e-12)
    np.testing.assert_allclose(local.dp, dp, rtol=1e-8)
    S = rod.second_order(cache, local, rho)
    np.testing.assert_allclose(S, Sec, rtol=1e-8, atol=1e-12 * np.abs(Sec).max())


def test_jr_inv_coefficients_on_both_sides_of_the_taylor_switch():
    theta = np.array([0.0, 1e-8, 1e-3, 0.0999999, 0.1, 0.1000001, 0.5, 2.0, 3.1])
    d, dp = jr_inv_coefficients(theta * theta)
    d_ref, dp_ref = _reference_coefficients(theta * theta)
    np.testing.assert_allclose(d, d_ref, rtol=1e-12)
    np.testing.assert_allclose(dp, dp_ref, rtol=1e-8)
    phi = np.random.default_rng(3).normal(0.0, 0.7, (6, 3))
    np.testing.assert_allclose(jr_inverse(phi), right_jacobian_inv(phi), rtol=1e-12, atol=1e-14)


def test_jr_inverse_kernel_is_the_array_formula_bit_for_bit():
    """``jr_inverse``'s compiled kernel against the stacked formula it replaced, (1 − dθ²)I + d φφᵀ +
    ½ hat(φ) with d from ``jr_inv_coefficients``: equal, not close (the same operations), on both sides
    of the Taylor switch."""
    rng = np.random.default_rng(5)
    phi = np.concatenate([rng.normal(0.0, 0.03, (40, 3)), rng.normal(0.0, 0.9, (40, 3))])
    theta2 = np.einsum("ij,ij->i", phi, phi)
    d, _ = jr_inv_coefficients(theta2)
    S = d[:, None, None] * (phi[:, :, None] * phi[:, None, :])
    S.reshape(-1, 9)[:, ::4] += (1.0 - d * theta2)[:, None]
    assert np.array_equal(jr_inverse(phi), S + hat(0.5 * phi))


@pytest.mark.parametrize("second_order", [False, True])
def test_normal_blocks_are_the_upper_products_of_the_local_jacobian(second_order):
    rod, cache, res = _random_rod(11, 0.2)
    rho = res.reshape(N - 1, 6)
    blocks = rod.normal_blocks(cache, rho, second_order)
    local = rod.local_jacobian(cache)
    J = local.J.copy()
    a, b = np.triu_indices(12)
    JTJ = np.swapaxes(J, 1, 2) @ J
    np.testing.assert_allclose(blocks.H, JTJ[:, a, b], rtol=1e-13, atol=1e-13 * np.abs(JTJ).max())
    g = (np.swapaxes(J, 1, 2) @ rho[:, :, None])[:, :, 0]
    np.testing.assert_allclose(blocks.g, g, rtol=1e-13, atol=1e-13 * np.abs(g).max())
    if second_order:
        S = rod.second_order(cache, local, rho)
        assert blocks.S is not None
        np.testing.assert_array_equal(blocks.S, S[:, a, b])
    else:
        assert blocks.S is None
