"""The solver loop: damped Newton (Levenberg–Marquardt) on the manifold, bordered band solves.

Each iteration solves (H + λD) h = −Jᵀρ (``banded.solve_bordered``). The first iteration uses the
Gauss–Newton H = JᵀJ (at the initial configuration the large residuals make the second-order terms
misleading); later ones add the rod's and observations' second-order terms Σ_k ρ_k ∇²ρ_k over the
vertebrae (the exact Hessian of E/2 in the chart δ ↦ (r + δr, R exp(hat δθ)) when the cameras are
fixed; their rows stay Gauss–Newton), falling back to Gauss–Newton at the same λ when its step does
not lower E. When that matrix is not positive definite at λ (negative curvature: a saddle or a ridge
of E nearby), two steps are tried and the one giving the lower E is taken: Gauss–Newton's at λ and
Newton's at the least damping λ' = max(10λ, SHIFT_MIN)·10^k that makes it definite. Gauss–Newton
alone cannot see negative curvature: from near a weak saddle its steps grow by a few per cent per
iteration (100 iterations were not enough on AASCE radiographs, docs/accuracy.md), and from a point
with a near-zero gradient it stops there, "converged" on the saddle. D is the running maximum of
diag(JᵀJ); λ starts at 1e-8 and follows Nielsen's rule (× max(0.1, 1 − (2ϱ − 1)³) on success, × 2,
4, 8, … on failure, from at least LAMBDA_MIN = 2.2e-16, machine epsilon), with ϱ the ratio of actual
to predicted decrease at the damping of the step taken. A trial step is accepted when it lowers E.

Convergence (with λ ≤ 1e-3, so that the step is not a damped one):
  * the step moves every position by ≤ XTOL_MM = 1e-6 mm, every rotation by ≤ XTOL_RAD = 1e-8 rad
    and every camera parameter by ≤ XTOL_CAMERA = 1e-9 (relative to max(1, |value|)), or
  * its predicted decrease of E (the Newton decrement) is ≤ FTOL·E + ETOL with FTOL = 1e-10 and
    ETOL = 1e-12 N·mm, i.e. what is left is at the level of rounding;
that last step is applied when it lowers E. Also converged: an accepted step that is within the step
tolerances and lowered E by ≤ FTOL·E + ETOL. ``iterations`` counts accepted steps; reaching
``max_iterations`` of them (``MAX_ITERATIONS``), or λ > 1e12 without a decrease (non-finite data),
ends the search unconverged.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from .banded import KD, BorderedSystem, band_to_dense, solve_bordered
from .problem import RegistrationProblem
from .rod_rows import RodCache
from .types import FitOutput, FloatArray, PointRows, Solution, State

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
LAMBDA_MIN = float(np.finfo(float).eps)
"""Least damping a rejected step is retried from (then × ν): machine epsilon, 2.2e-16, below which λD
is under the rounding unit of D, the largest diagonal of JᵀJ met so far, and a retry changes the step
little or not at all. Without it a damping decayed to 0.0 stayed there: on a Gauss–Newton crawl whose
gain ratio ϱ stays near 2 every accepted step divides λ by 10 (``LAMBDA_DOWN``), and 1e-8 underflows to
0.0 after some 320 steps (seen on case (g) film pairs with SID 540 mm and landmark noise twice the
stated SD); a step rejected at 0.0 was retried at 0·ν = 0, the same step, until ν overflowed to ∞ after
1023 doublings and λ = 0·∞ = NaN ended the search unconverged, as if λ had passed ``LAMBDA_MAX``."""
MAX_ITERATIONS = 500
"""Accepted steps before the search ends unconverged; ``spine bench clinic --split dev --seeds 3``
(every case, 1188 runs) needs at most 14, and 19 with the central ray 80 mm from the spine
(``clinic_films.CENTRAL_RAY_SPREAD_MM`` = 80). The limit guards against a flat valley: a perspective
film with SID and SOD whose central ray is free (no prior on it) lets the ray and the spine's place
in the film trade almost exactly, the cameras' rows carry no second-order terms, so Newton's matrix
there is indefinite at every step and the shifted step advances at a linear rate. Before the central
ray's prior the sweep's PA-only form e0 needed up to 144 steps (224 at 80 mm) and 5 of its 132 valid
payloads failed a limit of 100; 500 is twice the worst of those."""
SHIFT_MIN = 1e-12
"""Smallest damping tried to make an indefinite Newton matrix definite (then × 10 until it is)."""


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


def _damped_step(
    ab: np.ndarray, system: BorderedSystem, g: np.ndarray, lam: float, Dd: np.ndarray, nv: int
) -> np.ndarray | None:
    """The step solving (H + λD) h = −g, H = [[ab, B], [Bᵀ, C]]; None when not positive definite."""
    A = ab.copy()
    A[KD] += lam * Dd[:nv]
    C = system.C.copy()
    C.flat[:: len(C) + 1] += lam * Dd[nv:]
    return solve_bordered(A, system.B, C, g)


class _Trial:
    """A trial step h taken with damping λ: its predicted decrease, the convergence tests, the
    trial state and its evaluation (without second-order terms when the step would be final)."""

    def __init__(
        self, problem: RegistrationProblem, state: State, h: np.ndarray, lam: float, Dd: np.ndarray,
        g: np.ndarray, E: float,
    ):
        self.lam = lam
        self.small = _small(problem, state, h)
        self.predicted = float(lam * (h * Dd) @ h - h @ g)
        self.final = lam <= LAMBDA_GN and (self.small or self.predicted <= FTOL * E + ETOL)
        self.state = problem.step(state, h)
        # a final step's second-order terms are not needed (no normal equations follow)
        self.res, self.cache, self.rows = problem.evaluate(self.state, second_order=not self.final)
        self.E = float(self.res @ self.res)


class Minimum(NamedTuple):
    """Where ``minimise`` stopped: the state, the residual rows there (for ``solve``'s Jacobian) and
    the fit's report; positions, rotations and each view's camera values as a ``Solution`` names them."""

    state: State
    evaluated: tuple[FloatArray, RodCache, PointRows]
    output: FitOutput
    view_names: tuple[str, ...]

    @property
    def positions(self) -> FloatArray:
        return self.state.r

    @property
    def rotations(self) -> FloatArray:
        return self.state.R

    @property
    def cameras(self) -> dict[str, FloatArray]:
        return dict(zip(self.view_names, self.state.cameras, strict=True))


def solve(
    problem: RegistrationProblem, positions: ArrayLike, rotations: ArrayLike, max_iterations: int = MAX_ITERATIONS
) -> Solution:
    """Minimise E from (positions, rotations) and the cameras' initial values (module docstring), with
    the Jacobian at the optimum."""
    m = minimise(problem, positions, rotations, max_iterations)
    return _solution(problem, m.state, *m.evaluated, m.output)


def minimise(
    problem: RegistrationProblem, positions: ArrayLike, rotations: ArrayLike, max_iterations: int = MAX_ITERATIONS
) -> Minimum:
    """``solve``'s minimisation alone (no Jacobian at the optimum)."""
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
        diag = np.concatenate((system.ab[KD], system.C.diagonal()))
        np.maximum(D, diag, out=D)
        Dd = np.where(D > 0.0, D, 1.0)
        ab = system.ab if ab_2 is None else system.ab + ab_2
        accepted = False
        while lam <= LAMBDA_MAX:
            h = _damped_step(ab, system, g, lam, Dd, nv)
            trials = [] if h is None else [_Trial(problem, state, h, lam, Dd, g, E)]
            if h is None and ab is not system.ab:
                # Newton's matrix is not positive definite at this damping (a saddle or a ridge of E
                # nearby): its step with the least damping that makes it definite, and Gauss–Newton's
                # at this damping, both tried; the lower energy wins.
                lam_n = lam
                while h is None and lam_n < LAMBDA_MAX:
                    lam_n = max(10.0 * lam_n, SHIFT_MIN)
                    h = _damped_step(ab, system, g, lam_n, Dd, nv)
                if h is not None:
                    trials.append(_Trial(problem, state, h, lam_n, Dd, g, E))
                ab = system.ab
                h = _damped_step(ab, system, g, lam, Dd, nv)
                if h is not None:
                    trials.append(_Trial(problem, state, h, lam, Dd, g, E))
            if trials:
                best = min(trials, key=lambda t: t.E)
                if best.E < E:
                    newton = True
                    rho = (E - best.E) / best.predicted if best.predicted > 0.0 else 1.0
                    lam = best.lam * max(LAMBDA_DOWN, 1.0 - (2.0 * rho - 1.0) ** 3)
                    nu = 2.0
                    accepted = True
                    iterations += 1
                    converged = best.final or (best.small and E - best.E <= FTOL * E + ETOL)
                    state, res, cache, rows, E = best.state, best.res, best.cache, best.rows, best.E
                    break
                if trials[-1].final:
                    converged = True
                    break
            if ab is not system.ab:
                # The Newton model failed (indefinite, or its step did not lower E): retry with
                # Gauss–Newton at the same damping before damping more.
                ab = system.ab
                continue
            lam = max(lam, LAMBDA_MIN) * nu
            nu *= 2.0
        if converged or not accepted:
            break
    out = problem.output(state, res, cache, iterations, converged)
    return Minimum(state, (res, cache, rows), out, tuple(view.name for view in problem.views))


def linearise(problem: RegistrationProblem, fitted: Minimum | Solution) -> Solution:
    """``problem``'s ``Solution`` at the configuration and camera values of ``fitted``, a minimum of
    the same problem with some camera parameters held fixed: the residuals and Jacobian there, for a
    Laplace approximation that counts the held parameters' uncertainty under their priors. The rows'
    reference scales are ``problem``'s (its cameras' initial values, as in the fit)."""
    start = problem.initial_state(fitted.positions, fitted.rotations)
    values = tuple(np.array(fitted.cameras[view.name], dtype=float) for view in problem.views)
    state = State(start.r, start.R, values)
    res, cache, rows = problem.evaluate(state)
    return _solution(problem, state, res, cache, rows, fitted.output)


def _solution(
    problem: RegistrationProblem, state: State, res: FloatArray, cache: RodCache, rows: PointRows, out: FitOutput
) -> Solution:
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


__all__ = ["Minimum", "band_to_dense", "linearise", "minimise", "solve"]
