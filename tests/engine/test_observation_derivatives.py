"""Pedicle and tilt observations in the registration: analytic Jacobian and Hessian vs finite differences."""

import dataclasses

import numpy as np
import pytest

from benches.perf import placeholder_parameters, synthetic_spine
from spine_engine.fit import RegistrationProblem, ViewData, fit, initial_configuration
from spine_engine.projection import image_axes, project
from spine_engine.rotations import exp_so3

RNG = np.random.default_rng(5)
N = 17


def _problem(
    pedicles: bool, tilts: bool, tilt_weight: float = 3e4
) -> tuple[RegistrationProblem, np.ndarray, np.ndarray]:
    truth_r, truth_R = synthetic_spine(cobb_deg=40.0, twist_deg=20.0, kyphosis_mm=25.0, apex=0.5)
    rest_r, rest_R = synthetic_spine(cobb_deg=12.0, twist_deg=0.0, kyphosis_mm=35.0)
    params = placeholder_parameters(rest_r, rest_R)
    e_c, e_r = image_axes(("L", "F"))
    s, T = 1.12, np.array([150.0, 80.0])
    idx = np.arange(N)
    view = ViewData("pa", idx, project(truth_r, e_c, e_r, s, T) + RNG.normal(0, 0.5, (N, 2)), e_c, e_r, s, T, 10.0)
    extra: dict[str, object] = {}
    if pedicles:
        pi = np.repeat(np.arange(N), 2)
        offsets = np.column_stack(
            [
                np.tile([-1.0, 1.0], N) * RNG.uniform(10, 20, 2 * N),
                -RNG.uniform(10, 25, 2 * N),
                RNG.uniform(0, 8, 2 * N),
            ]
        )
        centres = truth_r[pi] + (truth_R[pi] @ offsets[:, :, None])[:, :, 0]
        columns = project(centres, e_c, e_r, s, T)[:, 0] + RNG.normal(0, 0.7, 2 * N)
        extra.update(offset_indices=pi, offset_vectors=offsets, offset_columns=columns)
    if tilts:
        ti = np.arange(0, N, 2)
        d1 = truth_R[ti][:, :, 0]
        dirs = np.stack([d1 @ e_c, d1 @ e_r], axis=1) @ exp_so3(np.array([0, 0, 0.05]))[:2, :2]
        extra.update(
            tilt_indices=ti,
            tilt_directions=dirs * RNG.uniform(0.5, 3.0, (len(ti), 1)),
            tilt_weights=np.full(len(ti), tilt_weight),
            tilt_director=np.array([1.0, 0.0, 0.0]),
        )
    view = dataclasses.replace(view, **extra)  # type: ignore[arg-type]
    top, bottom = (truth_r[0], truth_R[0]), (truth_r[-1], truth_R[-1])
    r0, R0 = initial_configuration(rest_r, rest_R, [view], top, bottom)
    r0[1:-1] += RNG.normal(0, 2.0, (N - 2, 3))
    R0[1:-1] = R0[1:-1] @ exp_so3(RNG.normal(0, 0.08, (N - 2, 3)))
    return RegistrationProblem(params, [view], top, bottom), r0, R0


@pytest.mark.parametrize(("pedicles", "tilts"), [(True, False), (False, True), (True, True)])
def test_jacobian_of_pedicle_and_tilt_rows_matches_central_differences(pedicles: bool, tilts: bool) -> None:
    prob, r, R = _problem(pedicles, tilts)
    J = prob.jacobian(r, R)
    start = 6 * (N - 1) + prob.n_fit
    assert prob.n_residuals - start == prob.n_offsets + prob.n_tilts > 0
    h = 1e-6
    J_fd = np.empty_like(J)
    for k in range(J.shape[1]):
        d = np.zeros(J.shape[1])
        d[k] = h
        J_fd[:, k] = (prob.residuals(*prob.retract(r, R, d)) - prob.residuals(*prob.retract(r, R, -d))) / (2 * h)
    Jx, Jx_fd = J[start:], J_fd[start:]
    assert np.linalg.norm(Jx) > 0
    assert np.linalg.norm(Jx - Jx_fd) < 1e-7 * np.linalg.norm(Jx)
    np.testing.assert_allclose(J[:start], J_fd[:start], atol=1e-6 * np.abs(J).max())


