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

Also: a damping decayed to 0.0 still rises after a rejected step (``solver.LAMBDA_MIN``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from spine_engine.fit import RegistrationProblem, RodParameters, ViewData, solve
from spine_engine.projection import image_axes, project

N = 17
SEGMENT_MM = 30.0
VERSE_DEV = Path(__file__).resolve().parents[1] / "data" / "verse_dev.csv"


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
    assert pa.camera is not None
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


def test_a_step_rejected_at_zero_damping_is_damped(monkeypatch: pytest.MonkeyPatch) -> None:
    """A damping decayed to 0.0 (``solver.LAMBDA_MIN``: a Gauss–Newton crawl whose every accepted step
    divides λ by 10 underflows 1e-8 to 0.0 after some 320 steps) must still rise when a step is rejected.
    It used to stay 0·ν = 0: the same undamped step was tried 1024 times, until ν overflowed and λ = NaN
    ended the search unconverged at its start ("did not converge in 0 iterations"). The search is started
    at λ = 0 (``LAMBDA0``), the state such a crawl leaves it in; the two-view problem's first undamped step,
    from 2 mm and 0.05 rad off, is rejected there (on seeds 0–5 of its noise, every one). Cost: about
    0.02 s (0.2 s on the old code)."""
    from spine_engine.fit import solver
    from tests.engine import test_cameras

    monkeypatch.setattr(test_cameras, "RNG", np.random.default_rng(0))  # the same problem in any test order
    prob, r, R = test_cameras._joint_problem()
    reference = solve(prob, r, R).output  # from the usual λ = 1e-8
    monkeypatch.setattr(solver, "LAMBDA0", 0.0)
    out = solve(prob, r, R).output
    assert out.converged and out.iterations > 0
    # the same minimum, to the flatness of its valley (the cameras and the spine trade there, solver.
    # MAX_ITERATIONS): on seeds 0–5 the two runs stop within 9e-8·E and 1.1e-3 mm of each other; bounds
    # 1e-6·E and 0.01 mm, a hundredth of the landmarks' noise SD (1 mm, ``_joint_problem``)
    assert out.energy_fit + out.energy_internal == pytest.approx(
        reference.energy_fit + reference.energy_internal, rel=1e-6
    )
    np.testing.assert_allclose(out.positions, reference.positions, rtol=0, atol=1e-2)


@pytest.mark.parametrize("case", ["d", "g"])
def test_clinic_films_fitted_from_zero_damping(monkeypatch: pytest.MonkeyPatch, case: str) -> None:
    """``register()`` with the damping at 0.0 (as ``test_a_step_rejected_at_zero_damping_is_damped``), on
    point-source films of VerSe dev's verse074 (``benches.clinic_films``, 0.5 mm noise stated as drawn,
    seed 3): case (g), SID and SOD without the central ray, used to end FitFailed "did not converge in 0
    iterations"; case (d), geometry unknown, was refused ``landmark_sd_contradicted`` for landmarks that fit
    the spine to 0.5 mm, since the check reads the residuals where the search stopped (its start). Both
    now fit as from λ = 1e-8. Cost: about 0.02 s per case (0.2 s for the first, importing the benches)."""
    from benches.clinic import truths_of_csv
    from benches.clinic_films import CASES, build_payload, simulate_series
    from spine_engine import register
    from spine_engine.fit import solver

    truth = next(t for t in truths_of_csv(VERSE_DEV) if t.spine_id == "verse074")
    payload = build_payload(simulate_series(truth, 0.5, 3), CASES[case]).model_dump(mode="json", exclude_none=True)
    reference = register(payload)
    monkeypatch.setattr(solver, "LAMBDA0", 0.0)
    result = register(payload)
    assert result["fit"]["converged"]
    # the same fit: the two runs' vertebrae lie within 2.3e-5 mm (d) and 2.6e-6 mm (g) of each other; bound
    # 1e-3 mm, 1/500 of the stated landmark SD (0.5 mm)
    np.testing.assert_allclose(
        [v["position"] for v in result["vertebrae"]], [v["position"] for v in reference["vertebrae"]], rtol=0, atol=1e-3
    )
