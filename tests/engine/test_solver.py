"""The solver near a saddle of E: a compressed rod that must buckle out of the film's plane.

A straight rod whose rest length is 1.75 % longer than the span between its fixed ends is loaded
past its buckling load: the straight shape is a saddle of the energy and the rod's minima are bowed
(Euler buckling; Timoshenko & Gere, Theory of Elastic Stability, 2nd ed., 1961, ch. 2). PA landmarks
hold every vertebra's left–right and vertical position, so the bow goes into the depth, which the
film does not see. Just past the buckling load the negative curvature of E along the bow is small
against the Gauss–Newton curvature (the geometry of the AASCE radiographs that did not converge,
docs/accuracy.md): Gauss–Newton's steps away from the straight shape then grow by a few per cent per
iteration. The solver used to fall back to those steps whenever Newton's matrix was indefinite, and
did not converge in 100 iterations from a bow of 0.01 mm, or stopped on the saddle from 0.001 mm.
"""

from __future__ import annotations

import numpy as np
import pytest

from spine_engine.fit import RegistrationProblem, RodParameters, ViewData, solve
from spine_engine.projection import image_axes, project

N = 17
SEGMENT_MM = 30.0


def _compressed_rod(overlength: float) -> tuple[RegistrationProblem, np.ndarray, np.ndarray]:
    """A straight vertical rod (d1 = +x, d2 = −y, d3 = −z, caudal), rest lengths ``overlength`` × its
    segments, no rest curvature, ends fixed, every vertebra landmarked on a PA film."""
    r = np.stack([np.zeros(N), np.zeros(N), -SEGMENT_MM * np.arange(N)], axis=1)
    R = np.tile(np.diag([1.0, -1.0, -1.0]), (N, 1, 1))
    params = RodParameters(
        np.full(N - 1, SEGMENT_MM * overlength),
        np.zeros((N - 1, 3)),
        np.tile([0.0, 0.0, 1.0], (N - 1, 1)),
        np.tile([1e6, 1e6, 5e5], (N - 1, 1)),
        np.tile([5e3, 5e3, 1e4], (N - 1, 1)),
    )
    e_c, e_r = image_axes(("L", "F"))
    T = np.array([100.0, 50.0])
    view = ViewData("pa", np.arange(N), project(r, e_c, e_r, 1.1, T), e_c, e_r, 1.1, T, 10.0)
    return RegistrationProblem(params, [view], (r[0], R[0]), (r[-1], R[-1])), r, R


@pytest.mark.parametrize("bow_mm", [1e-3, 1e-2])
def test_a_rod_started_near_its_saddle_converges_to_a_buckled_minimum(bow_mm):
    problem, r, R = _compressed_rod(1.0175)
    start = r.copy()
    start[:, 1] = bow_mm * np.sin(np.pi * np.arange(N) / (N - 1))
    out = solve(problem, start, R).output
    assert out.converged and out.iterations < 60
    depth = np.abs(out.positions[:, 1]).max()
    assert depth > 5.0  # bowed into the depth, not left straight
    energy = out.energy_fit + out.energy_internal
    assert energy < problem.energy(r, R) - 1.0
    # a minimum: the Newton matrix at the optimum is positive definite (the straight rod's is not)
    _, H = problem.gradient_and_hessian(out.positions, out.rotations)
    assert np.linalg.eigvalsh(H).min() > 0.0
    _, H_straight = problem.gradient_and_hessian(r, R)
    assert np.linalg.eigvalsh(H_straight).min() < 0.0


def test_linearise_at_the_optimum_is_the_solvers_solution() -> None:
    """``linearise`` of a problem at its own solution gives ``solve``'s residuals, Jacobian and layout;
    at the solution of the same problem with the PA's scale held, the rows of the free problem there
    (the scale's prior row included)."""
    import dataclasses

    from spine_engine.fit import linearise, solve
    from tests.engine.test_cameras import _joint_problem

    prob, r, R = _joint_problem()
    solution = solve(prob, r, R)
    same = linearise(prob, solution)
    np.testing.assert_allclose(same.residuals, solution.residuals, rtol=0, atol=1e-12)
    np.testing.assert_allclose(same.jacobian, solution.jacobian, rtol=0, atol=1e-12 * np.abs(solution.jacobian).max())
    np.testing.assert_allclose(same.x, solution.x, rtol=0, atol=0)
    assert same.layout == solution.layout and same.row_kinds == solution.row_kinds
    pa = prob.views[0]
    held_free = pa.camera.free.copy()
    held_free[0] = False
    held = dataclasses.replace(pa, camera=dataclasses.replace(pa.camera, free=held_free))
    pinned = type(prob)(prob.params, [held, *prob.views[1:]], None, None, pose_priors=prob.pose_priors,
                        energy_unit=prob.energy_unit)  # fmt: skip
    fitted = solve(pinned, r, R)
    free = linearise(prob, fitted)
    assert free.jacobian.shape == (len(solution.residuals), prob.n_params)
    assert fitted.jacobian.shape[1] == prob.n_params - 1
    s_row = next(k for k, kind in enumerate(free.row_kinds) if kind == "camera")
    assert free.jacobian[s_row].any()  # the scale's prior row, absent from the held problem's columns