@pytest.mark.parametrize(("pedicles", "tilts"), [(True, False), (False, True)])
def test_newton_hessian_with_pedicles_and_tilts_matches_second_differences(pedicles: bool, tilts: bool) -> None:
    prob, r, R = _problem(pedicles, tilts, tilt_weight=3e6)
    g, H = prob.gradient_and_hessian(r, R)
    _, H_gn = prob.gradient_and_hessian(r, R, second_order=False)
    J, rho = prob.jacobian(r, R), prob.residuals(r, R)
    np.testing.assert_allclose(g, J.T @ rho, rtol=1e-10, atol=1e-9 * np.abs(g).max())
    np.testing.assert_allclose(H_gn, J.T @ J, rtol=1e-10, atol=1e-10 * np.abs(H_gn).max())

    # the observations' rows alone: ½∇²‖ρ_x‖² by second differences of their energy in the chart
    # δ ↦ (r + δr, R exp(hat δθ)); it is block-diagonal (each row touches one vertebra)
    start = 6 * (N - 1) + prob.n_fit

    def energy(delta: np.ndarray) -> float:
        rho_x = prob.residuals(*prob.retract(r, R, delta))[start:]
        return float(rho_x @ rho_x)

    n = prob.n_params
    h = 1e-4
    E0 = energy(np.zeros(n))
    H_fd = np.zeros((n, n))
    for j in range(N - 2):
        for a in range(6 * j, 6 * j + 6):
            for b in range(a, 6 * j + 6):
                ea, eb = np.zeros(n), np.zeros(n)
                ea[a], eb[b] = h, h
                if a == b:
                    value = (energy(ea) - 2 * E0 + energy(-ea)) / h**2
                else:
                    value = (energy(ea + eb) - energy(ea - eb) - energy(eb - ea) + energy(-ea - eb)) / (4 * h**2)
                H_fd[a, b] = H_fd[b, a] = 0.5 * value
    Jx = J[start:]
    S_fd = H_fd - Jx.T @ Jx
    # the analytic second-order part of the observations: total minus that of the same problem without them
    plain = RegistrationProblem(
        prob.params, [dataclasses.replace(prob.views[0], offset_indices=None, tilt_indices=None)], prob.top, prob.bottom
    )
    _, H_plain = plain.gradient_and_hessian(r, R)
    _, H_plain_gn = plain.gradient_and_hessian(r, R, second_order=False)
    S = (H - H_gn) - (H_plain - H_plain_gn)
    assert np.linalg.norm(S) > 1e-4 * np.linalg.norm(Jx.T @ Jx)  # not negligible
    assert np.linalg.norm(S - S_fd) < 1e-4 * np.linalg.norm(S)


def test_fit_with_exact_pedicles_and_tilts_recovers_the_truth() -> None:
    truth_r, truth_R = synthetic_spine(cobb_deg=35.0, twist_deg=15.0, kyphosis_mm=25.0, apex=0.45)
    params = placeholder_parameters(truth_r, truth_R)
    e_c, e_r = image_axes(("L", "F"))
    s, T = 1.1, np.array([100.0, 60.0])
    idx = np.arange(N)
    pi = np.repeat(idx, 2)
    offsets = np.column_stack([np.tile([-12.0, 12.0], N), np.full(2 * N, -16.0), np.full(2 * N, 5.0)])
    centres = truth_r[pi] + (truth_R[pi] @ offsets[:, :, None])[:, :, 0]
    d1 = truth_R[:, :, 0]
    view = ViewData(
        "pa", idx, project(truth_r, e_c, e_r, s, T), e_c, e_r, s, T, 10.0,
        offset_indices=pi, offset_vectors=offsets, offset_columns=project(centres, e_c, e_r, s, T)[:, 0],
        tilt_indices=idx, tilt_directions=np.stack([d1 @ e_c, d1 @ e_r], axis=1),
        tilt_weights=np.full(N, 1e5), tilt_director=np.array([1.0, 0.0, 0.0]),
    )  # fmt: skip
    top, bottom = (truth_r[0], truth_R[0]), (truth_r[-1], truth_R[-1])
    rest_r, rest_R = synthetic_spine(cobb_deg=10.0, kyphosis_mm=30.0)
    r0, R0 = initial_configuration(rest_r, rest_R, [view], top, bottom)
    out = fit(params, [view], top, bottom, r0, R0)
    assert out.converged
    assert np.max(np.linalg.norm(out.positions - truth_r, axis=1)) < 1e-3
    assert np.max(np.abs(out.tilt_residuals_deg["pa"])) < 1e-4
    assert np.max(np.abs(out.offset_residuals_mm["pa"])) < 1e-4
