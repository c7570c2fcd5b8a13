"""Rod registration: round trips on geometric ground truths, invariances, derivatives, subsets."""

import numpy as np
import pytest

from benches.perf import build_case, placeholder_parameters, synthetic_spine
from spine_engine.fit import RegistrationProblem, RodParameters, ViewData, fit, initial_configuration
from spine_engine.projection import image_axes, project
from spine_engine.rod import internal_energy, strains
from spine_engine.rotations import exp_so3, log_so3

RNG = np.random.default_rng(11)
N = 17
PA = ("L", "F")
LATERAL = ("A", "F")


def _truth() -> tuple[np.ndarray, np.ndarray]:
    """A scoliotic spine by geometric construction (not by the minimiser)."""
    return synthetic_spine(cobb_deg=42.0, twist_deg=18.0, kyphosis_mm=27.0, apex=0.55, origin=(3.0, -7.0, 1100.0))


def _view(name, orientation, r, levels, s=1.13, T=(180.0, 95.0), weight=10.0, noise=0.0) -> ViewData:
    e_c, e_r = image_axes(orientation)
    idx = np.asarray(levels, dtype=int)
    points = project(r[idx], e_c, e_r, s, np.asarray(T))
    if noise:
        points = points + RNG.normal(scale=noise, size=points.shape)
    return ViewData(name, idx, points, e_c, e_r, s, np.asarray(T, dtype=float), weight)


