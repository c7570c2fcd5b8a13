"""The solver loop: damped Newton (Levenberg–Marquardt) on the manifold, bordered band solves.

Each iteration solves (H + λD) h = −Jᵀρ (``banded.solve_bordered``). The first iteration uses the
Gauss–Newton H = JᵀJ (at the initial configuration the large residuals make the second-order terms
misleading); later ones add the rod's and observations' second-order terms Σ_k ρ_k ∇²ρ_k over the
vertebrae (the exact Hessian of E/2 in the chart δ ↦ (r + δr, R exp(hat δθ)) when the cameras are
fixed; their rows stay Gauss–Newton), falling back to Gauss–Newton at the same λ when that matrix
is not positive definite or its step does not lower E. D is the running maximum of diag(JᵀJ); λ
starts at 1e-8 and follows Nielsen's rule (× max(0.1, 1 − (2ϱ − 1)³) on success, × 2, 4, 8, … on
failure), with ϱ the ratio of actual to predicted decrease. A trial step is accepted when it lowers E.

Convergence (with λ ≤ 1e-3, so that the step is not a damped one):
  * the step moves every position by ≤ XTOL_MM = 1e-6 mm, every rotation by ≤ XTOL_RAD = 1e-8 rad
    and every camera parameter by ≤ XTOL_CAMERA = 1e-9 (relative to max(1, |value|)), or
  * its predicted decrease of E (the Newton decrement) is ≤ FTOL·E + ETOL with FTOL = 1e-10 and
    ETOL = 1e-12 N·mm, i.e. what is left is at the level of rounding;
that last step is applied when it lowers E. Also converged: an accepted step that is within the step
tolerances and lowered E by ≤ FTOL·E + ETOL. ``iterations`` counts accepted steps; reaching
``max_iterations`` of them, or λ > 1e12 without a decrease (non-finite data), ends the search
unconverged.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from .banded import KD, band_to_dense, solve_bordered
from .problem import RegistrationProblem, State
from .types import Solution

XTOL_MM = 1e-6
"""Convergence: a step moving no position by more than this (mm) ..."""
XTOL_RAD = 1e-8
"""... and no rotation by more than this (rad) ..."""
XTOL_CAMERA = 1e-9
"""... and no camera parameter by more than this times max(1, |value|) ends the search."""
FTOL = 1e-10
"""Convergence: a step predicted to lower E by at most FTOL·E + ETOL ends the search."""
ETOL = 1e-12
"""Convergence: absolute part of that energy tolerance, N·mm (for E near zero)."""
LAMBDA_DOWN = 0.1
"""Largest decrease of the damping after a step of ideal gain ratio (Nielsen's rule has 1/3)."""
LAMBDA0 = 1e-8
"""Initial Marquardt damping, relative to the diagonal of JᵀJ."""
LAMBDA_GN = 1e-3
"""Damping below which a step is a Gauss–Newton step, for the stationarity test."""
LAMBDA_MAX = 1e12
"""Damping at which the search gives up on decreasing E further."""


def _small(problem: RegistrationProblem, state: State, h: np.ndarray) -> bool:
    hm = np.abs(h[: problem.n_vertebra_params].reshape(problem.m, 6))
    if hm.size and (hm[:, :3].max() > XTOL_MM or hm[:, 3:].max() > XTOL_RAD):
        return False
    if problem.n_border:
        values = np.concatenate(
            [v[cam.free] for cam, v in zip(problem.cameras, state.cameras, strict=True)]
        )
        if np.any(np.abs(h[problem.n_vertebra_params :]) > XTOL_CAMERA * np.maximum(1.0, np.abs(values))):
            return False
    return True


def solve(
    problem: RegistrationProblem, positions: ArrayLike, rotations: ArrayLike, max_iterations: int = 100
) -> Solution:
    """Minimise E from (positions, rotations) and the cameras' initial values (module docstring)."""
    state = problem.initial_state(positions, rotations)
    res, cache, rows = problem.evaluate(state)
    E = float(res @ res)
    lam = LAMBDA0
    nu = 2.0
    nv = problem.n_vertebra_params
    D = np.zeros(problem.n_params)
    iterations = 0
    converged = False
    newton = False
    while iterations < max_iterations:
        system, ab_2, g = problem.normal_equations(state, res, cache, second_order=newton, rows=rows)
        diag = np.concatenate((system.ab[KD], np.diag(system.C)))
        np.maximum(D, diag, out=D)
        Dd = np.where(D > 0.0, D, 1.0)
        ab = system.ab if ab_2 is None else system.ab + ab_2
        accepted = False
        while lam <= LAMBDA_MAX:
            A = ab.copy()
            A[KD] += lam * Dd[:nv]
            C = system.C + np.diag(lam * Dd[nv:])
            h = solve_bordered(A, system.B, C, g)
            if h is not None:
                small = _small(problem, state, h)
                predicted = float(lam * (h * Dd) @ h - h @ g)
                final = lam <= LAMBDA_GN and (small or predicted <= FTOL * E + ETOL)
                trial = problem.step(state, h)
                # a final step's second-order terms are not needed (no normal equations follow)
                res_t, cache_t, rows_t = problem.evaluate(trial, second_order=not final)
                E_t = float(res_t @ res_t)
                if E_t < E:
                    newton = True
                    rho = (E - E_t) / predicted if predicted > 0.0 else 1.0
                    lam *= max(LAMBDA_DOWN, 1.0 - (2.0 * rho - 1.0) ** 3)
                    nu = 2.0
                    accepted = True
                    iterations += 1
                    converged = final or (small and E - E_t <= FTOL * E + ETOL)
                    state, res, cache, rows, E = trial, res_t, cache_t, rows_t, E_t
                    break
                if final:
                    converged = True
                    break
            if ab is not system.ab:
                # The Newton model failed (indefinite, or its step did not lower E): retry with
                # Gauss–Newton at the same damping before damping more.
                ab = system.ab
                continue
            lam *= nu
            nu *= 2.0
        if converged or not accepted:
            break
    out = problem.output(state, res, cache, iterations, converged)
    J = problem.jacobian_state(state, (cache, rows))
    x = np.zeros(problem.n_params)
    for cam, values, cols in zip(problem.cameras, state.cameras, problem._cam_cols, strict=True):
        x[cols] = values[cam.free]
    return Solution(
        positions=state.r,
        rotations=state.R,
        cameras={view.name: values for view, values in zip(problem.views, state.cameras, strict=True)},
        x=x,
        residuals=res,
        jacobian=J,
        weights=np.ones(len(res)),
        row_kinds=problem.row_kinds,
        layout=problem.layout,
        energy_unit=problem.energy_unit,
        output=out,
    )


__all__ = ["band_to_dense", "solve"]
