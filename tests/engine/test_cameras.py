"""Perspective and joint-projection derivatives against finite differences.

The cameras' analytic derivatives (``fit.cameras``) and the whole Jacobian of a problem whose views'
projections are estimated with the spine, every vertebra free, soft poses and camera priors
(``fit.problem``), against central differences of the residuals (step 1e-6; the bound 1e-6 relative
is far above the O(h²) truncation and rounding of that step and far below any sign or factor error).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from benches.perf import placeholder_parameters, synthetic_spine
from benches.truth import read_verse
from spine_engine.anatomy import load_profile
from spine_engine.fit import Camera, Pose, PosePrior, RegistrationProblem, ViewData, solve
from spine_engine.fit.cameras import landmark_rows_kernel, project
from spine_engine.projection import image_axes
from spine_engine.reconstruction import BEAMS, mid_plane_offset
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


@pytest.mark.parametrize("k", [0, 1, 2])
def test_landmark_rows_kernel_writes_the_projection_scaled_bit_for_bit(k: int) -> None:
    """The problem's landmark rows (``landmark_rows_kernel``) are c·(p − p̂), c·∂p/∂r and c·∂p/∂π of the
    estimated parameters, exactly as computed from ``project`` (the same floating-point operations:
    equality, not a tolerance), written from their start row and columns only."""
    camera, (e_c, e_r) = _cameras()[k]
    r = RNG.normal(0.0, 80.0, (N, 3)) + np.array([0.0, 0.0, -200.0])
    idx = np.array([0, 2, 3, 7, 16], dtype=np.intp)
    observed = RNG.normal(0.0, 100.0, (len(idx), 2))
    c, start = 0.37, 3
    free = np.flatnonzero(camera.free)
    border = np.arange(len(free)) + 1
    beam = camera.beam_direction(e_c, e_r) if camera.kind == "perspective" else np.zeros(3)
    sid, sod = (camera.sid_mm, camera.sod_mm) if camera.kind == "perspective" else (1.0, 1.0)
    rho, Jv, Jb = np.full(20, -7.0), np.full((20, 6), -7.0), np.full((20, len(free) + 2), -7.0)
    landmark_rows_kernel(r, idx, observed, c, np.array((e_c, e_r), dtype=float), camera.values, beam, float(sid),
                         float(sod), camera.kind == "perspective", free, border, rho, Jv, Jb, start)  # fmt: skip
    pr = project(camera, camera.values, r[idx], e_c, e_r, beam if camera.kind == "perspective" else None)
    rows = slice(start, start + 2 * len(idx))
    assert np.array_equal(rho[rows], (c * (pr.points - observed)).ravel())
    assert np.array_equal(Jv[rows, :3], (c * pr.d_r).reshape(-1, 3))
    assert np.array_equal(Jb[rows][:, border], (c * pr.d_params[:, :, camera.free]).reshape(2 * len(idx), -1))
    untouched = np.ones(20, dtype=bool)
    untouched[rows] = False
    assert (rho[untouched] == -7.0).all() and (Jv[untouched] == -7.0).all() and (Jv[rows, 3:] == -7.0).all()
    assert (Jb[untouched] == -7.0).all() and (Jb[rows][:, [0, len(free) + 1]] == -7.0).all()


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
              PosePrior(N - 1, Pose(truth_r[-1], turned), 2.0, np.array([0.1, 0.5, 0.04]))]  # fmt: skip
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


def test_depth_prior_row_is_centred_on_its_mean() -> None:
    """The depth row √(κ/2)(b·(r_mid − o) − d̄)/σ_d (κ = 2 here): 0 where the mid vertebra lies d̄
    from the plane at SOD along the beam, d̄/σ_d (sign included) where it lies in that plane."""
    truth_r, truth_R = synthetic_spine(cobb_deg=20.0, twist_deg=0.0, kyphosis_mm=30.0)
    params = placeholder_parameters(truth_r, truth_R)
    mean, sd = -16.6, 30.0
    free = np.array([False, False, True, True, True, False])  # central ray given, film not turned
    camera = Camera("perspective", np.array([180.0, 450.0, 0.0, 0.0, 0.0, 0.0]), free, sid_mm=1800.0,
                    sod_mm=1600.0, beam=BEAM_PA, depth_prior_sd_mm=sd, depth_prior_mean_mm=mean)  # fmt: skip
    points = project(camera, camera.values, truth_r, *PA).points
    view = ViewData("pa", np.arange(N), points, *PA, camera.reference_scale, np.zeros(2), 50.0, camera=camera)
    prob = RegistrationProblem(params, [view], None, None, energy_unit=2.0)
    row = prob.row_kinds.index("camera")
    assert prob.row_kinds.count("camera") == 1
    mid = truth_r[prob.depth_reference]
    for depth_of_mid, expected in ((mean, 0.0), (0.0, -mean / sd)):
        o = mid - depth_of_mid * BEAM_PA  # b·(r_mid − o) = depth_of_mid
        values = np.array([180.0, 450.0, *o, 0.0])
        state = prob.initial_state(truth_r, truth_R)
        state = state._replace(cameras=(values,))
        assert prob.evaluate(state)[0][row] == pytest.approx(expected, abs=1e-12)


def test_mid_plane_offset_of_the_default_rest_shape() -> None:
    """SOD runs to the spine's mid-plane, the depth prior holds T9: on the PA film (beam posterior →
    anterior) the default rest shape's T9, near the thoracic apex, lies nearer the source than its
    centroid, by as much as the dev spines' T9 does on average (the rest shape is their mean shape;
    tests/data/verse_dev.csv: within one SD of their offsets); on the lateral (beam along x) the
    generic spine, straight in the frontal plane, has none."""
    profile = load_profile("default")
    spines = np.array([p for _, p in read_verse(Path(__file__).resolve().parents[1] / "data" / "verse_dev.csv")])
    offsets = spines[:, N // 2] @ BEAMS["pa"] - spines.mean(axis=1) @ BEAMS["pa"]
    pa = mid_plane_offset(profile, BEAMS["pa"])
    assert pa < 0.0
    assert abs(pa - offsets.mean()) < offsets.std()
    assert mid_plane_offset(profile, BEAMS["lateral"]) == pytest.approx(0.0, abs=1e-9)
