"""The fit: registration of the discrete Cosserat rod to radiograph landmarks (Li et al., CAIP 2009).

Kept apart as PyElastica keeps its kernels from its time-stepper:

| module | holds |
| --- | --- |
| ``types`` | ``FloatArray``, ``Pose`` and the pose helper ``as_pose``, ``ViewData``, ``Camera``, ``Solution``… |
| ``rod_rows`` | the rod's residual rows (strains), Jacobian and second-order terms |
| ``cameras`` | weak-perspective and perspective projection with analytic derivatives |
| ``pose_rows`` | the offset-point and tilt rows (observations that touch one vertebra's pose) |
| ``problem`` | ``RegistrationProblem``: all rows, the parameter layout, normal equations |
| ``banded`` | LAPACK band storage and the bordered (arrow) solve |
| ``solver`` | the Levenberg–Marquardt / Newton loop (``minimise``); the ``Solution`` (``solve``, ``linearise``) |
| ``initial`` | the initial configuration |

``fit(...)`` registers with T1 and L5 exact (the paper); ``fit_free(...)`` with every vertebra free.
"""

from __future__ import annotations

from collections.abc import Sequence

from numpy.typing import ArrayLike

from .initial import initial_configuration
from .problem import RegistrationProblem
from .solver import MAX_ITERATIONS, Minimum, linearise, minimise, solve
from .types import (
    Camera,
    FitOutput,
    FloatArray,
    ParameterLayout,
    Pose,
    PosePrior,
    RodParameters,
    Solution,
    State,
    ViewData,
    as_pose,
    nearest_rotation,
    weak_camera,
)


def fit(
    params: RodParameters,
    views: Sequence[ViewData],
    top: Pose | tuple[ArrayLike, ArrayLike],
    bottom: Pose | tuple[ArrayLike, ArrayLike],
    init_positions: ArrayLike,
    init_rotations: ArrayLike,
    max_iterations: int = MAX_ITERATIONS,
) -> FitOutput:
    """Register the rod to the landmarks of ``views`` with T1 = ``top`` and L5 = ``bottom`` fixed exactly.

    The output's vertebrae 0 and N−1 are bit-for-bit ``top`` and ``bottom``."""
    problem = RegistrationProblem(params, views, top, bottom)
    return solve(problem, init_positions, init_rotations, max_iterations).output


__all__ = [
    "Camera",
    "FitOutput",
    "FloatArray",
    "Minimum",
    "ParameterLayout",
    "Pose",
    "PosePrior",
    "RegistrationProblem",
    "RodParameters",
    "Solution",
    "State",
    "ViewData",
    "as_pose",
    "fit",
    "initial_configuration",
    "linearise",
    "minimise",
    "nearest_rotation",
    "solve",
    "weak_camera",
]
