"""Perspective and joint-projection derivatives against finite differences (issue #10, items 2 and 3).

The cameras' analytic derivatives (``fit.cameras``) and the whole Jacobian of a problem whose views'
projections are estimated with the spine, every vertebra free, soft poses and camera priors
(``fit.problem``), against central differences of the residuals (step 1e-6; the bound 1e-6 relative
is far above the O(h²) truncation and rounding of that step and far below any sign or factor error).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from spine_engine.experiments.perf import placeholder_parameters, synthetic_spine
from spine_engine.fit import Camera, Pose, PosePrior, RegistrationProblem, ViewData, solve
from spine_engine.fit.cameras import project
from spine_engine.projection import image_axes
from spine_engine.rotations import exp_so3

RNG = np.random.default_rng(11)
N = 17
PA = image_axes(("L", "F"))
LAT = image_axes(("A", "F"))
BEAM_PA = np.array([0.0, -1.0, 0.0])
BEAM_LAT = np.array([1.0, 0.0, 0.0])


def _cameras() -> list[tuple[Camera, tuple[np.ndarray, np.ndarray]]]:
    weak = Camera("weak", np.array([1.13, 140.0, 420.0, np.radians(1.5)]), np.ones(4, dtype=bool),
                  scale_prior=(1.125, 0.035))  # fmt: skip
    persp = Camera("perspective", np.array([210.0, 480.0, 5.0, -12.0, -200.0, np.radians(-1.0)]),
                   np.ones(6, dtype=bool), sid_mm=1800.0, sod_mm=1550.0, beam=BEAM_LAT)  # fmt: skip
    free = np.array([True, True, False, True, False, False])  # central ray unknown: o moves along the beam only
    persp_pa = Camera("perspective", np.array([180.0, 450.0, 0.0, 20.0, -210.0, 0.0]), free,
                      sid_mm=1800.0, sod_mm=1600.0, beam=BEAM_PA)  # fmt: skip
    return [(weak, PA), (persp, LAT), (persp_pa, PA)]


@pytest.mark.parametrize("k", [0, 1, 2])
def test_camera_derivatives_match_central_differences(k: int) -> None:
    camera, (e_c, e_r) = _cameras()[k]
    r = RNG.normal(0.0, 80.0, (9, 3)) + np.array([0.0, 0.0, -200.0])
    out = project(camera, camera.values, r, e_c, e_r)
    h = 1e-6
    for a in range(3):
        d = np.zeros(3)
        d[a] = h * 100
        fd = (project(camera, camera.values, r + d, e_c, e_r).points
              - project(camera, camera.values, r - d, e_c, e_r).points) / (2 * h * 100)  # fmt: skip
        np.testing.assert_allclose(out.d_r[:, :, a], fd, rtol=1e-6, atol=1e-9)
    for p in range(len(camera.values)):
        d = np.zeros(len(camera.values))
        d[p] = h * max(1.0, abs(camera.values[p]))
        fd = (project(camera, camera.values + d, r, e_c, e_r).points
              - project(camera, camera.values - d, r, e_c, e_r).points) / (2 * d[p])  # fmt: skip
        np.testing.assert_allclose(out.d_params[:, :, p], fd, rtol=1e-6, atol=1e-7)


def test_perspective_is_the_pinhole() -> None:
    """A point on the central ray lands on c; magnification SID/SOD at the plane through o; a point
    nearer the source is magnified more."""
    camera, (e_c, e_r) = _cameras()[1]
    o = camera.values[2:5]
    assert np.allclose(project(camera, camera.values, o[None] + 40.0 * BEAM_LAT, e_c, e_r).points[0], camera.values[:2])
    step = 10.0 * e_r
    near = project(camera, camera.values, np.stack([o + step, o]), e_c, e_r).points
    assert np.linalg.norm(near[0] - near[1]) == pytest.approx(10.0 * 1800.0 / 1550.0)
    closer = project(camera, camera.values, np.stack([o - 100 * BEAM_LAT + step, o - 100 * BEAM_LAT]), e_c, e_r).points
    assert np.linalg.norm(closer[0] - closer[1]) == pytest.approx(10.0 * 1800.0 / 1450.0)


def _joint_problem() -> tuple[RegistrationProblem, np.ndarray, np.ndarray]:
    truth_r, truth_R = synthetic_spine(cobb_deg=35.0, twist_deg=15.0, kyphosis_mm=25.0, apex=0.5)
    rest_r, rest_R = synthetic_spine(cobb_deg=10.0, twist_deg=0.0, kyphosis_mm=35.0)
    params = placeholder_parameters(rest_r, rest_R)
    views = []
    for name, (camera, (e_c, e_r)), levels in (
        ("pa", _cameras()[0], np.arange(N)),
        ("lateral", _cameras()[1], np.arange(3, N)),
    ):
        points = project(camera, camera.values, truth_r[levels], e_c, e_r).points + RNG.normal(0, 1.0, (len(levels), 2))
        jittered = dataclasses.replace(camera, values=camera.values * (1 + RNG.normal(0, 1e-3, len(camera.values))))
        views.append(ViewData(name, levels, points, e_c, e_r, camera.reference_scale, np.zeros(2), 50.0,
                              camera=jittered))  # fmt: skip
    pa = views[0]
    pi = np.repeat(np.arange(0, N, 4), 2)
    offsets = np.column_stack([np.tile([-1.0, 1.0], len(pi) // 2) * 15.0, -np.full(len(pi), 18.0), np.zeros(len(pi))])
    weak = _cameras()[0][0]
    columns = RNG.normal(0, 5, len(pi)) + project(weak, weak.values, truth_r[pi], *PA).points[:, 0]
    views[0] = dataclasses.replace(pa, offset_indices=pi, offset_vectors=offsets, offset_columns=columns)
    turned = truth_R[-1] @ exp_so3(np.array([0.05, 0.0, 0.02]))
    priors = [PosePrior(0, Pose(truth_r[0] + 2.0, truth_R[0]), 3.0, np.radians(4.0)),
              PosePrior(N - 1, Pose(truth_r[-1], turned), 2.0, 0.1)]  # fmt: skip
    r = truth_r + RNG.normal(0, 2.0, truth_r.shape)
    R = truth_R @ exp_so3(RNG.normal(0, 0.05, (N, 3)))
    return RegistrationProblem(params, views, None, None, pose_priors=priors, energy_unit=3.0), r, R


def test_joint_jacobian_matches_central_differences() -> None:
    prob, r, R = _joint_problem()
    assert prob.n_border == 4 + 6 and prob.layout.n_params == 6 * N + 10
    state = prob.initial_state(r, R)
    J = prob.jacobian_state(state)
    h = 1e-6
    J_fd = np.empty_like(J)
    for k in range(J.shape[1]):
        d = np.zeros(J.shape[1])
        d[k] = h
        J_fd[:, k] = (prob.evaluate(prob.step(state, d))[0] - prob.evaluate(prob.step(state, -d))[0]) / (2 * h)
    assert set(prob.row_kinds) >= {"rod", "landmark:pa", "landmark:lateral", "offset:pa", "pose", "camera"}
    np.testing.assert_allclose(J, J_fd, rtol=0, atol=1e-6 * np.abs(J).max())


def test_bordered_normal_equations_equal_the_dense_ones() -> None:
    prob, r, R = _joint_problem()
    state = prob.initial_state(r, R)
    res, cache, _ = prob.evaluate(state)
    system, _, g = prob.normal_equations(state, res, cache, second_order=False)
    J = prob.jacobian_state(state)
    np.testing.assert_allclose(system.dense(), J.T @ J, rtol=1e-10, atol=1e-8 * np.abs(J.T @ J).max())
    np.testing.assert_allclose(g, J.T @ res, rtol=1e-10, atol=1e-8 * np.abs(g).max())


def test_joint_fit_converges_and_returns_the_layout() -> None:
    prob, r, R = _joint_problem()
    solution = solve(prob, r, R)
    assert solution.output.converged
    assert solution.jacobian.shape == (len(solution.residuals), prob.n_params)
    assert set(solution.layout.views["lateral"]) == {"c_c", "c_r", "o_x", "o_y", "o_z", "psi"}
    assert (solution.layout.position >= 0).all()  # no exact boundary: every vertebra is free
    # stationary: the gradient Jᵀρ vanishes at the optimum (relative to its size at the start)
    g0 = prob.jacobian(r, R).T @ prob.residuals(r, R)
    assert np.linalg.norm(solution.jacobian.T @ solution.residuals) < 1e-5 * np.linalg.norm(g0)