def _rotation_error(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    return np.linalg.norm(log_so3(np.swapaxes(Ra, -1, -2) @ Rb), axis=-1)


def _rigidly_moved(r: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    G = exp_so3(np.array([0.3, -0.2, 0.5]))
    return r @ G.T + np.array([50.0, -40.0, -900.0]), G @ R


def _perturbed(r: np.ndarray, R: np.ndarray, mm: float, rad: float) -> tuple[np.ndarray, np.ndarray]:
    r2, R2 = r.copy(), R.copy()
    r2[1:-1] += RNG.normal(scale=mm, size=(N - 2, 3))
    R2[1:-1] = R2[1:-1] @ exp_so3(RNG.normal(scale=rad, size=(N - 2, 3)))
    return r2, R2


def _params_from(r: np.ndarray, R: np.ndarray, alpha=(1e6, 1e6, 5e5), beta=(5e3, 5e3, 1e4)) -> RodParameters:
    ds = np.linalg.norm(np.diff(r, axis=0), axis=1) * 0.97  # rest lengths need not be the chords
    u0, v0 = strains(r, R, ds)
    return RodParameters(ds, u0, v0, np.tile(alpha, (N - 1, 1)), np.tile(beta, (N - 1, 1)))


def _assert_boundary_exact(out, r, R):
    assert np.array_equal(out.positions[0], r[0]) and np.array_equal(out.positions[-1], r[-1])
    assert np.array_equal(out.rotations[0], R[0]) and np.array_equal(out.rotations[-1], R[-1])


# ---------------------------------------------------------------- round trips


@pytest.mark.parametrize("start", ["initial", "perturbed"])
@pytest.mark.parametrize("lateral", [False, True])
def test_round_trip_recovers_the_ground_truth(start, lateral):
    r, R = _truth()
    params = _params_from(r, R)
    views = [_view("pa", PA, r, range(N))]
    if lateral:
        views.append(_view("lateral", LATERAL, r, range(N), s=1.08, T=(-40.0, 300.0)))
    top, bottom = (r[0], R[0]), (r[-1], R[-1])
    if start == "initial":
        # start from another spine's shape placed between the ends and onto the landmarks
        other_r, other_R = synthetic_spine(cobb_deg=10.0, kyphosis_mm=40.0)
        r0, R0 = initial_configuration(other_r, other_R, views, top, bottom)
        assert RegistrationProblem(params, views, top, bottom).energy(r0, R0) > 1.0
    else:
        r0, R0 = _perturbed(r, R, mm=5.0, rad=0.08)
    out = fit(params, views, top, bottom, r0, R0)
    assert out.converged
    assert np.max(np.linalg.norm(out.positions - r, axis=1)) < 1e-3
    assert np.max(_rotation_error(out.rotations, R)) < 1e-5
    _assert_boundary_exact(out, r, R)
    assert out.energy_internal < 1e-9 and out.energy_fit < 1e-9
    np.testing.assert_allclose(out.u, params.u0, atol=1e-8)


def test_round_trip_with_only_t1_and_l5_landmarks():
    # Rest strains = truth and no interior landmark: the truth is the unique zero-energy shape.
    r, R = _truth()
    params = _params_from(r, R)
    views = [_view("pa", PA, r, [0, N - 1])]
    r0, R0 = _perturbed(r, R, mm=8.0, rad=0.1)
    out = fit(params, views, (r[0], R[0]), (r[-1], R[-1]), r0, R0)
    assert out.converged
    assert np.max(np.linalg.norm(out.positions - r, axis=1)) < 1e-3
    assert np.max(_rotation_error(out.rotations, R)) < 1e-5
    assert out.residuals_mm["pa"].shape == (2,)


# ---------------------------------------------------------------- realistic fits


def _mismatched_problem(levels_pa, levels_lat=None, noise=0.0):
    truth_r, truth_R = _truth()
    rest_r, rest_R = synthetic_spine(cobb_deg=15.0, twist_deg=0.0, kyphosis_mm=35.0)
    params = placeholder_parameters(rest_r, rest_R)
    views = [_view("pa", PA, truth_r, levels_pa, noise=noise)]
    if levels_lat is not None:
        views.append(_view("lateral", LATERAL, truth_r, levels_lat, s=1.08, T=(-40.0, 300.0), noise=noise))
    top, bottom = (truth_r[0], truth_R[0]), (truth_r[-1], truth_R[-1])
    r0, R0 = initial_configuration(rest_r, rest_R, views, top, bottom)
    return params, views, top, bottom, r0, R0, truth_r, truth_R


@pytest.mark.parametrize("count", [2, 3, 5, 9, 12, 17])
def test_pa_landmark_subsets_converge(count):
    levels = sorted({int(i) for i in np.round(np.linspace(0, N - 1, count))})
    params, views, top, bottom, r0, R0, truth_r, truth_R = _mismatched_problem(levels)
    out = fit(params, views, top, bottom, r0, R0)
    assert out.converged
    assert out.iterations <= 15
    _assert_boundary_exact(out, truth_r, truth_R)
    assert out.residuals_mm["pa"].shape == (len(levels),)
    # a stationary point: the gradient of E vanishes
    prob = RegistrationProblem(params, views, top, bottom)
    g, _ = prob.gradient_and_hessian(out.positions, out.rotations)
    assert np.max(np.abs(g)) < 1e-6 * max(1.0, out.energy_fit + out.energy_internal)
    # the reported energies and residuals agree with the residual vector
    rho = prob.residuals(out.positions, out.rotations)
    assert out.energy_internal + out.energy_fit == pytest.approx(float(rho @ rho), rel=1e-12)
    e_fit = views[0].weight * np.sum(out.residuals_mm["pa"] ** 2)
    assert out.energy_fit == pytest.approx(e_fit, rel=1e-12)
    u, v = strains(out.positions, out.rotations, params.ds)
    np.testing.assert_allclose(out.u, u, atol=1e-15)
    np.testing.assert_allclose(out.v, v, atol=1e-15)
    e_int = internal_energy(u, v, params.u0, params.v0, params.alpha, params.beta, params.ds)
    assert out.energy_internal == pytest.approx(e_int, rel=1e-12)


def test_lateral_view_improves_depth():
    pa_only = _mismatched_problem(range(N))
    both = _mismatched_problem(range(N), range(N))
    errors = []
    for params, views, top, bottom, r0, R0, truth_r, _ in (pa_only, both):
        out = fit(params, views, top, bottom, r0, R0)
        assert out.converged
        errors.append(np.sqrt(np.mean((out.positions[:, 1] - truth_r[:, 1]) ** 2)))
    depth_pa, depth_both = errors
    assert depth_both < 0.5 * depth_pa, (depth_pa, depth_both)


def test_result_is_invariant_to_image_scale_and_translation():
    params, views, top, bottom, r0, R0, _, _ = _mismatched_problem(range(N), [0, 4, 8, 12, 16], noise=0.7)
    base = fit(params, views, top, bottom, r0, R0)
    factor, shift = 2.7, np.array([-130.0, 55.0])
    moved = [
        ViewData(
            v.name,
            v.indices,
            v.points * factor + shift,
            v.e_c,
            v.e_r,
            v.scale * factor,
            v.translation * factor + shift,
            v.weight,
        )
        for v in views
    ]
    rest_r, rest_R = synthetic_spine(cobb_deg=15.0, twist_deg=0.0, kyphosis_mm=35.0)
    r1, R1 = initial_configuration(rest_r, rest_R, moved, top, bottom)
    np.testing.assert_allclose(r1, r0, atol=1e-9)
    out = fit(params, moved, top, bottom, r1, R1)
    assert base.converged and out.converged
    np.testing.assert_allclose(out.positions, base.positions, atol=1e-6)
    assert np.max(_rotation_error(out.rotations, base.rotations)) < 1e-8
    for name in base.residuals_mm:
        np.testing.assert_allclose(out.residuals_mm[name], base.residuals_mm[name], atol=1e-6)


# ---------------------------------------------------------------- derivatives


def _generic_configuration():
    params, views, top, bottom, r0, R0, _, _ = _mismatched_problem(range(N), [0, 3, 7, 11, 16], noise=1.0)
    r, R = _perturbed(r0, R0, mm=3.0, rad=0.05)
    return RegistrationProblem(params, views, top, bottom), r, R


def test_jacobian_matches_central_differences():
    prob, r, R = _generic_configuration()
    J = prob.jacobian(r, R)
    assert J.shape == (prob.n_residuals, 6 * (N - 2))
    J_fd = np.empty_like(J)
    for k in range(J.shape[1]):
        h = 1e-5
        d = np.zeros(J.shape[1])
        d[k] = h
        plus = prob.residuals(*prob.retract(r, R, d))
        minus = prob.residuals(*prob.retract(r, R, -d))
        J_fd[:, k] = (plus - minus) / (2 * h)
    rel = np.linalg.norm(J - J_fd, axis=0) / np.linalg.norm(J, axis=0)
    assert rel.max() < 1e-5, rel.max()
    assert np.linalg.norm(J - J_fd) / np.linalg.norm(J) < 1e-7


def test_newton_hessian_matches_second_differences():
    prob, r, R = _generic_configuration()
    g, H = prob.gradient_and_hessian(r, R)
    _, H_gn = prob.gradient_and_hessian(r, R, second_order=False)
    J = prob.jacobian(r, R)
    rho = prob.residuals(r, R)
    np.testing.assert_allclose(g, J.T @ rho, rtol=1e-10, atol=1e-9 * np.abs(g).max())
    np.testing.assert_allclose(H_gn, J.T @ J, rtol=1e-10, atol=1e-10 * np.abs(H_gn).max())

    def energy(delta):
        res = prob.residuals(*prob.retract(r, R, delta))
        return float(res @ res)

    n = prob.n_params
    h = 1e-4
    E0 = energy(np.zeros(n))
    H_fd = np.zeros((n, n))
    cols = RNG.choice(n, 24, replace=False)
    for a in cols:
        for b in range(n):
            ea, eb = np.zeros(n), np.zeros(n)
            ea[a], eb[b] = h, h
            if a == b:
                H_fd[a, b] = (energy(ea) - 2 * E0 + energy(-ea)) / h**2
            else:
                H_fd[a, b] = (energy(ea + eb) - energy(ea - eb) - energy(eb - ea) + energy(-ea - eb)) / (4 * h**2)
    H_fd = 0.5 * H_fd[cols]
    S, S_fd = (H - H_gn)[cols], H_fd - H_gn[cols]
    assert np.linalg.norm(S) > 1e-3 * np.linalg.norm(H_gn[cols])  # the second-order part is not negligible
    assert np.linalg.norm(S - S_fd) < 1e-4 * np.linalg.norm(S)


# ---------------------------------------------------------------- initial configuration and errors


def test_initial_configuration_matches_ends_and_landmarks():
    _, views, top, bottom, r0, R0, _, _ = _mismatched_problem([0, 2, 5, 9, 13, 16], [0, 8, 16])
    assert np.array_equal(r0[0], top[0]) and np.array_equal(r0[-1], bottom[0])
    assert np.array_equal(R0[0], top[1]) and np.array_equal(R0[-1], bottom[1])
    np.testing.assert_allclose(R0 @ np.swapaxes(R0, 1, 2), np.broadcast_to(np.eye(3), R0.shape), atol=1e-12)
    pa = views[0]
    interior = (pa.indices > 0) & (pa.indices < N - 1)
    projected = project(r0[pa.indices[interior]], pa.e_c, pa.e_r, pa.scale, pa.translation)
    np.testing.assert_allclose(projected, pa.points[interior], atol=1e-3)
    # directors follow the displaced centreline: d3 stays close to the chord direction
    chords = np.diff(r0, axis=0)
    chords /= np.linalg.norm(chords, axis=1, keepdims=True)
    assert np.min(np.sum(chords * R0[:-1, :, 2], axis=1)) > np.cos(np.radians(15))


def test_pa_only_initial_configuration_keeps_rest_depth():
    truth_r, truth_R = _truth()
    rest_r, rest_R = _rigidly_moved(truth_r, truth_R)
    views = [_view("pa", PA, truth_r, range(N))]
    r0, _ = initial_configuration(rest_r, rest_R, views, (truth_r[0], truth_R[0]), (truth_r[-1], truth_R[-1]))
    blended, _ = initial_configuration(rest_r, rest_R, [], (truth_r[0], truth_R[0]), (truth_r[-1], truth_R[-1]))
    np.testing.assert_allclose(r0[:, 1], blended[:, 1], atol=1e-9)
    # a rigidly moved rest shape between its own ends is put back exactly
    np.testing.assert_allclose(blended, truth_r, atol=1e-9)


def test_benchmark_problem_converges_quickly():
    pb = build_case()
    r0, R0 = initial_configuration(pb.rest_positions, pb.rest_rotations, pb.views, pb.top, pb.bottom)
    out = fit(pb.params, pb.views, pb.top, pb.bottom, r0, R0)
    assert out.converged and out.iterations <= 8
    unconverged = fit(pb.params, pb.views, pb.top, pb.bottom, r0, R0, max_iterations=1)
    assert not unconverged.converged and unconverged.iterations == 1


def test_bad_inputs_raise_value_error():
    r, R = _truth()
    params = _params_from(r, R)
    top, bottom = (r[0], R[0]), (r[-1], R[-1])
    bad_index = ViewData("pa", np.array([0, N]), np.zeros((2, 2)), *image_axes(PA), 1.0, np.zeros(2), 1.0)
    with pytest.raises(ValueError, match="indices"):
        RegistrationProblem(params, [bad_index], top, bottom)
    with pytest.raises(ValueError, match="shape"):
        short = RodParameters(params.ds, params.u0[:-1], params.v0, params.alpha, params.beta)
        RegistrationProblem(short, [], top, bottom)
    with pytest.raises(ValueError, match="expected positions"):
        fit(params, [], top, bottom, r[:-1], R[:-1])
    with pytest.raises(ValueError, match="distinct"):
        RegistrationProblem(params, [_view("pa", PA, r, [0]), _view("pa", PA, r, [1])], top, bottom)
